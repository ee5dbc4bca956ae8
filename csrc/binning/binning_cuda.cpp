// Torch glue of the CUDA tile binning (built only with CUDA on; the steps in binning_cuda.h).
// Every buffer comes from torch's caching allocator; the one host synchronisation reads the
// total number of intersections, which sizes the outputs.
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <torch/library.h>

#include <cstdlib>

#include "binning.h"
#include "binning_cuda.h"
#include "common/torch_checks.h"

namespace tiger {

namespace {
#define TIGER_CUDA_OK(expr)                                                                   \
  do {                                                                                        \
    const cudaError_t err_ = (expr);                                                          \
    TORCH_CHECK(err_ == cudaSuccess, "tiger.bin_gaussians: CUDA error: ", cudaGetErrorString(err_)); \
  } while (0)

at::Tensor temp_buffer(size_t bytes, const at::Tensor& like) {
  return at::empty({int64_t(bytes) + 1}, like.options().dtype(at::kByte));
}

bool serial_binning() {
  const char* v = std::getenv("TIGER_BIN_SERIAL");
  return v != nullptr && v[0] == '1';
}

// Keys a block sorts in shared memory; longer tile lists are merged from sorted runs of this
// length. TIGER_BIN_SORT_KEYS (a power of two in [2, kBinSortKeysMax]) lowers it: tests run the
// merge path on small scenes with it.
int sort_keys() {
  const char* v = std::getenv("TIGER_BIN_SORT_KEYS");
  if (v == nullptr || v[0] == 0) return kBinSortKeysMax;
  const long long k = std::atoll(v);
  TORCH_CHECK(k >= 2 && k <= kBinSortKeysMax && (k & (k - 1)) == 0,
              "tiger.bin_gaussians: TIGER_BIN_SORT_KEYS must be a power of two in [2, ",
              kBinSortKeysMax, "], got '", v, "'");
  return int(k);
}

template <typename T>
T* ptr_of(at::Tensor& t) {
  return reinterpret_cast<T*>(t.data_ptr());
}
}  // namespace

std::tuple<at::Tensor, at::Tensor> bin_gaussians_cuda(const at::Tensor& means2d,
                                                      const at::Tensor& conics,
                                                      const at::Tensor& opacities,
                                                      const at::Tensor& depths,
                                                      const at::Tensor& radii, int64_t width,
                                                      int64_t height, int64_t tile_size,
                                                      double alpha_threshold) {
  check_binning_inputs("tiger.bin_gaussians", means2d, conics, opacities, depths, radii, width,
                       height, tile_size);
  const c10::cuda::CUDAGuard guard(means2d.device());
  cudaStream_t stream = c10::cuda::getCurrentCUDAStream().stream();
  const int64_t n = means2d.size(0);
  const int ts = int(tile_size);
  BinGeometry g{int(width), int(height), ts, int((width + ts - 1) / ts), int((height + ts - 1) / ts)};
  const int64_t n_tiles = int64_t(g.tiles_x) * g.tiles_y;
  TORCH_CHECK(n_tiles < (int64_t(1) << 31), "tiger.bin_gaussians: too many tiles (", n_tiles, ")");
  TORCH_CHECK(n < (int64_t(1) << 31), "tiger.bin_gaussians: at most 2^31-1 Gaussians, got ", n);
  const int keys_in_shared = sort_keys();
  const auto int_opts = means2d.options().dtype(at::kInt), long_opts = means2d.options().dtype(at::kLong);
  auto tile_offsets = at::empty({n_tiles + 1}, long_opts);
  if (n == 0) {
    tile_offsets.zero_();
    return {tile_offsets, at::empty({0}, int_opts)};
  }
  const auto m2 = means2d.contiguous(), cn = conics.contiguous(), op = opacities.contiguous(),
             dp = depths.contiguous(), r = radii.contiguous();
  // One zeroed buffer: the chunk counter, the tile counts, and a last zero (the scan runs over
  // tiles + 1 entries, so tile_offsets[tiles] is the total).
  auto state = at::zeros({n_tiles + 2}, long_opts);
  auto* counter = reinterpret_cast<unsigned long long*>(state.data_ptr<int64_t>());
  unsigned long long* tile_counts = counter + 1;
  // Large Gaussians are listed and walked in chunks by warps (load balance); TIGER_BIN_SERIAL=1
  // walks every Gaussian by one thread (comparisons).
  at::Tensor listed_ids, chunk_base;
  BinChunks chunks{nullptr, nullptr, counter};
  if (!serial_binning()) {
    listed_ids = at::empty({n}, int_opts);
    chunk_base = at::empty({n}, long_opts);
    chunks.ids = listed_ids.data_ptr<int32_t>();
    chunks.chunk_base = chunk_base.data_ptr<int64_t>();
  }
  const BinChunks* list = listed_ids.defined() ? &chunks : nullptr;
  at::Tensor depth_rank;
  if (means2d.scalar_type() == at::kDouble) {  // float64 depths sort by their rank
    depth_rank = at::empty({n}, int_opts);
    auto k0 = at::empty({n}, long_opts), k1 = at::empty({n}, long_opts);
    auto i0 = at::empty({n}, int_opts), i1 = at::empty({n}, int_opts);
    size_t bytes = 0;
    auto run = [&](void* temp) {
      TIGER_CUDA_OK(bin_depth_rank_cuda(temp, bytes, dp.data_ptr<double>(), n, ptr_of<uint64_t>(k0),
                                        ptr_of<uint64_t>(k1), i0.data_ptr<int32_t>(),
                                        i1.data_ptr<int32_t>(), depth_rank.data_ptr<int32_t>(),
                                        stream));
    };
    run(nullptr);
    auto temp = temp_buffer(bytes, means2d);
    run(temp.data_ptr());
  }
  at::Tensor keys;
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "bin_gaussians_cuda", [&] {
    using T = scalar_t;
    const BinInputs<T> in{m2.data_ptr<T>(), cn.data_ptr<T>(), op.data_ptr<T>(), dp.data_ptr<T>(),
                          r.data_ptr<int32_t>(),
                          depth_rank.defined() ? depth_rank.data_ptr<int32_t>() : nullptr, n,
                          T(alpha_threshold)};
    TIGER_CUDA_OK(bin_tiles_cuda<T>(in, g, false, tile_counts, nullptr, nullptr, list, stream));
    size_t bytes = 0;
    TIGER_CUDA_OK(bin_offsets_cuda(nullptr, bytes, tile_counts, tile_offsets.data_ptr<int64_t>(),
                                   n_tiles, stream));
    auto temp = temp_buffer(bytes, means2d);
    TIGER_CUDA_OK(bin_offsets_cuda(temp.data_ptr(), bytes, tile_counts,
                                   tile_offsets.data_ptr<int64_t>(), n_tiles, stream));
    const int64_t m = tile_offsets[n_tiles].item<int64_t>();  // the one host synchronisation
    keys = at::empty({m}, long_opts);
    TIGER_CUDA_OK(bin_tiles_cuda<T>(in, g, true, tile_counts, tile_offsets.data_ptr<int64_t>(),
                                    ptr_of<uint64_t>(keys), list, stream));
  });
  const int64_t m = keys.numel();
  auto gaussian_ids = at::empty({m}, int_opts);
  if (m > 0) {
    // scratch of the lists longer than keys_in_shared (the merge passes)
    auto keys_alt = at::empty({m}, long_opts);
    TIGER_CUDA_OK(bin_sort_tiles_cuda(tile_offsets.data_ptr<int64_t>(), n_tiles,
                                      ptr_of<uint64_t>(keys), ptr_of<uint64_t>(keys_alt),
                                      keys_in_shared, gaussian_ids.data_ptr<int32_t>(), stream));
  }
  return {tile_offsets, gaussian_ids};
}

TORCH_LIBRARY_IMPL(tiger, CUDA, m) { m.impl("bin_gaussians", &bin_gaussians_cuda); }

}  // namespace tiger

// Torch glue of the CUDA tile binning (built only with CUDA on; the two paths and their steps
// in binning_cuda.h).
// Every buffer comes from torch's caching allocator; the one host synchronisation reads the
// total number of intersections, which sizes the outputs.
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <torch/library.h>

#include "binning.h"
#include "binning_cuda.h"
#include "common/cuda_zeros.h"
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

// The kernel choices of one call (binning.h; checked by check_binning_choices).
struct BinChoices {
  int block_sort_keys, warp_sort_keys;
  int64_t giant_tiles;
  bool serial;  // every Gaussian walked by one thread (the former walk, for comparisons)
};

template <typename T>
T* ptr_of(at::Tensor& t) {
  return reinterpret_cast<T*>(t.data_ptr());
}

// The Gaussians' stable depth order (*order points into i0 or i1, [n] int32 each).
template <typename T>
void depth_order(const BinInputs<T>& in, at::Tensor& i0, at::Tensor& i1, int32_t** order,
                 const at::Tensor& like, cudaStream_t stream) {
  using K = DepthKey<T>;
  const int64_t n = in.n;
  const auto key_opts = like.options().dtype(sizeof(K) == 4 ? at::kInt : at::kLong);
  auto k0 = at::empty({n}, key_opts), k1 = at::empty({n}, key_opts);
  size_t bytes = 0;
  auto run = [&](void* temp) {
    TIGER_CUDA_OK(bin_depth_order_cuda<T>(temp, bytes, in.depths, n, ptr_of<K>(k0), ptr_of<K>(k1),
                                          i0.data_ptr<int32_t>(), i1.data_ptr<int32_t>(), order,
                                          stream));
  };
  run(nullptr);
  auto temp = temp_buffer(bytes, like);
  run(temp.data_ptr());
}

// Per-tile path (binning_cuda.h): fills tile_offsets, returns the Gaussian ids.
template <typename T>
at::Tensor bin_per_tile(BinInputs<T> in, const BinGeometry& g, int64_t n_tiles,
                        at::Tensor& tile_offsets, const BinChoices& choice, const at::Tensor& like,
                        cudaStream_t stream) {
  const int64_t n = in.n;
  const auto int_opts = like.options().dtype(at::kInt), long_opts = like.options().dtype(at::kLong);
  // One zeroed buffer: the chunk counter, the long-list counter of the sort, the tile counts,
  // and a last zero (the scan runs over tiles + 1 entries, so tile_offsets[tiles] is the total).
  auto state = cuda_zeros({n_tiles + 3}, long_opts);
  auto* counter = reinterpret_cast<unsigned long long*>(state.data_ptr<int64_t>());
  unsigned long long* n_long_lists = counter + 1;
  unsigned long long* tile_counts = counter + 2;
  // Large Gaussians are listed and walked in chunks by warps (load balance); choice.serial
  // walks every Gaussian by one thread (comparisons).
  at::Tensor listed_ids, chunk_base;
  BinChunks chunks{nullptr, nullptr, counter};
  if (!choice.serial) {
    listed_ids = at::empty({n}, int_opts);
    chunk_base = at::empty({n}, long_opts);
    chunks.ids = listed_ids.data_ptr<int32_t>();
    chunks.chunk_base = chunk_base.data_ptr<int64_t>();
  }
  const BinChunks* list = listed_ids.defined() ? &chunks : nullptr;
  at::Tensor depth_rank;
  if constexpr (sizeof(T) == 8) {  // float64 depths sort by their rank
    auto i0 = at::empty({n}, int_opts), i1 = at::empty({n}, int_opts);
    int32_t* order = nullptr;
    depth_order(in, i0, i1, &order, like, stream);
    depth_rank = at::empty({n}, int_opts);
    TIGER_CUDA_OK(bin_order_counts_cuda(order, nullptr, n, nullptr,
                                        depth_rank.data_ptr<int32_t>(), stream));
    in.depth_rank = depth_rank.data_ptr<int32_t>();
  }
  int64_t* offsets = tile_offsets.data_ptr<int64_t>();
  TIGER_CUDA_OK(bin_tiles_cuda<T>(in, g, false, tile_counts, nullptr, nullptr, list, stream));
  size_t bytes = 0;
  TIGER_CUDA_OK(bin_offsets_cuda(nullptr, bytes, tile_counts, offsets, n_tiles, stream));
  auto temp = temp_buffer(bytes, like);
  TIGER_CUDA_OK(bin_offsets_cuda(temp.data_ptr(), bytes, tile_counts, offsets, n_tiles, stream));
  const int64_t m = tile_offsets[n_tiles].item<int64_t>();  // the one host synchronisation
  auto keys = at::empty({m}, long_opts);
  TIGER_CUDA_OK(bin_tiles_cuda<T>(in, g, true, tile_counts, offsets, ptr_of<uint64_t>(keys), list,
                                  stream));
  auto gaussian_ids = at::empty({m}, int_opts);
  if (m > 0) {
    auto keys_alt = at::empty({m}, long_opts);  // scratch of the lists merged from runs
    auto long_lists = at::empty({n_tiles}, int_opts);
    TIGER_CUDA_OK(bin_sort_tiles_cuda(offsets, n_tiles, ptr_of<uint64_t>(keys),
                                      ptr_of<uint64_t>(keys_alt), choice.block_sort_keys,
                                      choice.warp_sort_keys,
                                      gaussian_ids.data_ptr<int32_t>(),
                                      long_lists.data_ptr<int32_t>(), n_long_lists, stream));
  }
  return gaussian_ids;
}

// Global-sort path (binning_cuda.h): fills tile_offsets, returns the Gaussian ids.
template <typename T>
at::Tensor bin_global(const BinInputs<T>& in, const BinGeometry& g, int64_t n_tiles,
                      at::Tensor& tile_offsets, const BinChoices& choice, const at::Tensor& like,
                      cudaStream_t stream) {
  const int64_t n = in.n;
  const auto int_opts = like.options().dtype(at::kInt), long_opts = like.options().dtype(at::kLong);
  auto counts = at::empty({n}, long_opts);
  // Small Gaussians are counted one per thread; the large ones, listed by that kernel, by one
  // warp or block each (load balance). choice.serial: every Gaussian by one thread.
  at::Tensor large_ids, large_counters;
  if (!choice.serial) {
    large_ids = at::empty({n}, int_opts);
    large_counters = at::empty({2}, int_opts);
  }
  int32_t* large = large_ids.defined() ? large_ids.data_ptr<int32_t>() : nullptr;
  auto* large_n = large_counters.defined()
                      ? reinterpret_cast<unsigned int*>(large_counters.data_ptr<int32_t>())
                      : nullptr;
  TIGER_CUDA_OK(bin_count_cuda<T>(in, g, choice.giant_tiles, counts.data_ptr<int64_t>(), large, large_n,
                                  stream));
  // the depth order's id buffers (the order ends in one of them) live until the emit
  auto i0 = at::empty({n}, int_opts), i1 = at::empty({n}, int_opts);
  int32_t* order = nullptr;
  depth_order(in, i0, i1, &order, like, stream);
  // the counts in depth order, each Gaussian's rank in it, their scan (segment ends)
  auto rank = at::empty({n}, int_opts);
  auto offsets = at::empty({n}, long_opts);
  {
    auto ordered = at::empty({n}, long_opts);
    TIGER_CUDA_OK(bin_order_counts_cuda(order, counts.data_ptr<int64_t>(), n,
                                        ordered.data_ptr<int64_t>(), rank.data_ptr<int32_t>(),
                                        stream));
    size_t bytes = 0;
    TIGER_CUDA_OK(bin_scan_cuda(nullptr, bytes, ordered.data_ptr<int64_t>(),
                                offsets.data_ptr<int64_t>(), n, stream));
    auto temp = temp_buffer(bytes, like);
    TIGER_CUDA_OK(bin_scan_cuda(temp.data_ptr(), bytes, ordered.data_ptr<int64_t>(),
                                offsets.data_ptr<int64_t>(), n, stream));
  }
  counts = at::Tensor();
  const int64_t m = offsets[n - 1].item<int64_t>();  // the one host synchronisation
  auto keys = at::empty({m}, int_opts), keys_alt = at::empty({m}, int_opts);
  auto ids = at::empty({m}, int_opts), ids_alt = at::empty({m}, int_opts);
  TIGER_CUDA_OK(bin_emit_cuda<T>(in, order, rank.data_ptr<int32_t>(), large, large_n, g,
                                 offsets.data_ptr<int64_t>(), ptr_of<uint32_t>(keys),
                                 ids.data_ptr<int32_t>(), stream));
  offsets = rank = i0 = i1 = large_ids = large_counters = at::Tensor();
  int tile_bits = 1;  // at least one bit: a sort over [0, 0) is not defined
  while ((int64_t(1) << tile_bits) < n_tiles) ++tile_bits;
  uint32_t* keys_sorted = ptr_of<uint32_t>(keys);
  int32_t* ids_sorted = ids.data_ptr<int32_t>();
  if (m > 0) {
    size_t bytes = 0;
    auto sort = [&](void* temp) {
      TIGER_CUDA_OK(bin_sort_cuda(temp, bytes, ptr_of<uint32_t>(keys), ptr_of<uint32_t>(keys_alt),
                                  ids.data_ptr<int32_t>(), ids_alt.data_ptr<int32_t>(), m,
                                  tile_bits, &keys_sorted, &ids_sorted, stream));
    };
    sort(nullptr);
    auto temp = temp_buffer(bytes, like);
    sort(temp.data_ptr());
  }
  TIGER_CUDA_OK(bin_ranges_cuda(keys_sorted, m, n_tiles, tile_offsets.data_ptr<int64_t>(), stream));
  return ids_sorted == ids.data_ptr<int32_t>() ? ids : ids_alt;
}
}  // namespace

std::tuple<at::Tensor, at::Tensor> bin_gaussians_cuda(const at::Tensor& means2d,
                                                      const at::Tensor& conics,
                                                      const at::Tensor& opacities,
                                                      const at::Tensor& depths,
                                                      const at::Tensor& radii, int64_t width,
                                                      int64_t height, int64_t tile_size,
                                                      double alpha_threshold,
                                                      c10::string_view path,
                                                      int64_t block_sort_keys,
                                                      int64_t warp_sort_keys, int64_t giant_tiles,
                                                      bool serial, int64_t views) {
  check_binning_inputs("tiger.bin_gaussians", means2d, conics, opacities, depths, radii, width,
                       height, tile_size);
  check_binning_views("tiger.bin_gaussians", means2d.size(0), views);
  check_binning_choices("tiger.bin_gaussians", path, block_sort_keys, warp_sort_keys, giant_tiles);
  const c10::cuda::CUDAGuard guard(means2d.device());
  cudaStream_t stream = c10::cuda::getCurrentCUDAStream().stream();
  const int64_t n = means2d.size(0);
  const int ts = int(tile_size);
  BinGeometry g{int(width), int(height), ts, int((width + ts - 1) / ts), int((height + ts - 1) / ts)};
  // views images' tile grids, one after the other (binning.h)
  const int64_t view_tiles = int64_t(g.tiles_x) * g.tiles_y, n_tiles = views * view_tiles;
  TORCH_CHECK(n_tiles < (int64_t(1) << 31), "tiger.bin_gaussians: ", views, " images of ",
              view_tiles, " tiles are more than 2^31 tiles");
  TORCH_CHECK(n < (int64_t(1) << 31), "tiger.bin_gaussians: at most 2^31-1 Gaussians, got ", n);
  // path "auto": the per-tile path up to kBinTilePathMaxGaussians Gaussians, else the global sort
  const bool per_tile = path == "auto" ? n <= kBinTilePathMaxGaussians : path == "tiles";
  const BinChoices choice{int(block_sort_keys), int(warp_sort_keys), giant_tiles, serial};
  auto tile_offsets = at::empty({n_tiles + 1}, means2d.options().dtype(at::kLong));
  if (n == 0) {
    tile_offsets.zero_();
    return {tile_offsets, at::empty({0}, means2d.options().dtype(at::kInt))};
  }
  const auto m2 = means2d.contiguous(), cn = conics.contiguous(), op = opacities.contiguous(),
             dp = depths.contiguous(), r = radii.contiguous();
  at::Tensor gaussian_ids;
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "bin_gaussians_cuda", [&] {
    using T = scalar_t;
    const BinInputs<T> in{m2.data_ptr<T>(), cn.data_ptr<T>(), op.data_ptr<T>(), dp.data_ptr<T>(),
                          r.data_ptr<int32_t>(), nullptr, n, T(alpha_threshold), n / views};
    gaussian_ids = per_tile ? bin_per_tile<T>(in, g, n_tiles, tile_offsets, choice, means2d, stream)
                            : bin_global<T>(in, g, n_tiles, tile_offsets, choice, means2d, stream);
  });
  return {tile_offsets, gaussian_ids};
}

TORCH_LIBRARY_IMPL(tiger, CUDA, m) { m.impl("bin_gaussians", &bin_gaussians_cuda); }

}  // namespace tiger

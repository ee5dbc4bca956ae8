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

// Candidate tiles beyond which a large Gaussian gets a whole block instead of a warp;
// TIGER_BIN_GIANT_TILES overrides it (benchmark sweeps).
int64_t giant_tiles() {
  const char* v = std::getenv("TIGER_BIN_GIANT_TILES");
  const long long t = v != nullptr ? std::atoll(v) : 0;
  return t > 0 ? int64_t(t) : int64_t(512);
}

template <typename T>
at::Tensor empty_of(int64_t n, const at::Tensor& like) {
  return at::empty({n}, like.options().dtype(sizeof(T) == 4 ? at::kInt : at::kLong));
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
  auto tile_offsets = at::empty({n_tiles + 1}, means2d.options().dtype(at::kLong));
  if (n == 0) {
    tile_offsets.zero_();
    return {tile_offsets, at::empty({0}, means2d.options().dtype(at::kInt))};
  }
  const auto m2 = means2d.contiguous(), cn = conics.contiguous(), op = opacities.contiguous(),
             dp = depths.contiguous(), r = radii.contiguous();
  const auto int_opts = means2d.options().dtype(at::kInt), long_opts = means2d.options().dtype(at::kLong);
  auto counts = at::empty({n}, long_opts);
  // Small Gaussians are counted one per thread; the large ones, listed by that kernel, by one
  // warp or block each (load balance). TIGER_BIN_SERIAL=1 selects the former
  // one-thread-per-Gaussian binning (comparisons).
  at::Tensor large_ids, large_counters;
  if (!serial_binning()) {
    large_ids = at::empty({n}, int_opts);
    large_counters = at::empty({2}, int_opts);
  }
  int32_t* large = large_ids.defined() ? large_ids.data_ptr<int32_t>() : nullptr;
  auto* large_n = large_counters.defined()
                      ? reinterpret_cast<unsigned int*>(large_counters.data_ptr<int32_t>())
                      : nullptr;
  auto rank = at::empty({n}, int_opts);
  auto offsets = at::empty({n}, long_opts);
  // the depth sort's id buffers (the order ends in one of them) live until the emit
  auto i0 = at::empty({n}, int_opts), i1 = at::empty({n}, int_opts);
  int32_t* order = nullptr;
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "bin_gaussians_cuda_count", [&] {
    using T = scalar_t;
    using K = DepthKey<T>;
    TIGER_CUDA_OK(bin_count_cuda<T>(m2.data_ptr<T>(), cn.data_ptr<T>(), op.data_ptr<T>(),
                                    r.data_ptr<int32_t>(), n, g, T(alpha_threshold), giant_tiles(),
                                    counts.data_ptr<int64_t>(), large, large_n, stream));
    // the depth order of the Gaussians, their counts in it, and each one's rank
    auto k0 = empty_of<T>(n, means2d), k1 = empty_of<T>(n, means2d);
    size_t bytes = 0;
    TIGER_CUDA_OK(bin_depth_order_cuda<T>(nullptr, bytes, dp.data_ptr<T>(), n, ptr_of<K>(k0),
                                          ptr_of<K>(k1), i0.data_ptr<int32_t>(),
                                          i1.data_ptr<int32_t>(), &order, stream));
    auto temp = temp_buffer(bytes, means2d);
    TIGER_CUDA_OK(bin_depth_order_cuda<T>(temp.data_ptr(), bytes, dp.data_ptr<T>(), n,
                                          ptr_of<K>(k0), ptr_of<K>(k1), i0.data_ptr<int32_t>(),
                                          i1.data_ptr<int32_t>(), &order, stream));
    auto ordered = at::empty({n}, long_opts);
    TIGER_CUDA_OK(bin_order_counts_cuda(order, counts.data_ptr<int64_t>(), n,
                                        ordered.data_ptr<int64_t>(), rank.data_ptr<int32_t>(),
                                        stream));
    size_t scan_bytes = 0;
    TIGER_CUDA_OK(bin_scan_cuda(nullptr, scan_bytes, ordered.data_ptr<int64_t>(),
                                offsets.data_ptr<int64_t>(), n, stream));
    auto scan_temp = temp_buffer(scan_bytes, means2d);
    TIGER_CUDA_OK(bin_scan_cuda(scan_temp.data_ptr(), scan_bytes, ordered.data_ptr<int64_t>(),
                                offsets.data_ptr<int64_t>(), n, stream));
  });
  counts = at::Tensor();
  const int64_t m = offsets[n - 1].item<int64_t>();  // the one host synchronisation
  auto keys = at::empty({m}, int_opts), keys_alt = at::empty({m}, int_opts);
  auto ids = at::empty({m}, int_opts), ids_alt = at::empty({m}, int_opts);
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "bin_gaussians_cuda_emit", [&] {
    using T = scalar_t;
    TIGER_CUDA_OK(bin_emit_cuda<T>(m2.data_ptr<T>(), cn.data_ptr<T>(), op.data_ptr<T>(),
                                   r.data_ptr<int32_t>(), order, rank.data_ptr<int32_t>(), large, large_n,
                                   n, g, T(alpha_threshold), offsets.data_ptr<int64_t>(),
                                   ptr_of<uint32_t>(keys), ids.data_ptr<int32_t>(), stream));
  });
  offsets = at::Tensor();
  rank = at::Tensor();
  i0 = at::Tensor();
  i1 = at::Tensor();
  large_ids = at::Tensor();
  large_counters = at::Tensor();
  int tile_bits = 1;  // at least one bit: a sort over [0, 0) is not defined
  while ((int64_t(1) << tile_bits) < n_tiles) ++tile_bits;
  uint32_t* keys_sorted = ptr_of<uint32_t>(keys);
  int32_t* ids_sorted = ids.data_ptr<int32_t>();
  if (m > 0) {
    size_t sort_bytes = 0;
    TIGER_CUDA_OK(bin_sort_cuda(nullptr, sort_bytes, ptr_of<uint32_t>(keys), ptr_of<uint32_t>(keys_alt),
                                ids.data_ptr<int32_t>(), ids_alt.data_ptr<int32_t>(), m, tile_bits,
                                nullptr, nullptr, stream));
    auto temp = temp_buffer(sort_bytes, means2d);
    TIGER_CUDA_OK(bin_sort_cuda(temp.data_ptr(), sort_bytes, ptr_of<uint32_t>(keys),
                                ptr_of<uint32_t>(keys_alt), ids.data_ptr<int32_t>(),
                                ids_alt.data_ptr<int32_t>(), m, tile_bits, &keys_sorted,
                                &ids_sorted, stream));
  }
  TIGER_CUDA_OK(bin_ranges_cuda(keys_sorted, m, n_tiles, tile_offsets.data_ptr<int64_t>(), stream));
  at::Tensor gaussian_ids = ids_sorted == ids.data_ptr<int32_t>() ? ids : ids_alt;
  return {tile_offsets, gaussian_ids};
}

TORCH_LIBRARY_IMPL(tiger, CUDA, m) { m.impl("bin_gaussians", &bin_gaussians_cuda); }

}  // namespace tiger

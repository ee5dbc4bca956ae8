// Torch glue of the CUDA tile binning (built only with CUDA on). Every buffer comes
// from torch's caching allocator; the one host synchronisation reads the total number
// of intersections, which sizes the outputs.
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
  auto counts = at::empty({n}, means2d.options().dtype(at::kLong));
  auto offsets = at::empty({n}, means2d.options().dtype(at::kLong));
  int64_t m = 0;
  at::Tensor rank;
  // Small Gaussians are counted one per thread; the large ones, listed by that kernel, by one
  // warp or block each (load balance). TIGER_BIN_SERIAL=1 selects the former
  // one-thread-per-Gaussian binning (comparisons).
  at::Tensor large_ids, large_counters;
  if (!serial_binning()) {
    large_ids = at::empty({n}, means2d.options().dtype(at::kInt));
    large_counters = at::empty({2}, means2d.options().dtype(at::kInt));
  }
  int32_t* large = large_ids.defined() ? large_ids.data_ptr<int32_t>() : nullptr;
  auto* large_n = large_counters.defined()
                      ? reinterpret_cast<unsigned int*>(large_counters.data_ptr<int32_t>())
                      : nullptr;
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "bin_gaussians_cuda_count", [&] {
    using T = scalar_t;
    TIGER_CUDA_OK(bin_count_cuda<T>(m2.data_ptr<T>(), cn.data_ptr<T>(), op.data_ptr<T>(),
                                    r.data_ptr<int32_t>(), n, g, T(alpha_threshold),
                                    counts.data_ptr<int64_t>(), large, large_n, stream));
  });
  size_t scan_bytes = 0;
  TIGER_CUDA_OK(bin_scan_cuda(nullptr, scan_bytes, counts.data_ptr<int64_t>(),
                              offsets.data_ptr<int64_t>(), n, stream));
  {
    auto temp = temp_buffer(scan_bytes, means2d);
    TIGER_CUDA_OK(bin_scan_cuda(temp.data_ptr(), scan_bytes, counts.data_ptr<int64_t>(),
                                offsets.data_ptr<int64_t>(), n, stream));
  }
  if (means2d.scalar_type() == at::kDouble) {
    // float64 depths need more than the 32 key bits: sort them first, key on the rank.
    rank = at::empty({n}, means2d.options().dtype(at::kInt));
    auto k0 = at::empty({n}, means2d.options().dtype(at::kLong));
    auto k1 = at::empty({n}, means2d.options().dtype(at::kLong));
    auto i0 = at::empty({n}, means2d.options().dtype(at::kInt));
    auto i1 = at::empty({n}, means2d.options().dtype(at::kInt));
    auto kp = [](at::Tensor& t) { return reinterpret_cast<uint64_t*>(t.data_ptr<int64_t>()); };
    size_t bytes = 0;
    TIGER_CUDA_OK(bin_depth_rank_cuda(nullptr, bytes, dp.data_ptr<double>(), n, kp(k0), kp(k1),
                                      i0.data_ptr<int32_t>(), i1.data_ptr<int32_t>(),
                                      rank.data_ptr<int32_t>(), stream));
    auto temp = temp_buffer(bytes, means2d);
    TIGER_CUDA_OK(bin_depth_rank_cuda(temp.data_ptr(), bytes, dp.data_ptr<double>(), n, kp(k0),
                                      kp(k1), i0.data_ptr<int32_t>(), i1.data_ptr<int32_t>(),
                                      rank.data_ptr<int32_t>(), stream));
  }
  m = offsets[n - 1].item<int64_t>();  // the one host synchronisation
  auto keys = at::empty({m}, means2d.options().dtype(at::kLong));
  auto keys_alt = at::empty({m}, means2d.options().dtype(at::kLong));
  auto ids = at::empty({m}, means2d.options().dtype(at::kInt));
  auto ids_alt = at::empty({m}, means2d.options().dtype(at::kInt));
  auto kptr = [](at::Tensor& t) { return reinterpret_cast<uint64_t*>(t.data_ptr<int64_t>()); };
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "bin_gaussians_cuda_emit", [&] {
    using T = scalar_t;
    TIGER_CUDA_OK(bin_emit_cuda<T>(m2.data_ptr<T>(), cn.data_ptr<T>(), op.data_ptr<T>(),
                                   dp.data_ptr<T>(), r.data_ptr<int32_t>(),
                                   rank.defined() ? rank.data_ptr<int32_t>() : nullptr, large,
                                   large_n, n, g, T(alpha_threshold), offsets.data_ptr<int64_t>(),
                                   kptr(keys), ids.data_ptr<int32_t>(), stream));
  });
  counts = at::Tensor();
  offsets = at::Tensor();
  large_ids = at::Tensor();
  large_counters = at::Tensor();
  int tile_bits = 0;
  while ((int64_t(1) << tile_bits) < n_tiles) ++tile_bits;
  const int end_bit = 32 + tile_bits;
  uint64_t* keys_sorted = kptr(keys);
  int32_t* ids_sorted = ids.data_ptr<int32_t>();
  if (m > 0) {
    size_t sort_bytes = 0;
    TIGER_CUDA_OK(bin_sort_cuda(nullptr, sort_bytes, kptr(keys), kptr(keys_alt),
                                ids.data_ptr<int32_t>(), ids_alt.data_ptr<int32_t>(), m, end_bit,
                                nullptr, nullptr, stream));
    auto temp = temp_buffer(sort_bytes, means2d);
    TIGER_CUDA_OK(bin_sort_cuda(temp.data_ptr(), sort_bytes, kptr(keys), kptr(keys_alt),
                                ids.data_ptr<int32_t>(), ids_alt.data_ptr<int32_t>(), m, end_bit,
                                &keys_sorted, &ids_sorted, stream));
  }
  TIGER_CUDA_OK(bin_ranges_cuda(keys_sorted, m, n_tiles, tile_offsets.data_ptr<int64_t>(), stream));
  at::Tensor gaussian_ids = ids_sorted == ids.data_ptr<int32_t>() ? ids : ids_alt;
  return {tile_offsets, gaussian_ids};
}

TORCH_LIBRARY_IMPL(tiger, CUDA, m) { m.impl("bin_gaussians", &bin_gaussians_cuda); }

}  // namespace tiger

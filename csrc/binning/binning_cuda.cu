// CUDA tile binning: count -> int64 scan -> emit (tile, depth) keys -> CUB radix sort
// -> tile ranges. The tile test is tile_touches from common/raster_math.h, so a tile is
// listed only where the ellipse reaches alpha >= threshold at one of its pixel centres.
#include <cub/device/device_radix_sort.cuh>
#include <cub/device/device_scan.cuh>

#include "binning_cuda.h"
#include "common/cuda_helpers.cuh"
#include "common/raster_math.h"

namespace tiger {
namespace {

constexpr int kThreads = 256;

struct TileRect {
  int x0, x1, y0, y1;  // [x0, x1) x [y0, y1) in tile units
};

__device__ __forceinline__ int clamp_tile(double a, int hi) {
  return a < 0.0 ? 0 : (a > double(hi) ? hi : int(a));
}

template <typename T>
__device__ TileRect tile_rect(T u, T v, int32_t rx, int32_t ry, const BinGeometry& g) {
  const double ts = g.tile_size;
  return {clamp_tile(floor((double(u) - rx) / ts), g.tiles_x),
          clamp_tile(floor((double(u) + rx) / ts) + 1.0, g.tiles_x),
          clamp_tile(floor((double(v) - ry) / ts), g.tiles_y),
          clamp_tile(floor((double(v) + ry) / ts) + 1.0, g.tiles_y)};
}

// Visits the tiles Gaussian i really touches, in row-major order (count and emit agree).
template <typename T, typename F>
__device__ void visit_tiles(int64_t i, const T* means2d, const T* conics, const T* opacities,
                            const int32_t* radii, const BinGeometry& g, T alpha_threshold, F&& f) {
  const int32_t rx = radii[2 * i], ry = radii[2 * i + 1];
  if (rx <= 0 || ry <= 0) return;
  const T u = means2d[2 * i], v = means2d[2 * i + 1];
  const T ca = conics[3 * i], cb = conics[3 * i + 1], cc = conics[3 * i + 2];
  const TileRect r = tile_rect(u, v, rx, ry, g);
  const T qcut = cutoff_quadratic<T>(opacities[i], alpha_threshold);
  for (int ty = r.y0; ty < r.y1; ++ty) {
    const int py0 = ty * g.tile_size;
    const int py1 = min(py0 + g.tile_size, g.height);
    for (int tx = r.x0; tx < r.x1; ++tx) {
      const int px0 = tx * g.tile_size;
      const int px1 = min(px0 + g.tile_size, g.width);
      if (tile_touches<T>(u, v, ca, cb, cc, qcut, px0, px1, py0, py1)) f(ty * g.tiles_x + tx);
    }
  }
}

template <typename T>
__global__ void count_kernel(const T* means2d, const T* conics, const T* opacities,
                             const int32_t* radii, int64_t n, BinGeometry g, T alpha_threshold,
                             int64_t* counts) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  int64_t c = 0;
  visit_tiles(i, means2d, conics, opacities, radii, g, alpha_threshold, [&](int) { ++c; });
  counts[i] = c;
}

template <typename T>
__device__ __forceinline__ uint32_t depth_bits(T d) {
  return cuda::depth_key_bits(float(d));
}

template <typename T>
__global__ void emit_kernel(const T* means2d, const T* conics, const T* opacities, const T* depths,
                            const int32_t* radii, const int32_t* depth_rank, int64_t n,
                            BinGeometry g, T alpha_threshold, const int64_t* offsets,
                            uint64_t* keys, int32_t* ids) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  int64_t k = i == 0 ? 0 : offsets[i - 1];
  const uint64_t dkey = depth_rank ? uint64_t(uint32_t(depth_rank[i])) : uint64_t(depth_bits(depths[i]));
  visit_tiles(i, means2d, conics, opacities, radii, g, alpha_threshold, [&](int tile) {
    keys[k] = (uint64_t(tile) << 32) | dkey;
    ids[k] = int32_t(i);
    ++k;
  });
}

// tile_offsets[t] = first sorted index whose tile is >= t; tile_offsets[n_tiles] = m.
__global__ void ranges_kernel(const uint64_t* keys, int64_t m, int64_t n_tiles,
                              int64_t* tile_offsets) {
  const int64_t k = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (k >= m) return;
  const int64_t tile = int64_t(keys[k] >> 32);
  const int64_t prev = k == 0 ? -1 : int64_t(keys[k - 1] >> 32);
  for (int64_t t = prev + 1; t <= tile; ++t) tile_offsets[t] = k;
  if (k == m - 1)
    for (int64_t t = tile + 1; t <= n_tiles; ++t) tile_offsets[t] = m;
}

__global__ void depth_keys_kernel(const double* depths, int64_t n, uint64_t* keys, int32_t* ids) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  keys[i] = cuda::depth_key_bits64(depths[i]);
  ids[i] = int32_t(i);
}

__global__ void scatter_rank_kernel(const int32_t* sorted_ids, int64_t n, int32_t* rank) {
  const int64_t r = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (r < n) rank[sorted_ids[r]] = int32_t(r);
}

}  // namespace

template <typename T>
cudaError_t bin_count_cuda(const T* means2d, const T* conics, const T* opacities,
                           const int32_t* radii, int64_t n, BinGeometry g, T alpha_threshold,
                           int64_t* counts, cudaStream_t stream) {
  if (n == 0) return cudaSuccess;
  count_kernel<T><<<cuda::ceil_div(n, kThreads), kThreads, 0, stream>>>(
      means2d, conics, opacities, radii, n, g, alpha_threshold, counts);
  return cudaGetLastError();
}

cudaError_t bin_scan_cuda(void* temp, size_t& temp_bytes, const int64_t* counts, int64_t* offsets,
                          int64_t n, cudaStream_t stream) {
  return cub::DeviceScan::InclusiveSum(temp, temp_bytes, counts, offsets, n, stream);
}

template <typename T>
cudaError_t bin_emit_cuda(const T* means2d, const T* conics, const T* opacities, const T* depths,
                          const int32_t* radii, const int32_t* depth_rank, int64_t n,
                          BinGeometry g, T alpha_threshold, const int64_t* offsets,
                          uint64_t* keys, int32_t* ids, cudaStream_t stream) {
  if (n == 0) return cudaSuccess;
  emit_kernel<T><<<cuda::ceil_div(n, kThreads), kThreads, 0, stream>>>(
      means2d, conics, opacities, depths, radii, depth_rank, n, g, alpha_threshold, offsets, keys,
      ids);
  return cudaGetLastError();
}

cudaError_t bin_sort_cuda(void* temp, size_t& temp_bytes, uint64_t* keys, uint64_t* keys_alt,
                          int32_t* ids, int32_t* ids_alt, int64_t m, int end_bit,
                          uint64_t** keys_out, int32_t** ids_out, cudaStream_t stream) {
  cub::DoubleBuffer<uint64_t> k(keys, keys_alt);
  cub::DoubleBuffer<int32_t> v(ids, ids_alt);
  const cudaError_t err =
      cub::DeviceRadixSort::SortPairs(temp, temp_bytes, k, v, m, 0, end_bit, stream);
  if (keys_out) *keys_out = k.Current();
  if (ids_out) *ids_out = v.Current();
  return err;
}

cudaError_t bin_ranges_cuda(const uint64_t* sorted_keys, int64_t m, int64_t n_tiles,
                            int64_t* tile_offsets, cudaStream_t stream) {
  if (m == 0) return cudaMemsetAsync(tile_offsets, 0, sizeof(int64_t) * (n_tiles + 1), stream);
  ranges_kernel<<<cuda::ceil_div(m, kThreads), kThreads, 0, stream>>>(sorted_keys, m, n_tiles,
                                                                      tile_offsets);
  return cudaGetLastError();
}

cudaError_t bin_depth_rank_cuda(void* temp, size_t& temp_bytes, const double* depths, int64_t n,
                                uint64_t* keys, uint64_t* keys_alt, int32_t* ids, int32_t* ids_alt,
                                int32_t* rank, cudaStream_t stream) {
  if (temp == nullptr) {
    return bin_sort_cuda(nullptr, temp_bytes, keys, keys_alt, ids, ids_alt, n, 64, nullptr,
                         nullptr, stream);
  }
  if (n == 0) return cudaSuccess;
  depth_keys_kernel<<<cuda::ceil_div(n, kThreads), kThreads, 0, stream>>>(depths, n, keys, ids);
  cudaError_t err = cudaGetLastError();
  if (err != cudaSuccess) return err;
  int32_t* sorted = nullptr;
  err = bin_sort_cuda(temp, temp_bytes, keys, keys_alt, ids, ids_alt, n, 64, nullptr, &sorted,
                      stream);
  if (err != cudaSuccess) return err;
  scatter_rank_kernel<<<cuda::ceil_div(n, kThreads), kThreads, 0, stream>>>(sorted, n, rank);
  return cudaGetLastError();
}

#define TIGER_INSTANTIATE(T)                                                                     \
  template cudaError_t bin_count_cuda<T>(const T*, const T*, const T*, const int32_t*, int64_t,  \
                                         BinGeometry, T, int64_t*, cudaStream_t);                \
  template cudaError_t bin_emit_cuda<T>(const T*, const T*, const T*, const T*, const int32_t*,  \
                                        const int32_t*, int64_t, BinGeometry, T, const int64_t*, \
                                        uint64_t*, int32_t*, cudaStream_t);
TIGER_INSTANTIATE(float)
TIGER_INSTANTIATE(double)
#undef TIGER_INSTANTIATE

}  // namespace tiger

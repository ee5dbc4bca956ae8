// CUDA tile binning: candidates (bounding-box tiles) -> scan -> balanced count -> int64 scan
// -> balanced emit of (tile, depth) keys -> CUB radix sort -> tile ranges. The tile test is
// tile_touches from common/raster_math.h, so a tile is listed only where the ellipse reaches
// alpha >= threshold at one of its pixel centres. The count and emit kernels spread the
// candidate tiles of all Gaussians evenly over threads (kChunk each), so a Gaussian covering
// thousands of tiles no longer stalls its warp (one thread per Gaussian did: 3 ms of a 3.9 ms
// forward on a real scene).
#include <cub/device/device_radix_sort.cuh>
#include <cub/device/device_scan.cuh>

#include <stdlib.h>

#include "binning_cuda.h"
#include "common/cuda_helpers.cuh"
#include "common/raster_math.h"

namespace tiger {
namespace {

constexpr int kThreads = 256;
// Candidate tiles (bounding-box tiles of all Gaussians, concatenated in Gaussian order) are
// handed out in chunks of kChunk, one chunk per thread: one binary search per chunk, then a
// linear walk. Every thread tests at most kChunk tiles, whatever the size of the Gaussians
// (load balance). 32 by default (TIGER_BIN_CHUNK=16 for comparisons).

template <typename T>
__device__ __forceinline__ TileRect rect_of(int64_t i, const T* means2d, const int32_t* radii,
                                            const BinGeometry& g) {
  const int32_t rx = radii[2 * i], ry = radii[2 * i + 1];
  if (rx <= 0 || ry <= 0) return {0, 0, 0, 0};
  return tile_rect(means2d[2 * i], means2d[2 * i + 1], rx, ry, g.tile_size, g.tiles_x, g.tiles_y);
}

// Number of candidate (bounding-box) tiles per Gaussian.
template <typename T>
__global__ void candidates_kernel(const T* means2d, const int32_t* radii, int64_t n, BinGeometry g,
                                  int64_t* candidates) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i < n) candidates[i] = rect_of(i, means2d, radii, g).count();
}

// First index i in [lo, hi] with ends[i] > k (ends ascending, ends[hi] > k).
__device__ __forceinline__ int64_t upper_bound(const int64_t* ends, int64_t lo, int64_t hi,
                                               int64_t k) {
  while (lo < hi) {
    const int64_t mid = lo + (hi - lo) / 2;
    if (ends[mid] > k) hi = mid; else lo = mid + 1;
  }
  return lo;
}

// The exact test of one Gaussian, loaded once per run of its candidates.
template <typename T>
struct TileTester {
  T u, v, ca, cb, cc, qcut;
  TileRect r;
  int64_t first;  // index of this Gaussian's first candidate

  __device__ void load(int64_t i, int64_t first_candidate, const T* means2d, const T* conics,
                       const T* opacities, const int32_t* radii, const BinGeometry& g,
                       T alpha_threshold) {
    u = means2d[2 * i];
    v = means2d[2 * i + 1];
    ca = conics[3 * i];
    cb = conics[3 * i + 1];
    cc = conics[3 * i + 2];
    qcut = cutoff_quadratic<T>(opacities[i], alpha_threshold);
    r = rect_of(i, means2d, radii, g);
    first = first_candidate;
  }
  // Row-major tile index of candidate k.
  __device__ int tile(int64_t k, const BinGeometry& g) const {
    const int64_t j = k - first;
    const int w = r.width();
    return (r.y0 + int(j / w)) * g.tiles_x + r.x0 + int(j % w);
  }
  __device__ bool touches(int tile_index, const BinGeometry& g) const {
    const int ty = tile_index / g.tiles_x, tx = tile_index - ty * g.tiles_x;
    const int px0 = tx * g.tile_size, py0 = ty * g.tile_size;
    return tile_touches<T>(u, v, ca, cb, cc, qcut, px0, min(px0 + g.tile_size, g.width), py0,
                           min(py0 + g.tile_size, g.height));
  }
};

// Load-balanced walk over all candidate tiles: chunk c covers candidates
// [c * kChunk, (c + 1) * kChunk), possibly of several Gaussians. For each run of one
// Gaussian inside a chunk, flush(i, tester, hits, k0) gets the bit mask of touched tiles
// (bit b = candidate k0 + b). cand_ends = inclusive scan of the per-Gaussian candidates.
template <int kChunk, typename T, typename Flush>
__device__ void walk_candidates(const T* means2d, const T* conics, const T* opacities,
                                const int32_t* radii, const int64_t* cand_ends, int64_t n,
                                const BinGeometry& g, T alpha_threshold, Flush&& flush) {
  static_assert(kChunk >= 1 && kChunk <= 32, "hit masks are 32-bit");
  const int64_t total = cand_ends[n - 1];
  const int64_t n_chunks = (total + kChunk - 1) / kChunk;
  const int64_t stride = int64_t(gridDim.x) * blockDim.x;
  for (int64_t c = int64_t(blockIdx.x) * blockDim.x + threadIdx.x; c < n_chunks; c += stride) {
    const int64_t k0 = c * kChunk, k1 = min(k0 + kChunk, total);
    int64_t i = upper_bound(cand_ends, 0, n - 1, k0);
    TileTester<T> t;
    t.load(i, i == 0 ? 0 : cand_ends[i - 1], means2d, conics, opacities, radii, g, alpha_threshold);
    int64_t end = cand_ends[i];
    uint32_t hits = 0;
    for (int64_t k = k0; k < k1; ++k) {
      if (k >= end) {  // next Gaussian with candidates (skips empty ones)
        flush(i, t, hits, k0);
        hits = 0;
        const int64_t first = end;
        i = cand_ends[i + 1] > k ? i + 1 : upper_bound(cand_ends, i + 2, n - 1, k);
        t.load(i, first, means2d, conics, opacities, radii, g, alpha_threshold);
        end = cand_ends[i];
      }
      if (t.touches(t.tile(k, g), g)) hits |= 1u << int(k - k0);  // kChunk <= 32
    }
    flush(i, t, hits, k0);
  }
}

// counts[i] += touched tiles of Gaussian i (counts zeroed before).
template <int kChunk, typename T>
__global__ void __launch_bounds__(kThreads)
    count_balanced_kernel(const T* means2d, const T* conics, const T* opacities,
                          const int32_t* radii, const int64_t* cand_ends, int64_t n, BinGeometry g,
                          T alpha_threshold, int64_t* counts) {
  walk_candidates<kChunk>(means2d, conics, opacities, radii, cand_ends, n, g, alpha_threshold,
                  [&](int64_t i, TileTester<T>, uint32_t hits, int64_t) {
                    if (hits)
                      atomicAdd(reinterpret_cast<unsigned long long*>(counts + i),
                                static_cast<unsigned long long>(__popc(hits)));
                  });
}

template <typename T>
__device__ __forceinline__ uint32_t depth_bits(T d) {
  return cuda::depth_key_bits(float(d));
}

// Writes the (tile, depth) keys of Gaussian i's touched tiles into its segment
// [offsets[i-1], offsets[i]). Threads sharing a Gaussian claim slots through cursor[i]
// (zeroed before), so the order inside a segment varies from run to run; the keys of one
// segment are distinct (one per tile) and the radix sort is stable, so the sorted lists
// are the same as with any fixed order: (tile, depth, id).
template <int kChunk, typename T>
__global__ void __launch_bounds__(kThreads)
    emit_balanced_kernel(const T* means2d, const T* conics, const T* opacities, const T* depths,
                         const int32_t* radii, const int32_t* depth_rank, const int64_t* cand_ends,
                         int64_t n, BinGeometry g, T alpha_threshold, const int64_t* offsets,
                         int64_t* cursor, uint64_t* keys, int32_t* ids) {
  walk_candidates<kChunk>(
      means2d, conics, opacities, radii, cand_ends, n, g, alpha_threshold,
      [&](int64_t i, TileTester<T> t, uint32_t hits, int64_t k0) {
        if (!hits) return;
        int64_t slot = (i == 0 ? 0 : offsets[i - 1]) +
                       int64_t(atomicAdd(reinterpret_cast<unsigned long long*>(cursor + i),
                                         static_cast<unsigned long long>(__popc(hits))));
        const uint64_t dkey = depth_rank ? uint64_t(uint32_t(depth_rank[i]))
                                         : uint64_t(depth_bits(depths[i]));
        while (hits) {
          const int b = __ffs(hits) - 1;
          hits &= hits - 1;
          keys[slot] = (uint64_t(t.tile(k0 + b, g)) << 32) | dkey;
          ids[slot] = int32_t(i);
          ++slot;
        }
      });
}

// The previous binning, one thread per Gaussian walking its whole bounding box (kept for
// same-process comparisons: TIGER_BIN_SERIAL=1). Visits touched tiles in row-major order.
template <typename T, typename F>
__device__ void visit_tiles(int64_t i, const T* means2d, const T* conics, const T* opacities,
                            const int32_t* radii, const BinGeometry& g, T alpha_threshold, F&& f) {
  const TileRect r = rect_of(i, means2d, radii, g);
  if (r.count() == 0) return;
  TileTester<T> t;
  t.load(i, 0, means2d, conics, opacities, radii, g, alpha_threshold);
  for (int ty = r.y0; ty < r.y1; ++ty)
    for (int tx = r.x0; tx < r.x1; ++tx)
      if (t.touches(ty * g.tiles_x + tx, g)) f(ty * g.tiles_x + tx);
}

template <typename T>
__global__ void count_serial_kernel(const T* means2d, const T* conics, const T* opacities,
                                    const int32_t* radii, int64_t n, BinGeometry g,
                                    T alpha_threshold, int64_t* counts) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  int64_t c = 0;
  visit_tiles(i, means2d, conics, opacities, radii, g, alpha_threshold, [&](int) { ++c; });
  counts[i] = c;
}

template <typename T>
__global__ void emit_serial_kernel(const T* means2d, const T* conics, const T* opacities,
                                   const T* depths, const int32_t* radii, const int32_t* depth_rank,
                                   int64_t n, BinGeometry g, T alpha_threshold,
                                   const int64_t* offsets, uint64_t* keys, int32_t* ids) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  int64_t k = i == 0 ? 0 : offsets[i - 1];
  const uint64_t dkey =
      depth_rank ? uint64_t(uint32_t(depth_rank[i])) : uint64_t(depth_bits(depths[i]));
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

// Chunk size of the balanced kernels: TIGER_BIN_CHUNK=16 or 32 (default).
static bool small_chunks() {
  const char* v = getenv("TIGER_BIN_CHUNK");
  return v != nullptr && v[0] == '1' && v[1] == '6';
}

// A grid that fills the GPU once; the balanced kernels loop over their chunks.
static cudaError_t balanced_grid(int& blocks) {
  int dev = 0, sms = 0;
  cudaError_t err = cudaGetDevice(&dev);
  if (err == cudaSuccess) err = cudaDeviceGetAttribute(&sms, cudaDevAttrMultiProcessorCount, dev);
  blocks = (sms > 0 ? sms : 1) * (2048 / kThreads);
  return err;
}

template <typename T>
cudaError_t bin_candidates_cuda(const T* means2d, const int32_t* radii, int64_t n, BinGeometry g,
                                int64_t* candidates, cudaStream_t stream) {
  if (n == 0) return cudaSuccess;
  candidates_kernel<T><<<cuda::ceil_div(n, kThreads), kThreads, 0, stream>>>(means2d, radii, n, g,
                                                                          candidates);
  return cudaGetLastError();
}

template <typename T>
cudaError_t bin_count_cuda(const T* means2d, const T* conics, const T* opacities,
                           const int32_t* radii, const int64_t* cand_ends, int64_t n,
                           BinGeometry g, T alpha_threshold, int64_t* counts, cudaStream_t stream) {
  if (n == 0) return cudaSuccess;
  if (cand_ends == nullptr) {
    count_serial_kernel<T><<<cuda::ceil_div(n, kThreads), kThreads, 0, stream>>>(
        means2d, conics, opacities, radii, n, g, alpha_threshold, counts);
    return cudaGetLastError();
  }
  int blocks = 0;
  cudaError_t err = balanced_grid(blocks);
  if (err == cudaSuccess) err = cudaMemsetAsync(counts, 0, sizeof(int64_t) * n, stream);
  if (err != cudaSuccess) return err;
  auto kernel = small_chunks() ? count_balanced_kernel<16, T> : count_balanced_kernel<32, T>;
  kernel<<<blocks, kThreads, 0, stream>>>(means2d, conics, opacities, radii, cand_ends, n, g,
                                          alpha_threshold, counts);
  return cudaGetLastError();
}

cudaError_t bin_scan_cuda(void* temp, size_t& temp_bytes, const int64_t* counts, int64_t* offsets,
                          int64_t n, cudaStream_t stream) {
  return cub::DeviceScan::InclusiveSum(temp, temp_bytes, counts, offsets, n, stream);
}

template <typename T>
cudaError_t bin_emit_cuda(const T* means2d, const T* conics, const T* opacities, const T* depths,
                          const int32_t* radii, const int32_t* depth_rank,
                          const int64_t* cand_ends, int64_t n, BinGeometry g, T alpha_threshold,
                          const int64_t* offsets, int64_t* cursor, uint64_t* keys, int32_t* ids,
                          cudaStream_t stream) {
  if (n == 0) return cudaSuccess;
  if (cand_ends == nullptr) {
    emit_serial_kernel<T><<<cuda::ceil_div(n, kThreads), kThreads, 0, stream>>>(
        means2d, conics, opacities, depths, radii, depth_rank, n, g, alpha_threshold, offsets,
        keys, ids);
    return cudaGetLastError();
  }
  int blocks = 0;
  cudaError_t err = balanced_grid(blocks);
  if (err == cudaSuccess) err = cudaMemsetAsync(cursor, 0, sizeof(int64_t) * n, stream);
  if (err != cudaSuccess) return err;
  auto kernel = small_chunks() ? emit_balanced_kernel<16, T> : emit_balanced_kernel<32, T>;
  kernel<<<blocks, kThreads, 0, stream>>>(means2d, conics, opacities, depths, radii, depth_rank,
                                          cand_ends, n, g, alpha_threshold, offsets, cursor, keys,
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

#define TIGER_INSTANTIATE(T)                                                                      \
  template cudaError_t bin_candidates_cuda<T>(const T*, const int32_t*, int64_t, BinGeometry,     \
                                              int64_t*, cudaStream_t);                            \
  template cudaError_t bin_count_cuda<T>(const T*, const T*, const T*, const int32_t*,            \
                                         const int64_t*, int64_t, BinGeometry, T, int64_t*,       \
                                         cudaStream_t);                                           \
  template cudaError_t bin_emit_cuda<T>(const T*, const T*, const T*, const T*, const int32_t*,   \
                                        const int32_t*, const int64_t*, int64_t, BinGeometry, T,  \
                                        const int64_t*, int64_t*, uint64_t*, int32_t*, cudaStream_t);
TIGER_INSTANTIATE(float)
TIGER_INSTANTIATE(double)
#undef TIGER_INSTANTIATE

}  // namespace tiger

// CUDA tile binning: count (small Gaussians per thread; candidate counts of the large ones)
// -> scan of those -> chunked count of the large ones -> int64 scan -> emit (both kinds) of
// (tile, depth) keys -> CUB radix sort -> tile ranges. The tile test is tile_touches from
// common/raster_math.h, so a tile is listed only where the ellipse reaches alpha >= threshold
// at one of its pixel centres. The large Gaussians' candidate tiles are spread evenly over
// threads, so a Gaussian covering thousands of tiles no longer stalls its warp (one thread per
// Gaussian did: 3 ms of a 3.9 ms forward on a real scene).
#include <cub/device/device_radix_sort.cuh>
#include <cub/device/device_scan.cuh>

#include <stdint.h>
#include <stdlib.h>

#include "binning_cuda.h"
#include "common/cuda_helpers.cuh"
#include "common/raster_math.h"

namespace tiger {
namespace {

constexpr int kThreads = 256;
// Gaussians with at most kSmallTiles candidate (bounding-box) tiles are binned by one thread
// each, walking their box in row-major order; that is balanced for them (every thread of a
// warp does at most kSmallTiles tests) and needs no search. The candidate tiles of the larger
// ones are concatenated (in Gaussian order) and handed out in chunks of kChunk per thread:
// one binary search per chunk, then a linear walk, so no thread tests more than kChunk tiles
// however large a Gaussian is. TIGER_BIN_CHUNK=32 selects chunks of 32 (comparisons).
constexpr int kSmallTiles = 32;

template <typename T>
__device__ __forceinline__ TileRect rect_of(int64_t i, const T* means2d, const int32_t* radii,
                                            const BinGeometry& g) {
  const int32_t rx = radii[2 * i], ry = radii[2 * i + 1];
  if (rx <= 0 || ry <= 0) return {0, 0, 0, 0};
  return tile_rect(means2d[2 * i], means2d[2 * i + 1], rx, ry, g.tile_size, g.tiles_x, g.tiles_y);
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
  int64_t first;  // index of this Gaussian's first candidate in the concatenated list

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
  // Row-major tile index of candidate k (a Gaussian has < 2^31 candidates).
  __device__ int tile(int64_t k, const BinGeometry& g) const {
    const int j = int(k - first), w = r.width();
    const int row = j / w;
    return (r.y0 + row) * g.tiles_x + r.x0 + (j - row * w);
  }
  __device__ bool touches(int tx, int ty, const BinGeometry& g) const {
    const int px0 = tx * g.tile_size, py0 = ty * g.tile_size;
    return tile_touches<T>(u, v, ca, cb, cc, qcut, px0, min(px0 + g.tile_size, g.width), py0,
                           min(py0 + g.tile_size, g.height));
  }
};

// Load-balanced walk over the concatenated candidate tiles of the large Gaussians: chunk c
// covers candidates [c * kChunk, (c + 1) * kChunk), possibly of two or more Gaussians. For
// each run of one Gaussian inside a chunk, flush(i, tester, hits, k0) gets the bit mask of
// touched tiles (bit b = candidate k0 + b). cand_ends = inclusive scan of the candidates
// (0 for the small Gaussians, which the per-Gaussian kernels bin).
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
    int w = t.r.width(), j = int(k0 - t.first);
    int row = j / w, col = j - row * w;  // advanced without divisions below
    uint32_t hits = 0;
    for (int64_t k = k0; k < k1; ++k) {
      if (k >= end) {  // next Gaussian with candidates (skips the empty ones)
        flush(i, t, hits, k0);
        hits = 0;
        const int64_t first = end;
        i = cand_ends[i + 1] > k ? i + 1 : upper_bound(cand_ends, i + 2, n - 1, k);
        t.load(i, first, means2d, conics, opacities, radii, g, alpha_threshold);
        end = cand_ends[i];
        w = t.r.width();
        row = 0;
        col = 0;
      }
      if (t.touches(t.r.x0 + col, t.r.y0 + row, g)) hits |= 1u << int(k - k0);
      if (++col == w) {
        col = 0;
        ++row;
      }
    }
    flush(i, t, hits, k0);
  }
}

// counts[i] += touched tiles of large Gaussian i (counts written by count_small_kernel).
template <int kChunk, typename T>
__global__ void __launch_bounds__(kThreads)
    count_large_kernel(const T* means2d, const T* conics, const T* opacities,
                       const int32_t* radii, const int64_t* cand_ends, int64_t n, BinGeometry g,
                       T alpha_threshold, int64_t* counts) {
  walk_candidates<kChunk>(means2d, conics, opacities, radii, cand_ends, n, g, alpha_threshold,
                          [&](int64_t i, const TileTester<T>&, uint32_t hits, int64_t) {
                            if (hits)
                              atomicAdd(reinterpret_cast<unsigned long long*>(counts + i),
                                        static_cast<unsigned long long>(__popc(hits)));
                          });
}

template <typename T>
__device__ __forceinline__ uint32_t depth_bits(T d) {
  return cuda::depth_key_bits(float(d));
}

template <typename T>
__device__ __forceinline__ uint64_t depth_key(int64_t i, const T* depths, const int32_t* depth_rank) {
  return depth_rank ? uint64_t(uint32_t(depth_rank[i])) : uint64_t(depth_bits(depths[i]));
}

// Writes the (tile, depth) keys of large Gaussian i's touched tiles into its segment
// [offsets[i-1], offsets[i]). Threads sharing a Gaussian claim slots through cursor[i]
// (zeroed before), so the order inside a segment varies from run to run; the keys of one
// segment are distinct (one per tile) and the radix sort is stable, so the sorted lists
// are the same as with any fixed order: (tile, depth, id).
template <int kChunk, typename T>
__global__ void __launch_bounds__(kThreads)
    emit_large_kernel(const T* means2d, const T* conics, const T* opacities, const T* depths,
                      const int32_t* radii, const int32_t* depth_rank, const int64_t* cand_ends,
                      int64_t n, BinGeometry g, T alpha_threshold, const int64_t* offsets,
                      int64_t* cursor, uint64_t* keys, int32_t* ids) {
  walk_candidates<kChunk>(
      means2d, conics, opacities, radii, cand_ends, n, g, alpha_threshold,
      [&](int64_t i, const TileTester<T>& t, uint32_t hits, int64_t k0) {
        if (!hits) return;
        int64_t slot = (i == 0 ? 0 : offsets[i - 1]) +
                       int64_t(atomicAdd(reinterpret_cast<unsigned long long*>(cursor + i),
                                         static_cast<unsigned long long>(__popc(hits))));
        const uint64_t dkey = depth_key(i, depths, depth_rank);
        while (hits) {
          const int b = __ffs(hits) - 1;
          hits &= hits - 1;
          keys[slot] = (uint64_t(t.tile(k0 + b, g)) << 32) | dkey;
          ids[slot] = int32_t(i);
          ++slot;
        }
      });
}

// One thread per Gaussian walks its bounding box in row-major order, for the Gaussians with
// at most `small_max` candidate tiles (all of them with TIGER_BIN_SERIAL=1, the former
// binning, kept for same-process comparisons).
template <typename T, typename F>
__device__ void visit_tiles(int64_t i, const TileRect& r, const T* means2d, const T* conics,
                            const T* opacities, const int32_t* radii, const BinGeometry& g,
                            T alpha_threshold, F&& f) {
  TileTester<T> t;
  t.load(i, 0, means2d, conics, opacities, radii, g, alpha_threshold);
  for (int ty = r.y0; ty < r.y1; ++ty)
    for (int tx = r.x0; tx < r.x1; ++tx)
      if (t.touches(tx, ty, g)) f(ty * g.tiles_x + tx);
}

// counts[i] = touched tiles of small Gaussian i, 0 for a large one, whose candidate count goes
// to large_candidates[i] (0 for the small ones; large_candidates may be null when small_max
// covers every Gaussian).
template <typename T>
__global__ void count_small_kernel(const T* means2d, const T* conics, const T* opacities,
                                   const int32_t* radii, int64_t n, BinGeometry g,
                                   T alpha_threshold, int64_t small_max, int64_t* counts,
                                   int64_t* large_candidates) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  const TileRect r = rect_of(i, means2d, radii, g);
  const int64_t cand = r.count();
  int64_t c = 0;
  if (cand > 0 && cand <= small_max)
    visit_tiles(i, r, means2d, conics, opacities, radii, g, alpha_threshold, [&](int) { ++c; });
  counts[i] = c;
  if (large_candidates) large_candidates[i] = cand > small_max ? cand : 0;
}

template <typename T>
__global__ void emit_small_kernel(const T* means2d, const T* conics, const T* opacities,
                                  const T* depths, const int32_t* radii, const int32_t* depth_rank,
                                  int64_t n, BinGeometry g, T alpha_threshold, int64_t small_max,
                                  const int64_t* offsets, uint64_t* keys, int32_t* ids) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  const TileRect r = rect_of(i, means2d, radii, g);
  const int64_t cand = r.count();
  if (cand == 0 || cand > small_max) return;
  int64_t k = i == 0 ? 0 : offsets[i - 1];
  const uint64_t dkey = depth_key(i, depths, depth_rank);
  visit_tiles(i, r, means2d, conics, opacities, radii, g, alpha_threshold, [&](int tile) {
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

// Chunks of 16 candidate tiles per thread by default (faster than 32 on every case measured
// with the all-Gaussians chunking); TIGER_BIN_CHUNK=32 for comparisons.
static bool large_chunks() {
  const char* v = getenv("TIGER_BIN_CHUNK");
  return v != nullptr && v[0] == '3' && v[1] == '2';
}

// A grid that fills the GPU once; the chunked kernels loop over their chunks.
static cudaError_t balanced_grid(int& blocks) {
  int dev = 0, sms = 0;
  cudaError_t err = cudaGetDevice(&dev);
  if (err == cudaSuccess) err = cudaDeviceGetAttribute(&sms, cudaDevAttrMultiProcessorCount, dev);
  blocks = (sms > 0 ? sms : 1) * (2048 / kThreads);
  return err;
}

template <typename T>
cudaError_t bin_count_cuda(const T* means2d, const T* conics, const T* opacities,
                           const int32_t* radii, int64_t n, BinGeometry g, T alpha_threshold,
                           int64_t* counts, int64_t* large_candidates, cudaStream_t stream) {
  if (n == 0) return cudaSuccess;
  const int64_t small_max = large_candidates ? kSmallTiles : INT64_MAX;
  count_small_kernel<T><<<cuda::ceil_div(n, kThreads), kThreads, 0, stream>>>(
      means2d, conics, opacities, radii, n, g, alpha_threshold, small_max, counts,
      large_candidates);
  return cudaGetLastError();
}

template <typename T>
cudaError_t bin_count_large_cuda(const T* means2d, const T* conics, const T* opacities,
                                 const int32_t* radii, const int64_t* cand_ends, int64_t n,
                                 BinGeometry g, T alpha_threshold, int64_t* counts,
                                 cudaStream_t stream) {
  if (n == 0) return cudaSuccess;
  int blocks = 0;
  cudaError_t err = balanced_grid(blocks);
  if (err != cudaSuccess) return err;
  auto kernel = large_chunks() ? count_large_kernel<32, T> : count_large_kernel<16, T>;
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
  const int64_t small_max = cand_ends ? kSmallTiles : INT64_MAX;
  emit_small_kernel<T><<<cuda::ceil_div(n, kThreads), kThreads, 0, stream>>>(
      means2d, conics, opacities, depths, radii, depth_rank, n, g, alpha_threshold, small_max,
      offsets, keys, ids);
  cudaError_t err = cudaGetLastError();
  if (err != cudaSuccess || cand_ends == nullptr) return err;
  int blocks = 0;
  err = balanced_grid(blocks);
  if (err == cudaSuccess) err = cudaMemsetAsync(cursor, 0, sizeof(int64_t) * n, stream);
  if (err != cudaSuccess) return err;
  auto kernel = large_chunks() ? emit_large_kernel<32, T> : emit_large_kernel<16, T>;
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
  template cudaError_t bin_count_cuda<T>(const T*, const T*, const T*, const int32_t*, int64_t,   \
                                         BinGeometry, T, int64_t*, int64_t*, cudaStream_t);       \
  template cudaError_t bin_count_large_cuda<T>(const T*, const T*, const T*, const int32_t*,      \
                                               const int64_t*, int64_t, BinGeometry, T, int64_t*, \
                                               cudaStream_t);                                     \
  template cudaError_t bin_emit_cuda<T>(const T*, const T*, const T*, const T*, const int32_t*,   \
                                        const int32_t*, const int64_t*, int64_t, BinGeometry, T,  \
                                        const int64_t*, int64_t*, uint64_t*, int32_t*, cudaStream_t);
TIGER_INSTANTIATE(float)
TIGER_INSTANTIATE(double)
#undef TIGER_INSTANTIATE

}  // namespace tiger

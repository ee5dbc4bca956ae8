// CUDA tile binning, global-sort path (large scenes; the glue picks the path, binning_cuda.h):
// count (one thread per small Gaussian; the larger ones appended to a compact list) -> count of
// the large ones (one warp, or one block for the giant ones, per Gaussian) -> depth order of the
// Gaussians (radix sort of N depth keys) -> counts in that order, int64 scan -> emit (both
// kinds) of 32-bit tile keys, each Gaussian into its depth-ordered segment -> stable CUB radix
// sort on the tile bits only -> tile ranges. Emitting in depth order and sorting stably by tile
// gives the (tile, depth, id) order of a sort on 64-bit (tile, depth) keys, for a sort over ~13
// key bits instead of ~45 (2 radix passes instead of 6, 8-byte pairs instead of 12) plus one
// sort of N keys. A Gaussian covering thousands of tiles is walked by a whole block (256
// candidates per step), so it does not stall one thread's warp.
#include <cub/device/device_radix_sort.cuh>
#include <cub/device/device_scan.cuh>

#include <stdint.h>
#include <stdlib.h>

#include "bin_walk.cuh"

namespace tiger {
namespace bin_cuda {

// Gaussians with at most kSmallTiles candidate tiles are binned by one thread each, walking
// their box in row-major order. The larger ones go to a compact list (count kernel,
// block-aggregated appends): up to giant_tiles candidates one warp per Gaussian (32 tests per
// step), beyond one block per Gaussian (256 per step). Both walk the candidates in the same
// row-major order as one thread would and emit the hits in that order (ballot + prefix count),
// so a Gaussian's segment is written exactly as by the serial kernel.

// One warp walks the candidates of one Gaussian, 32 per step; emit(slot, tile) gets each hit
// with its rank in row-major order. Returns the number of hits (in every lane). All 32 lanes
// must call it.
template <typename T, typename Emit>
__device__ int64_t warp_walk(const TileTester<T>& t, const BinGeometry& g, Emit&& emit) {
  const int lane = threadIdx.x & 31;
  const unsigned lower = (1u << lane) - 1u;
  const int64_t cand = t.r.count();
  int64_t hits = 0;
  for (int64_t k0 = 0; k0 < cand; k0 += 32) {
    const int64_t k = k0 + lane;
    const int tile = k < cand ? t.test(int(k), g) : -1;
    const unsigned mask = __ballot_sync(cuda::kFullMask, tile >= 0);
    if (tile >= 0) emit(hits + __popc(mask & lower), tile);
    hits += __popc(mask);
  }
  return hits;
}

// The same with the whole block (kThreads threads, 256 candidates per step); every thread of
// the block must call it. warp_hits: kWarps ints of shared memory.
template <typename T, typename Emit>
__device__ int64_t block_walk(const TileTester<T>& t, const BinGeometry& g, int* warp_hits,
                              Emit&& emit) {
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
  const unsigned lower = (1u << lane) - 1u;
  const int64_t cand = t.r.count();
  int64_t hits = 0;
  for (int64_t k0 = 0; k0 < cand; k0 += kThreads) {
    const int64_t k = k0 + threadIdx.x;
    const int tile = k < cand ? t.test(int(k), g) : -1;
    const unsigned mask = __ballot_sync(cuda::kFullMask, tile >= 0);
    if (lane == 0) warp_hits[warp] = __popc(mask);
    __syncthreads();
    int before = 0, step = 0;
#pragma unroll
    for (int w = 0; w < kWarps; ++w) {
      const int h = warp_hits[w];
      before += w < warp ? h : 0;
      step += h;
    }
    if (tile >= 0) emit(hits + before + __popc(mask & lower), tile);
    hits += step;
    __syncthreads();  // warp_hits is rewritten by the next step
  }
  return hits;
}

// Large Gaussians: large_ids[0, counters[0]) one warp each, large_ids[n - counters[1], n) (the
// giant ones) one block each. per_gaussian(i, walk, leader) is called by every thread of the
// warp / block that owns Gaussian i, walk(emit) returning its hits; leader: one thread of them.
template <typename T, typename PerGaussian>
__device__ void for_large(const BinInputs<T>& in, const int32_t* large_ids,
                          const unsigned int* counters, const BinGeometry& g,
                          PerGaussian&& per_gaussian) {
  const int64_t n = in.n;
  __shared__ int warp_hits[kWarps];
  const unsigned int n_warp = counters[0], n_giant = counters[1];
  for (unsigned int j = blockIdx.x; j < n_giant; j += gridDim.x) {  // uniform in the block
    const int64_t i = large_ids[n - 1 - j];
    TileTester<T> t;
    t.load(i, in, g);
    per_gaussian(i, [&](auto&& emit) { return block_walk(t, g, warp_hits, emit); },
                 threadIdx.x == 0);
  }
  const int64_t warps = int64_t(gridDim.x) * kWarps;
  for (int64_t j = int64_t(blockIdx.x) * kWarps + (threadIdx.x >> 5); j < n_warp; j += warps) {
    const int64_t i = large_ids[j];  // uniform in the warp
    TileTester<T> t;
    t.load(i, in, g);
    per_gaussian(i, [&](auto&& emit) { return warp_walk(t, g, emit); },
                 (threadIdx.x & 31) == 0);
  }
}

// counts[i] = touched tiles of large Gaussian i (the rest written by count_small_kernel).
template <typename T>
__global__ void __launch_bounds__(kThreads)
    count_large_kernel(BinInputs<T> in, const int32_t* large_ids, const unsigned int* counters,
                       BinGeometry g, int64_t* counts) {
  for_large(in, large_ids, counters, g,
            [&](int64_t i, auto&& walk, bool leader) {
              const int64_t hits = walk([](int64_t, int) {});
              if (leader) counts[i] = hits;
            });
}

// First entry of Gaussian i's segment: the segments follow the depth order (rank[i]).
__device__ __forceinline__ int64_t segment_start(int64_t i, const int32_t* rank, const int64_t* offsets) {
  const int32_t r = rank[i];
  return r == 0 ? 0 : offsets[r - 1];
}

// Writes the tile keys of large Gaussian i's touched tiles, in row-major order, into its
// segment: the same layout as the serial emit.
template <typename T>
__global__ void __launch_bounds__(kThreads)
    emit_large_kernel(BinInputs<T> in, const int32_t* rank, const int32_t* large_ids,
                      const unsigned int* counters, BinGeometry g, const int64_t* offsets,
                      uint32_t* keys, int32_t* ids) {
  for_large(in, large_ids, counters, g,
            [&](int64_t i, auto&& walk, bool) {
              const int64_t first = segment_start(i, rank, offsets);
              walk([&](int64_t k, int tile) {
                keys[first + k] = uint32_t(tile);
                ids[first + k] = int32_t(i);
              });
            });
}

// One thread per Gaussian walks its bounding box in row-major order, for the Gaussians with
// at most `small_max` candidate tiles (all of them with the op's _serial=True, the former
// binning, kept for same-process comparisons).
template <typename T, typename F>
__device__ void visit_tiles(int64_t i, const TileRect& r, const BinInputs<T>& in,
                            const BinGeometry& g, F&& f) {
  TileTester<T> t;
  t.load(i, in, g);
  for (int ty = r.y0; ty < r.y1; ++ty)
    for (int tx = r.x0; tx < r.x1; ++tx)
      if (t.touches(tx, ty, g)) f(t.tile_id(tx, ty, g));
}

// Appends the block's large Gaussians to large_ids: those for a warp from the front
// (counters[0]), the giant ones from the back (counters[1]); one atomic per list and block.
// Every thread of the block must call it.
__device__ void append_large(bool to_warp, bool to_block, int64_t i, int64_t n,
                             int32_t* large_ids, unsigned int* counters) {
  __shared__ unsigned int warp_base[2][kWarps];
  __shared__ unsigned int block_base[2];
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
  const unsigned mw = __ballot_sync(cuda::kFullMask, to_warp);
  const unsigned mb = __ballot_sync(cuda::kFullMask, to_block);
  if (lane == 0) {
    warp_base[0][warp] = __popc(mw);
    warp_base[1][warp] = __popc(mb);
  }
  __syncthreads();
  if (threadIdx.x < 2) {
    unsigned int total = 0;
    for (int w = 0; w < kWarps; ++w) {
      const unsigned int c = warp_base[threadIdx.x][w];
      warp_base[threadIdx.x][w] = total;
      total += c;
    }
    block_base[threadIdx.x] = total ? atomicAdd(counters + threadIdx.x, total) : 0u;
  }
  __syncthreads();
  const unsigned lower = (1u << lane) - 1u;
  if (to_warp) large_ids[block_base[0] + warp_base[0][warp] + __popc(mw & lower)] = int32_t(i);
  if (to_block)
    large_ids[n - 1 - (block_base[1] + warp_base[1][warp] + __popc(mb & lower))] = int32_t(i);
}

// counts[i] = touched tiles of small Gaussian i, 0 for a large one, which is appended to
// large_ids (large_ids == nullptr: every Gaussian is small, the former binning).
template <typename T>
__global__ void __launch_bounds__(kThreads)
    count_small_kernel(BinInputs<T> in, BinGeometry g, int64_t giant_tiles, int64_t* counts,
                       int32_t* large_ids, unsigned int* counters) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  const int64_t n = in.n;
  const int64_t small_max = large_ids ? kSmallTiles : INT64_MAX;
  int64_t cand = 0;
  if (i < n) {
    const TileRect r = rect_of(i, in.means2d, in.radii, g);
    cand = r.count();
    int64_t c = 0;
    if (cand > 0 && cand <= small_max)
      visit_tiles(i, r, in, g, [&](int) { ++c; });
    counts[i] = c;
  }
  if (large_ids)  // uniform: every thread of the block takes part
    append_large(cand > small_max && cand <= giant_tiles, cand > giant_tiles, i, n, large_ids,
                 counters);
}

// Thread j takes the j-th Gaussian of the depth order: neighbouring threads fill neighbouring
// segments, so the key/id stores of a warp land together (by Gaussian index they scattered over
// the whole list: twice the emit time on the 1M standard scene); the geometry reads gather.
template <typename T>
__global__ void emit_small_kernel(BinInputs<T> in, const int32_t* order, BinGeometry g,
                                  int64_t small_max, const int64_t* offsets, uint32_t* keys,
                                  int32_t* ids) {
  const int64_t j = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (j >= in.n) return;
  const int64_t i = order[j];
  const TileRect r = rect_of(i, in.means2d, in.radii, g);
  const int64_t cand = r.count();
  if (cand == 0 || cand > small_max) return;
  int64_t k = j == 0 ? 0 : offsets[j - 1];
  visit_tiles(i, r, in, g, [&](int tile) {
    keys[k] = uint32_t(tile);
    ids[k] = int32_t(i);
    ++k;
  });
}

// tile_offsets[t] = first sorted index whose tile is >= t; tile_offsets[n_tiles] = m.
__global__ void ranges_kernel(const uint32_t* keys, int64_t m, int64_t n_tiles,
                              int64_t* tile_offsets) {
  const int64_t k = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (k >= m) return;
  const int64_t tile = int64_t(keys[k]);
  const int64_t prev = k == 0 ? -1 : int64_t(keys[k - 1]);
  for (int64_t t = prev + 1; t <= tile; ++t) tile_offsets[t] = k;
  if (k == m - 1)
    for (int64_t t = tile + 1; t <= n_tiles; ++t) tile_offsets[t] = m;
}

// Order-preserving unsigned keys of the depths (float: 32 bits, double: 64) and ids 0..n-1.
template <typename T>
__global__ void depth_keys_kernel(const T* depths, int64_t n, DepthKey<T>* keys, int32_t* ids) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  if constexpr (sizeof(T) == 4)
    keys[i] = cuda::depth_key_bits(float(depths[i]));
  else
    keys[i] = cuda::depth_key_bits64(double(depths[i]));
  ids[i] = int32_t(i);
}

// counts_in_order[k] = counts[order[k]] (for the scan that places the segments in depth order;
// skipped without counts) and rank[order[k]] = k.
__global__ void order_counts_kernel(const int32_t* order, const int64_t* counts, int64_t n,
                                    int64_t* counts_in_order, int32_t* rank) {
  const int64_t k = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (k >= n) return;
  const int32_t i = order[k];
  if (counts) counts_in_order[k] = counts[i];
  rank[i] = int32_t(k);
}

}  // namespace bin_cuda
using namespace bin_cuda;

template <typename T>
cudaError_t bin_count_cuda(const BinInputs<T>& in, BinGeometry g, int64_t giant_tiles,
                           int64_t* counts, int32_t* large_ids, unsigned int* large_counters,
                           cudaStream_t stream) {
  const int64_t n = in.n;
  if (n == 0) return cudaSuccess;
  if (large_ids) {
    const cudaError_t err = cudaMemsetAsync(large_counters, 0, 2 * sizeof(unsigned int), stream);
    if (err != cudaSuccess) return err;
  }
  count_small_kernel<T><<<cuda::ceil_div(n, kThreads), kThreads, 0, stream>>>(
      in, g, giant_tiles, counts, large_ids, large_counters);
  cudaError_t err = cudaGetLastError();
  if (err != cudaSuccess || large_ids == nullptr) return err;
  int blocks = 0;
  err = bin_full_grid(blocks);
  if (err != cudaSuccess) return err;
  count_large_kernel<T><<<blocks, kThreads, 0, stream>>>(in, large_ids, large_counters, g,
                                                         counts);
  return cudaGetLastError();
}

template <typename T>
cudaError_t bin_depth_order_cuda(void* temp, size_t& temp_bytes, const T* depths, int64_t n,
                                 DepthKey<T>* keys, DepthKey<T>* keys_alt, int32_t* ids,
                                 int32_t* ids_alt, int32_t** order, cudaStream_t stream) {
  cub::DoubleBuffer<DepthKey<T>> k(keys, keys_alt);
  cub::DoubleBuffer<int32_t> v(ids, ids_alt);
  if (temp == nullptr)
    return cub::DeviceRadixSort::SortPairs(nullptr, temp_bytes, k, v, n, 0,
                                           int(8 * sizeof(DepthKey<T>)), stream);
  if (n == 0) return cudaSuccess;
  depth_keys_kernel<T><<<cuda::ceil_div(n, kThreads), kThreads, 0, stream>>>(depths, n, keys, ids);
  cudaError_t err = cudaGetLastError();
  if (err != cudaSuccess) return err;
  err = cub::DeviceRadixSort::SortPairs(temp, temp_bytes, k, v, n, 0, int(8 * sizeof(DepthKey<T>)),
                                        stream);
  *order = v.Current();
  return err;
}

cudaError_t bin_order_counts_cuda(const int32_t* order, const int64_t* counts, int64_t n,
                                  int64_t* counts_in_order, int32_t* rank, cudaStream_t stream) {
  if (n == 0) return cudaSuccess;
  order_counts_kernel<<<cuda::ceil_div(n, kThreads), kThreads, 0, stream>>>(order, counts, n,
                                                                           counts_in_order, rank);
  return cudaGetLastError();
}

cudaError_t bin_scan_cuda(void* temp, size_t& temp_bytes, const int64_t* counts, int64_t* offsets,
                          int64_t n, cudaStream_t stream) {
  return cub::DeviceScan::InclusiveSum(temp, temp_bytes, counts, offsets, n, stream);
}

template <typename T>
cudaError_t bin_emit_cuda(const BinInputs<T>& in, const int32_t* order, const int32_t* rank,
                          const int32_t* large_ids, const unsigned int* large_counters,
                          BinGeometry g, const int64_t* offsets, uint32_t* keys, int32_t* ids,
                          cudaStream_t stream) {
  const int64_t n = in.n;
  if (n == 0) return cudaSuccess;
  const int64_t small_max = large_ids ? kSmallTiles : INT64_MAX;
  emit_small_kernel<T><<<cuda::ceil_div(n, kThreads), kThreads, 0, stream>>>(
      in, order, g, small_max, offsets, keys, ids);
  cudaError_t err = cudaGetLastError();
  if (err != cudaSuccess || large_ids == nullptr) return err;
  int blocks = 0;
  err = bin_full_grid(blocks);
  if (err != cudaSuccess) return err;
  emit_large_kernel<T><<<blocks, kThreads, 0, stream>>>(in, rank, large_ids, large_counters, g,
                                                        offsets, keys, ids);
  return cudaGetLastError();
}

cudaError_t bin_sort_cuda(void* temp, size_t& temp_bytes, uint32_t* keys, uint32_t* keys_alt,
                          int32_t* ids, int32_t* ids_alt, int64_t m, int end_bit,
                          uint32_t** keys_out, int32_t** ids_out, cudaStream_t stream) {
  cub::DoubleBuffer<uint32_t> k(keys, keys_alt);
  cub::DoubleBuffer<int32_t> v(ids, ids_alt);
  const cudaError_t err =
      cub::DeviceRadixSort::SortPairs(temp, temp_bytes, k, v, m, 0, end_bit, stream);
  if (keys_out) *keys_out = k.Current();
  if (ids_out) *ids_out = v.Current();
  return err;
}

cudaError_t bin_ranges_cuda(const uint32_t* sorted_keys, int64_t m, int64_t n_tiles,
                            int64_t* tile_offsets, cudaStream_t stream) {
  if (m == 0) return cudaMemsetAsync(tile_offsets, 0, sizeof(int64_t) * (n_tiles + 1), stream);
  ranges_kernel<<<cuda::ceil_div(m, kThreads), kThreads, 0, stream>>>(sorted_keys, m, n_tiles,
                                                                      tile_offsets);
  return cudaGetLastError();
}

#define TIGER_INSTANTIATE(T)                                                                     \
  template cudaError_t bin_count_cuda<T>(const BinInputs<T>&, BinGeometry, int64_t, int64_t*,    \
                                         int32_t*, unsigned int*, cudaStream_t);                 \
  template cudaError_t bin_depth_order_cuda<T>(void*, size_t&, const T*, int64_t, DepthKey<T>*,  \
                                               DepthKey<T>*, int32_t*, int32_t*, int32_t**,      \
                                               cudaStream_t);                                    \
  template cudaError_t bin_emit_cuda<T>(const BinInputs<T>&, const int32_t*, const int32_t*,     \
                                        const int32_t*, const unsigned int*, BinGeometry,        \
                                        const int64_t*, uint32_t*, int32_t*, cudaStream_t);
TIGER_INSTANTIATE(float)
TIGER_INSTANTIATE(double)
#undef TIGER_INSTANTIATE

}  // namespace tiger

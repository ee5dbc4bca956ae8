// CUDA tile binning, per-tile path (smaller scenes; steps in binning_cuda.h): a counting sort
// by tile. Every hit of the exact ellipse-tile test is counted into its tile, the counts
// scanned, and the same walk again drops each hit's 64-bit (depth, id) key into its tile's
// range; each range is then sorted on its own (a warp per short list, a block per long one).
// Against the global-sort path (a depth sort of the Gaussians plus a stable radix sort of the
// hits by tile) this launches no radix pass over all keys: on a real scene at 1080p (25,784 Gaussians, 332,605 hits) the two CUB sorts alone
// took 77 us of a 139 us binning, mostly launch latency. The hits need no order before the
// per-tile sort, so a large Gaussian's candidate tiles are cut into chunks of kChunkTiles that
// any warp can walk: the few Gaussians covering thousands of tiles cost no more than the same
// number of small ones.
#include <cub/block/block_merge_sort.cuh>
#include <cub/block/block_scan.cuh>
#include <cub/device/device_scan.cuh>

#include <stdint.h>

#include "bin_walk.cuh"

namespace tiger {
namespace bin_cuda {

// Gaussians with more than kSmallTiles candidates are walked by warps, kChunkTiles candidates
// (4 steps of 32) per chunk (chunks of 32 were slower: 24 -> 48 us for the count of the 4K real
// scene, more owner searches per tested tile).
constexpr int kChunkTiles = 128;
// The chunk counter's fields: chunks in the low kChunkBits bits, list slots above.
constexpr int kChunkBits = 33;
constexpr unsigned long long kChunkMask = (1ull << kChunkBits) - 1ull;

// The key a hit of Gaussian i sorts by within its tile: depth order in the high word (the
// order-preserving float32 bits, or the float64 depth rank), the id in the low word.
template <typename T>
__device__ __forceinline__ uint64_t sort_key(int64_t i, const BinInputs<T>& in) {
  uint32_t depth;
  if constexpr (sizeof(T) == 4)
    depth = cuda::depth_key_bits(in.depths[i]);
  else
    depth = uint32_t(in.depth_rank[i]);
  return (uint64_t(depth) << 32) | uint32_t(i);
}

// What a hit does: counted into its tile, or (emit) its key dropped into a free slot of the
// tile's range, the count running back down to zero (the slots' order is the sort's business).
struct HitSink {
  unsigned long long* tile_counts;
  const int64_t* tile_offsets;
  uint64_t* keys;

  __device__ __forceinline__ void count(int tile) const { atomicAdd(tile_counts + tile, 1ull); }
  __device__ __forceinline__ void emit(int tile, uint64_t key) const {
    const unsigned long long left = atomicAdd(tile_counts + tile, ~0ull);  // -1
    keys[tile_offsets[tile] + int64_t(left) - 1] = key;
  }
};

// Lists the block's large Gaussians (their chunks claimed with one atomic per block, so the
// chunk bases ascend with the slots). Every thread of the block must call it.
__device__ void list_large(bool large, int64_t i, int64_t chunks_of_i, const BinChunks& list) {
  using Scan = cub::BlockScan<unsigned long long, kThreads>;
  __shared__ typename Scan::TempStorage scan_temp;
  __shared__ unsigned long long block_base;
  if (!__syncthreads_or(large)) return;  // uniform
  const unsigned long long mine =
      large ? (1ull << kChunkBits) | static_cast<unsigned long long>(chunks_of_i) : 0ull;
  unsigned long long before = 0, total = 0;
  Scan(scan_temp).ExclusiveSum(mine, before, total);
  if (threadIdx.x == 0) block_base = atomicAdd(list.counter, total);
  __syncthreads();
  if (large) {
    const unsigned long long at = block_base + before;
    const int64_t slot = int64_t(at >> kChunkBits);
    list.ids[slot] = int32_t(i);
    list.chunk_base[slot] = int64_t(at & kChunkMask);
  }
}

// Threads per small Gaussian in the count and the emit: a real scene at 1080p has ~26k
// Gaussians, under one block per SM with one thread each, so their candidates (up to
// kSmallTiles) are shared by several threads; the emit's hits each wait for their slot (an
// atomic with return), so it takes more (one thread: 24 us, four: 10 us).
constexpr int kCountLanes = 4;
constexpr int kEmitLanes = 8;

// Threads of one small Gaussian walk its box in row-major order, thread `lane` of `lanes` the
// candidates k = lane, lane + lanes, ...; the count lists the large ones (all are small without
// a list: the former walk).
template <typename T, bool kEmit>
__global__ void __launch_bounds__(kThreads)
    small_kernel(BinInputs<T> in, BinGeometry g, HitSink sink, BinChunks list, bool listing) {
  constexpr int lanes = kEmit ? kEmitLanes : kCountLanes;
  const int64_t thread = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  const int64_t i = thread / lanes;
  const int lane = int(thread % lanes);
  const int64_t small_max = listing ? kSmallTiles : INT64_MAX;
  int64_t cand = 0;
  if (i < in.n) {
    const TileRect r = rect_of(i, in.means2d, in.radii, g);
    cand = r.count();
    if (cand > 0 && cand <= small_max) {
      TileTester<T> t;
      t.load(i, in, g);
      const uint64_t key = kEmit ? sort_key(i, in) : 0;
      const int w = r.width();
      int row = lane / w, col = lane - (lane / w) * w;
      for (int64_t k = lane; k < cand; k += lanes) {
        const int tx = r.x0 + col, ty = r.y0 + row;
        if (t.touches(tx, ty, g)) {
          if constexpr (kEmit)
            sink.emit(t.tile_id(tx, ty, g), key);
          else
            sink.count(t.tile_id(tx, ty, g));
        }
        for (col += lanes; col >= w; col -= w) ++row;
      }
    }
  }
  if (!kEmit && listing)  // uniform: every thread of the block takes part; lane 0 lists
    list_large(lane == 0 && cand > small_max, i, (cand + kChunkTiles - 1) / kChunkTiles, list);
}

// The slot of the listed Gaussian that owns chunk q: the last s with chunk_base[s] <= q
// (chunk_base[0] = 0). A 32-way search by the whole warp: about log32 of the list's length
// dependent loads instead of log2.
__device__ __forceinline__ int64_t owner_of_chunk(int64_t q, const int64_t* chunk_base,
                                                  int64_t listed) {
  const int lane = threadIdx.x & 31;
  int64_t lo = 0, hi = listed;
  while (hi - lo > 1) {
    const int64_t stride = (hi - lo + 31) / 32;
    const int64_t s = lo + lane * stride;
    const unsigned below = __ballot_sync(cuda::kFullMask, s < hi && chunk_base[s] <= q);
    lo += int64_t(31 - __clz(below)) * stride;  // lane 0's s = lo always qualifies
    hi = min(lo + stride, hi);
  }
  return lo;
}

// One warp per chunk of a listed Gaussian's candidates (grid-stride over all chunks).
template <typename T, bool kEmit>
__global__ void __launch_bounds__(kThreads)
    chunk_kernel(BinInputs<T> in, BinGeometry g, HitSink sink, BinChunks list) {
  const unsigned long long packed = *list.counter;
  const int64_t listed = int64_t(packed >> kChunkBits), chunks = int64_t(packed & kChunkMask);
  const int lane = threadIdx.x & 31;
  const int64_t warps = int64_t(gridDim.x) * kWarps;
  for (int64_t q = int64_t(blockIdx.x) * kWarps + (threadIdx.x >> 5); q < chunks; q += warps) {
    const int64_t s = owner_of_chunk(q, list.chunk_base, listed);  // uniform in the warp
    const int64_t i = list.ids[s];
    TileTester<T> t;
    t.load(i, in, g);
    const int64_t first = (q - list.chunk_base[s]) * kChunkTiles;
    const int64_t end = min(first + kChunkTiles, t.r.count());
    const uint64_t key = kEmit ? sort_key(i, in) : 0;
    for (int64_t k = first + lane; k < end; k += 32) {
      const int tile = t.test(int(k), g);
      if (tile < 0) continue;
      if constexpr (kEmit)
        sink.emit(tile, key);
      else
        sink.count(tile);
    }
  }
}

// The per-tile sorts, in size classes (a sort works on its whole capacity, so a list is sorted
// by the smallest class that holds it): one warp up to kWarpSortKeys keys, a bitonic network in
// registers (shuffles, no shared memory: CUB's warp merge sort took ~10 us per warp there, its
// shared-memory merges bank-conflicted with 8-byte keys), and the block up to kBinSortKeysMax,
// CUB merge sorts. The keys are distinct (the id is in them); padding keys (all ones) sort last
// and are not written.
constexpr uint64_t kPadKey = ~0ull;
struct KeyLess {
  __device__ __forceinline__ bool operator()(uint64_t a, uint64_t b) const { return a < b; }
};
template <int kItems>
using BlockSort = cub::BlockMergeSort<uint64_t, kThreads, kItems>;
static_assert(kBinSortKeysMax == 16 * kThreads, "the largest block class holds kBinSortKeysMax");

union SortTemp {
  typename BlockSort<2>::TempStorage b2;
  typename BlockSort<4>::TempStorage b4;
  typename BlockSort<8>::TempStorage b8;
  typename BlockSort<16>::TempStorage b16;
};

// Bitonic sort of the 32 * kItems keys of a warp, position it * 32 + lane in k[it] (striped):
// partners closer than 32 positions are in other lanes (shuffle), farther ones in the same lane.
template <int kItems>
__device__ __forceinline__ void warp_bitonic(uint64_t (&k)[kItems], int lane) {
  constexpr int kKeys = 32 * kItems;
#pragma unroll
  for (int size = 2; size <= kKeys; size <<= 1) {
#pragma unroll
    for (int j = size >> 1; j > 0; j >>= 1) {
#pragma unroll
      for (int it = 0; it < kItems; ++it) {
        const bool ascending = ((it * 32 + lane) & size) == 0;
        if (j >= 32) {
          const int other = it ^ (j / 32);
          if (other > it && (k[it] > k[other]) == ascending) {
            const uint64_t t = k[it];
            k[it] = k[other];
            k[other] = t;
          }
        } else {
          const uint64_t theirs = __shfl_xor_sync(cuda::kFullMask, k[it], j);
          const bool keep_min = ((lane & j) == 0) == ascending;
          k[it] = keep_min ? (theirs < k[it] ? theirs : k[it]) : (theirs > k[it] ? theirs : k[it]);
        }
      }
    }
  }
}

template <int kItems, typename Out>
__device__ __forceinline__ void warp_sort_class(const uint64_t* src, int64_t len, int lane,
                                                Out&& out) {
  uint64_t k[kItems];
#pragma unroll
  for (int it = 0; it < kItems; ++it) {
    const int x = it * 32 + lane;
    k[it] = x < len ? src[x] : kPadKey;
  }
  warp_bitonic(k, lane);
#pragma unroll
  for (int it = 0; it < kItems; ++it) {
    const int x = it * 32 + lane;
    if (x < len) out(x, k[it]);
  }
}

// Sorts src[0, len <= kWarpSortKeys) by one warp (every lane calls it).
template <typename Out>
__device__ void warp_sort_list(const uint64_t* src, int64_t len, Out&& out) {
  const int lane = threadIdx.x & 31;
  if (len <= 32)
    warp_sort_class<1>(src, len, lane, out);
  else if (len <= 64)
    warp_sort_class<2>(src, len, lane, out);
  else if (len <= 128)
    warp_sort_class<4>(src, len, lane, out);
  else
    warp_sort_class<8>(src, len, lane, out);
}

template <int kItems>
__device__ __forceinline__ typename BlockSort<kItems>::TempStorage& temp_of(SortTemp& t) {
  if constexpr (kItems == 2) return t.b2;
  else if constexpr (kItems == 4) return t.b4;
  else if constexpr (kItems == 8) return t.b8;
  else return t.b16;
}

// src[0, len) (len <= kItems * kThreads) sorted by the block, each key handed to
// out(position, key). Loads are striped (coalesced); the sorted keys come blocked.
template <int kItems, typename Out>
__device__ __forceinline__ void block_sort_class(const uint64_t* src, int64_t len, SortTemp& temp,
                                                 Out&& out) {
  uint64_t k[kItems];
#pragma unroll
  for (int it = 0; it < kItems; ++it) {
    const int64_t x = int64_t(it) * kThreads + threadIdx.x;
    k[it] = x < len ? src[x] : kPadKey;
  }
  BlockSort<kItems>(temp_of<kItems>(temp)).Sort(k, KeyLess{});
#pragma unroll
  for (int it = 0; it < kItems; ++it) {
    const int64_t x = int64_t(threadIdx.x) * kItems + it;
    if (x < len) out(x, k[it]);
  }
}

// Sorts src[0, len <= kBinSortKeysMax) by the smallest class that holds it: warp 0 alone up to
// kWarpSortKeys, else the block. Every thread of the block must call it (uniform len); temp is
// reused only after a barrier.
template <typename Out>
__device__ void sort_list(const uint64_t* src, int64_t len, SortTemp& temp, Out&& out) {
  if (len <= kWarpSortKeys) {
    if (threadIdx.x < 32) warp_sort_list(src, len, out);
  } else if (len <= 2 * kThreads) {
    block_sort_class<2>(src, len, temp, out);
  } else if (len <= 4 * kThreads) {
    block_sort_class<4>(src, len, temp, out);
  } else if (len <= 8 * kThreads) {
    block_sort_class<8>(src, len, temp, out);
  } else {
    block_sort_class<16>(src, len, temp, out);
  }
}

// Index of the first key of a[0, len) that is >= key.
__device__ __forceinline__ int64_t lower_bound(const uint64_t* a, int64_t len, uint64_t key) {
  int64_t lo = 0;
  while (len > 0) {
    const int64_t half = len >> 1;
    if (a[lo + half] < key) {
      lo += half + 1;
      len -= half + 1;
    } else {
      len = half;
    }
  }
  return lo;
}

// Most tiles' lists are short (a real scene at 1080p: 54 keys on average): one warp per tile,
// kWarps tiles per block, sorts those of up to kWarpSortKeys (and sort_keys) keys and lists the
// longer ones in large_tiles for sort_large_tiles_kernel (a block per short tile left 7 of its
// 8 warps idle, and 9 waves of such blocks took 27 us there).
__global__ void __launch_bounds__(kThreads)
    sort_small_tiles_kernel(const int64_t* tile_offsets, int64_t n_tiles, const uint64_t* keys,
                            int warp_keys, int32_t* ids, int32_t* large_tiles,
                            unsigned long long* n_large) {
  const int warp = threadIdx.x >> 5, lane = threadIdx.x & 31;
  const int64_t t = int64_t(blockIdx.x) * kWarps + warp;
  if (t >= n_tiles) return;  // uniform in the warp; no block barrier below
  const int64_t begin = tile_offsets[t], len = tile_offsets[t + 1] - begin;
  if (len > warp_keys) {
    if (lane == 0) large_tiles[atomicAdd(n_large, 1ull)] = int32_t(t);
    return;
  }
  int32_t* out = ids + begin;
  if (len == 1 && lane == 0) out[0] = int32_t(uint32_t(keys[begin]));
  if (len <= 1) return;
  warp_sort_list(keys + begin, len,
                 [out](int64_t x, uint64_t key) { out[x] = int32_t(uint32_t(key)); });
}

// One block per listed long tile (grid-stride over the list): the list sorted at once up to
// sort_keys keys; a longer one in runs of sort_keys, which are then merged pairwise between keys
// and keys_alt (each key placed at its rank: its index in its run plus the number of smaller
// keys in the other run).
__global__ void __launch_bounds__(kThreads)
    sort_large_tiles_kernel(const int64_t* tile_offsets, uint64_t* keys, uint64_t* keys_alt,
                            int sort_keys, int32_t* ids, const int32_t* large_tiles,
                            const unsigned long long* n_large) {
  __shared__ SortTemp temp;
  const int64_t listed = int64_t(*n_large);
  for (int64_t j = blockIdx.x; j < listed; j += gridDim.x) {
    const int32_t t = large_tiles[j];
    const int64_t begin = tile_offsets[t];
    const int64_t len = tile_offsets[t + 1] - begin;
    uint64_t* src = keys + begin;
    int32_t* out = ids + begin;
    const auto write_id = [out](int64_t x, uint64_t key) { out[x] = int32_t(uint32_t(key)); };
    __syncthreads();  // temp and the previous tile's buffers are free
    if (len <= sort_keys) {
      sort_list(src, len, temp, write_id);
      continue;
    }
    for (int64_t r0 = 0; r0 < len; r0 += sort_keys) {
      uint64_t* run = src + r0;
      sort_list(run, min(int64_t(sort_keys), len - r0), temp,
                [run](int64_t x, uint64_t key) { run[x] = key; });
      __syncthreads();  // temp is reused by the next run; the runs are read by the merges
    }
    uint64_t* dst = keys_alt + begin;
    for (int64_t w = sort_keys; w < len; w *= 2) {
      for (int64_t a0 = 0; a0 < len; a0 += 2 * w) {
        const int64_t b0 = min(a0 + w, len), b1 = min(a0 + 2 * w, len);
        for (int64_t x = a0 + threadIdx.x; x < b1; x += kThreads) {
          const uint64_t key = src[x];
          const int64_t at = x < b0 ? (x - a0) + lower_bound(src + b0, b1 - b0, key)
                                    : (x - b0) + lower_bound(src + a0, b0 - a0, key);
          dst[a0 + at] = key;
        }
      }
      __syncthreads();  // the block's global writes are visible to it after the barrier
      uint64_t* tmp = src;
      src = dst;
      dst = tmp;
    }
    for (int64_t x = threadIdx.x; x < len; x += kThreads) write_id(x, src[x]);
  }
}

}  // namespace bin_cuda
using namespace bin_cuda;

template <typename T>
cudaError_t bin_tiles_cuda(const BinInputs<T>& in, BinGeometry g, bool emit,
                           unsigned long long* tile_counts, const int64_t* tile_offsets,
                           uint64_t* keys, const BinChunks* chunks, cudaStream_t stream) {
  if (in.n == 0) return cudaSuccess;
  const HitSink sink{tile_counts, tile_offsets, keys};
  const BinChunks list = chunks ? *chunks : BinChunks{nullptr, nullptr, nullptr};
  if (emit)
    small_kernel<T, true><<<cuda::ceil_div(in.n * kEmitLanes, kThreads), kThreads, 0, stream>>>(
        in, g, sink, list, chunks != nullptr);
  else
    small_kernel<T, false><<<cuda::ceil_div(in.n * kCountLanes, kThreads), kThreads, 0, stream>>>(
        in, g, sink, list, chunks != nullptr);
  cudaError_t err = cudaGetLastError();
  if (err != cudaSuccess || chunks == nullptr) return err;
  int blocks = 0;
  err = bin_full_grid(blocks);
  if (err != cudaSuccess) return err;
  if (emit)
    chunk_kernel<T, true><<<blocks, kThreads, 0, stream>>>(in, g, sink, list);
  else
    chunk_kernel<T, false><<<blocks, kThreads, 0, stream>>>(in, g, sink, list);
  return cudaGetLastError();
}

cudaError_t bin_offsets_cuda(void* temp, size_t& temp_bytes, const unsigned long long* counts,
                             int64_t* tile_offsets, int64_t n_tiles, cudaStream_t stream) {
  return cub::DeviceScan::ExclusiveSum(temp, temp_bytes, counts,
                                       reinterpret_cast<unsigned long long*>(tile_offsets),
                                       n_tiles + 1, stream);
}

cudaError_t bin_sort_tiles_cuda(const int64_t* tile_offsets, int64_t n_tiles, uint64_t* keys,
                                uint64_t* keys_alt, int sort_keys, int warp_keys, int32_t* ids,
                                int32_t* large_tiles, unsigned long long* n_large,
                                cudaStream_t stream) {
  if (n_tiles == 0) return cudaSuccess;
  if (sort_keys < 2 || sort_keys > kBinSortKeysMax || (sort_keys & (sort_keys - 1)) != 0 ||
      warp_keys < 1 || warp_keys > kWarpSortKeys)
    return cudaErrorInvalidValue;
  sort_small_tiles_kernel<<<cuda::ceil_div(n_tiles, kWarps), kThreads, 0, stream>>>(
      tile_offsets, n_tiles, keys, min(warp_keys, sort_keys), ids, large_tiles, n_large);
  cudaError_t err = cudaGetLastError();
  int blocks = 0;
  if (err == cudaSuccess) err = bin_full_grid(blocks);
  if (err != cudaSuccess) return err;
  sort_large_tiles_kernel<<<blocks, kThreads, 0, stream>>>(tile_offsets, keys, keys_alt,
                                                           sort_keys, ids, large_tiles, n_large);
  return cudaGetLastError();
}

#define TIGER_INSTANTIATE(T)                                                                   \
  template cudaError_t bin_tiles_cuda<T>(const BinInputs<T>&, BinGeometry, bool,               \
                                         unsigned long long*, const int64_t*, uint64_t*,       \
                                         const BinChunks*, cudaStream_t);
TIGER_INSTANTIATE(float)
TIGER_INSTANTIATE(double)
#undef TIGER_INSTANTIATE

}  // namespace tiger

#pragma once
// Raw-pointer pieces of the CUDA tile binning (no torch headers). The glue allocates every
// buffer through torch (caching allocator) and runs one of two paths on one stream; both give
// every tile's Gaussians sorted by (depth, id), identical lists.
//
// Per-tile path (binning_tiles_cuda.cu; by default scenes of up to kBinTilePathMaxGaussians Gaussians,
// where the device-wide radix sorts of the other path are mostly launch latency):
//   1. bin_tiles_cuda(count): every hit (Gaussian, touched tile; exact ellipse-tile test) adds
//      one to its tile's count. One thread walks a Gaussian with at most kSmallTiles candidate
//      (bounding-box) tiles; the larger ones are listed (BinChunks) and their candidates walked
//      in chunks of 32, one warp per chunk, whatever the Gaussian's size
//   2. bin_offsets_cuda: exclusive int64 scan of the tile counts -> tile_offsets [tiles + 1]
//   3. bin_tiles_cuda(emit): the same walk; each hit takes a slot of its tile's range (the
//      count counted back down to zero) and writes its 64-bit sort key there: depth key in the
//      high word (float32 depth bits; float64: the Gaussian's rank in the depth order, from
//      bin_depth_order_cuda and bin_order_counts_cuda), Gaussian id in the low word
//   4. bin_sort_tiles_cuda: each tile's keys sorted (one warp per tile up to 256 keys, a
//      bitonic network in registers; one block per longer list up to sort_keys, CUB merge
//      sorts; longer ones as sorted runs merged in global memory) and the ids written
//
// Global-sort path (binning_global_cuda.cu; larger scenes, whose long tile lists a device-wide
// radix sort orders at memory speed):
//   1. bin_count_cuda: per-Gaussian number of touched tiles -> int64: one thread per Gaussian
//      for those with at most kSmallTiles candidates; the larger ones are appended to large_ids
//      (n int32 of scratch; counts in large_counters, 2 uint32) and counted by one warp each,
//      or one block each beyond giant_tiles candidates
//   2. bin_depth_order_cuda: the Gaussians' stable depth order (radix sort of N order-preserving
//      depth keys: 32 bits for float, 64 for double)
//   3. bin_order_counts_cuda: the counts in that order, and each Gaussian's rank in it
//   4. bin_scan_cuda: inclusive int64 scan of the ordered counts (segment ends; total = last)
//   5. bin_emit_cuda: 32-bit tile keys and Gaussian ids (both kinds), each Gaussian's hits in
//      row-major order in its segment, the segments in depth order
//   6. bin_sort_cuda: stable CUB radix sort of (tile, id) over the bits the tile count needs,
//      which leaves each tile's Gaussians in depth order (ties by id)
//   7. bin_ranges_cuda: tile_offsets [tiles+1] int64 from the sorted keys
//
// Without a list of large Gaussians (chunks / large_ids == nullptr) every Gaussian is walked
// by one thread: the former walk, kept for comparisons (the op's _serial=True).
#include <cuda_runtime_api.h>
#include <stddef.h>
#include <stdint.h>

#include <type_traits>

#include "binning_choices.h"

namespace tiger {

// One image's size and tile grid (every image of a views > 1 call has the same).
struct BinGeometry {
  int width, height, tile_size, tiles_x, tiles_y;
};

template <typename T>
struct BinInputs {
  const T* means2d;          // [n, 2]
  const T* conics;           // [n, 3]
  const T* opacities;        // [n]
  const T* depths;           // [n]
  const int32_t* radii;      // [n, 2]
  const int32_t* depth_rank; // [n]: per-tile path with float64 depths, else unused
  int64_t n;
  T alpha_threshold;
  // Gaussians per image (bin_gaussians(views=V): n / V; n for one image): Gaussian i is listed
  // only in the tiles of image i / per_view, which follow the tiles of the images before it.
  int64_t per_view;
};

// ---- per-tile path ----

// The listed large Gaussians: ids[s] and the first of their chunks, chunk_base[s] (ascending
// in s), both claimed by one 64-bit atomic on *counter: slots in bits 33.., chunks in bits 0..32.
struct BinChunks {
  int32_t* ids;                // [n]
  int64_t* chunk_base;         // [n]
  unsigned long long* counter; // 1, zero before the count
};

// emit == false: tile_counts [tiles] (zero before) += hits, and the chunk list is filled.
// emit == true: tile_counts counted back to zero, keys [m] written at tile_offsets.
template <typename T>
cudaError_t bin_tiles_cuda(const BinInputs<T>& in, BinGeometry g, bool emit,
                           unsigned long long* tile_counts, const int64_t* tile_offsets,
                           uint64_t* keys, const BinChunks* chunks, cudaStream_t stream);

// temp == nullptr: writes the needed temp_bytes and returns. counts has tiles + 1 entries, the
// last one zero; tile_offsets [tiles + 1].
cudaError_t bin_offsets_cuda(void* temp, size_t& temp_bytes, const unsigned long long* counts,
                             int64_t* tile_offsets, int64_t n_tiles, cudaStream_t stream);

// Sorts every tile's keys; ids [m] = their low words. keys_alt [m]: scratch of lists longer
// than sort_keys (a power of two in [2, kBinSortKeysMax]). Lists of up to warp_keys keys are
// sorted by one warp each; the longer ones are listed in large_tiles [tiles] (count in
// *n_large, zero before) and sorted by one block each.
cudaError_t bin_sort_tiles_cuda(const int64_t* tile_offsets, int64_t n_tiles, uint64_t* keys,
                                uint64_t* keys_alt, int sort_keys, int warp_keys, int32_t* ids,
                                int32_t* large_tiles, unsigned long long* n_large,
                                cudaStream_t stream);

// ---- global-sort path ----

// The radix key of a depth: as many bits as the depth.
template <typename T>
using DepthKey = std::conditional_t<sizeof(T) == 4, uint32_t, uint64_t>;

template <typename T>
cudaError_t bin_count_cuda(const BinInputs<T>& in, BinGeometry g, int64_t giant_tiles,
                           int64_t* counts, int32_t* large_ids, unsigned int* large_counters,
                           cudaStream_t stream);

// temp == nullptr: writes the needed temp_bytes and returns. Else *order points at whichever
// of ids / ids_alt holds the Gaussians in depth order.
template <typename T>
cudaError_t bin_depth_order_cuda(void* temp, size_t& temp_bytes, const T* depths, int64_t n,
                                 DepthKey<T>* keys, DepthKey<T>* keys_alt, int32_t* ids,
                                 int32_t* ids_alt, int32_t** order, cudaStream_t stream);

// counts == nullptr: the ranks alone (the per-tile path's float64 depth rank).
cudaError_t bin_order_counts_cuda(const int32_t* order, const int64_t* counts, int64_t n,
                                  int64_t* counts_in_order, int32_t* rank, cudaStream_t stream);

// temp == nullptr: writes the needed temp_bytes and returns.
cudaError_t bin_scan_cuda(void* temp, size_t& temp_bytes, const int64_t* counts, int64_t* offsets,
                          int64_t n, cudaStream_t stream);

// order (bin_depth_order), rank and offsets (bin_order_counts, bin_scan); large_ids /
// large_counters as filled by bin_count_cuda (nullptr: the former walk).
template <typename T>
cudaError_t bin_emit_cuda(const BinInputs<T>& in, const int32_t* order, const int32_t* rank,
                          const int32_t* large_ids, const unsigned int* large_counters,
                          BinGeometry g, const int64_t* offsets, uint32_t* keys, int32_t* ids,
                          cudaStream_t stream);

// Sorts (keys, ids) of length m stably by key bits [0, end_bit). On return *keys_out /
// *ids_out point at whichever of the two buffers holds the result.
cudaError_t bin_sort_cuda(void* temp, size_t& temp_bytes, uint32_t* keys, uint32_t* keys_alt,
                          int32_t* ids, int32_t* ids_alt, int64_t m, int end_bit,
                          uint32_t** keys_out, int32_t** ids_out, cudaStream_t stream);

cudaError_t bin_ranges_cuda(const uint32_t* sorted_keys, int64_t m, int64_t n_tiles,
                            int64_t* tile_offsets, cudaStream_t stream);

}  // namespace tiger

#pragma once
// Raw-pointer pieces of the CUDA tile binning (no torch headers): a counting sort by tile, then
// each tile's list sorted by (depth, id) on its own. The glue allocates every buffer through
// torch (caching allocator) and runs, on one stream:
//   1. bin_tiles_cuda(count): every hit (Gaussian, touched tile; exact ellipse-tile test) adds
//      one to its tile's count. One thread walks a Gaussian with at most kSmallTiles candidate
//      (bounding-box) tiles; the larger ones are listed (BinChunks) and their candidates walked
//      in chunks of kChunkTiles, one warp per chunk, whatever the Gaussian's size
//   2. bin_offsets_cuda: exclusive int64 scan of the tile counts -> tile_offsets [tiles + 1]
//   3. bin_tiles_cuda(emit): the same walk; each hit takes a slot of its tile's range (the
//      count counted back down to zero) and writes its 64-bit sort key there: depth key in the
//      high word (float32 depth bits; float64: the Gaussian's rank in the depth order, from
//      bin_depth_rank_cuda), Gaussian id in the low word
//   4. bin_sort_tiles_cuda: one block per tile sorts its keys (shared memory up to sort_keys
//      of them; longer lists as sorted runs merged in global memory) and writes the ids
// Equal to a stable sort by (tile, depth, id) over all hits, without a device-wide sort.
// chunks == nullptr: every Gaussian by one thread (the former walk, for comparisons:
// TIGER_BIN_SERIAL=1).
#include <cuda_runtime_api.h>
#include <stddef.h>
#include <stdint.h>

namespace tiger {

struct BinGeometry {
  int width, height, tile_size, tiles_x, tiles_y;
};

// The listed large Gaussians: ids[s] and the first of their chunks, chunk_base[s] (ascending
// in s), both claimed by one 64-bit atomic on *counter: slots in bits 33.., chunks in bits 0..32.
struct BinChunks {
  int32_t* ids;                // [n]
  int64_t* chunk_base;         // [n]
  unsigned long long* counter; // 1, zero before the count
};

template <typename T>
struct BinInputs {
  const T* means2d;          // [n, 2]
  const T* conics;           // [n, 3]
  const T* opacities;        // [n]
  const T* depths;           // [n]
  const int32_t* radii;      // [n, 2]
  const int32_t* depth_rank; // [n] for float64 depths (float32: the depth bits are the key)
  int64_t n;
  T alpha_threshold;
};

// Maximum sort_keys (the shared-memory list of one block).
constexpr int kBinSortKeysMax = 4096;

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

// float64 depths: rank[i] = position of Gaussian i in the stable depth order (radix sort of
// 64-bit order-preserving keys). temp == nullptr: writes the needed temp_bytes and returns.
cudaError_t bin_depth_rank_cuda(void* temp, size_t& temp_bytes, const double* depths, int64_t n,
                                uint64_t* keys, uint64_t* keys_alt, int32_t* ids,
                                int32_t* ids_alt, int32_t* rank, cudaStream_t stream);

// Sorts every tile's keys; ids [m] = their low words. keys_alt [m]: scratch of lists longer
// than sort_keys (a power of two in [2, kBinSortKeysMax]).
cudaError_t bin_sort_tiles_cuda(const int64_t* tile_offsets, int64_t n_tiles, uint64_t* keys,
                                uint64_t* keys_alt, int sort_keys, int32_t* ids,
                                cudaStream_t stream);

}  // namespace tiger

#pragma once
// Raw-pointer pieces of the CUDA tile binning (no torch headers). The glue allocates
// every buffer through torch (caching allocator) and runs, on one stream:
//   1. bin_count: per-Gaussian number of touched tiles (exact ellipse-tile test) -> int64:
//      one thread per Gaussian for those with at most 32 candidate (bounding-box) tiles; the
//      larger ones are appended to large_ids (n int32 of scratch; counts in large_counters, 2
//      uint32) and counted by one warp each, or one block each beyond giant_tiles candidates
//   2. bin_depth_order: the Gaussians' stable depth order (radix sort of N order-preserving
//      depth keys: 32 bits for float, 64 for double)
//   3. bin_order_counts: the counts in that order, and each Gaussian's rank in it
//   4. bin_scan: inclusive int64 scan of the ordered counts (segment ends; total = last)
//   5. bin_emit: 32-bit tile keys and Gaussian ids (both kinds), each Gaussian's hits in
//      row-major order in its segment, the segments in depth order
//   6. bin_sort: stable CUB radix sort of (tile, id) over the bits the tile count needs, which
//      leaves each tile's Gaussians in depth order (ties by id)
//   7. bin_ranges: tile_offsets [tiles+1] int64 from the sorted keys
// large_ids == nullptr: every Gaussian by one thread (the former binning, for comparisons:
// TIGER_BIN_SERIAL=1).
#include <cuda_runtime_api.h>
#include <stddef.h>
#include <stdint.h>

#include <type_traits>

namespace tiger {

struct BinGeometry {
  int width, height, tile_size, tiles_x, tiles_y;
};

// The radix key of a depth: as many bits as the depth.
template <typename T>
using DepthKey = std::conditional_t<sizeof(T) == 4, uint32_t, uint64_t>;

template <typename T>
cudaError_t bin_count_cuda(const T* means2d, const T* conics, const T* opacities,
                           const int32_t* radii, int64_t n, BinGeometry g, T alpha_threshold,
                           int64_t giant_tiles, int64_t* counts, int32_t* large_ids,
                           unsigned int* large_counters, cudaStream_t stream);

// temp == nullptr: writes the needed temp_bytes and returns. Else *order points at whichever
// of ids / ids_alt holds the Gaussians in depth order.
template <typename T>
cudaError_t bin_depth_order_cuda(void* temp, size_t& temp_bytes, const T* depths, int64_t n,
                                 DepthKey<T>* keys, DepthKey<T>* keys_alt, int32_t* ids,
                                 int32_t* ids_alt, int32_t** order, cudaStream_t stream);

cudaError_t bin_order_counts_cuda(const int32_t* order, const int64_t* counts, int64_t n,
                                  int64_t* counts_in_order, int32_t* rank, cudaStream_t stream);

// temp == nullptr: writes the needed temp_bytes and returns.
cudaError_t bin_scan_cuda(void* temp, size_t& temp_bytes, const int64_t* counts, int64_t* offsets,
                          int64_t n, cudaStream_t stream);

// order (bin_depth_order), rank and offsets (bin_order_counts, bin_scan); large_ids /
// large_counters as filled by bin_count_cuda (nullptr: the former binning).
template <typename T>
cudaError_t bin_emit_cuda(const T* means2d, const T* conics, const T* opacities,
                          const int32_t* radii, const int32_t* order, const int32_t* rank,
                          const int32_t* large_ids,
                          const unsigned int* large_counters, int64_t n, BinGeometry g,
                          T alpha_threshold, const int64_t* offsets, uint32_t* keys, int32_t* ids,
                          cudaStream_t stream);

// Sorts (keys, ids) of length m stably by key bits [0, end_bit). On return *keys_out /
// *ids_out point at whichever of the two buffers holds the result.
cudaError_t bin_sort_cuda(void* temp, size_t& temp_bytes, uint32_t* keys, uint32_t* keys_alt,
                          int32_t* ids, int32_t* ids_alt, int64_t m, int end_bit,
                          uint32_t** keys_out, int32_t** ids_out, cudaStream_t stream);

cudaError_t bin_ranges_cuda(const uint32_t* sorted_keys, int64_t m, int64_t n_tiles,
                            int64_t* tile_offsets, cudaStream_t stream);

}  // namespace tiger

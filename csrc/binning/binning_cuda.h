#pragma once
// Raw-pointer pieces of the CUDA tile binning (no torch headers). The glue allocates
// every buffer through torch (caching allocator) and runs, on one stream:
//   1. bin_count: per-Gaussian number of touched tiles (exact ellipse-tile test) -> int64:
//      one thread per Gaussian for those with at most 32 candidate (bounding-box) tiles; the
//      larger ones are appended to large_ids (n int32 of scratch; counts in large_counters, 2
//      uint32) and counted by one warp each, or one block each beyond 2048 candidates
//   2. bin_scan: inclusive int64 scan of the counts (offsets; total = offsets[N-1])
//   3. bin_emit: 64-bit keys (tile << 32 | depth order bits) and Gaussian ids (both kinds),
//      each Gaussian's hits in row-major order in its segment
//   4. bin_sort: CUB radix sort of (key, id) over only the bits the tile count needs
//   5. bin_ranges: tile_offsets [tiles+1] int64 from the sorted keys
// float64 depths do not fit 32 key bits: bin_depth_rank first sorts them (64-bit keys)
// and the per-Gaussian rank becomes the depth part of the key.
// large_ids == nullptr: every Gaussian by one thread (the former binning, for comparisons:
// TIGER_BIN_SERIAL=1).
#include <cuda_runtime_api.h>
#include <stddef.h>
#include <stdint.h>

namespace tiger {

struct BinGeometry {
  int width, height, tile_size, tiles_x, tiles_y;
};

template <typename T>
cudaError_t bin_count_cuda(const T* means2d, const T* conics, const T* opacities,
                           const int32_t* radii, int64_t n, BinGeometry g, T alpha_threshold,
                           int64_t* counts, int32_t* large_ids, unsigned int* large_counters,
                           cudaStream_t stream);

// temp == nullptr: writes the needed temp_bytes and returns.
cudaError_t bin_scan_cuda(void* temp, size_t& temp_bytes, const int64_t* counts, int64_t* offsets,
                          int64_t n, cudaStream_t stream);

// depth_rank (optional): per-Gaussian depth rank used instead of the float depth bits.
// large_ids / large_counters as filled by bin_count_cuda (nullptr: the former binning).
template <typename T>
cudaError_t bin_emit_cuda(const T* means2d, const T* conics, const T* opacities, const T* depths,
                          const int32_t* radii, const int32_t* depth_rank,
                          const int32_t* large_ids, const unsigned int* large_counters, int64_t n,
                          BinGeometry g, T alpha_threshold, const int64_t* offsets,
                          uint64_t* keys, int32_t* ids, cudaStream_t stream);

// Sorts (keys, ids) of length m by key bits [0, end_bit). On return *keys_out / *ids_out
// point at whichever of the two buffers holds the result.
cudaError_t bin_sort_cuda(void* temp, size_t& temp_bytes, uint64_t* keys, uint64_t* keys_alt,
                          int32_t* ids, int32_t* ids_alt, int64_t m, int end_bit,
                          uint64_t** keys_out, int32_t** ids_out, cudaStream_t stream);

cudaError_t bin_ranges_cuda(const uint64_t* sorted_keys, int64_t m, int64_t n_tiles,
                            int64_t* tile_offsets, cudaStream_t stream);

// For float64 depths: rank[i] = position of Gaussian i in the stable depth order.
cudaError_t bin_depth_rank_cuda(void* temp, size_t& temp_bytes, const double* depths, int64_t n,
                                uint64_t* keys, uint64_t* keys_alt, int32_t* ids, int32_t* ids_alt,
                                int32_t* rank, cudaStream_t stream);

}  // namespace tiger

// The order the rasterization kernels draw tiles in: longest tile lists first (raster.h).
//
// One block per tile and a block's walk as long as its list (up to its pixels' saturation):
// the blocks of the few long lists, scheduled last in index order, ran alone on their SMs at
// the end of the kernel. Drawn first, the short lists fill the other SMs around them (longest
// processing time first). Lists are bucketed by length in half-octaves (a counting sort in one
// block: two reads of tile_offsets), which orders them within a factor of sqrt(2).
#include "raster_cuda.h"

namespace tiger {
namespace {

// Half-octaves of lengths below 2^33 (2 * 33); a list holds int32 ids, so fewer than 2^31 entries.
constexpr int kOrderBuckets = 66;

// Half-octave of n >= 0: 0 for 0 and 1, then 2 * floor(log2 n) + the bit below the top one.
__device__ __forceinline__ int length_bucket(int64_t n) {
  if (n < 2) return 0;
  const int top = 63 - __clzll(static_cast<long long>(n));
  return 2 * top + int((n >> (top - 1)) & 1);
}

__global__ void __launch_bounds__(1024) heavy_first_kernel(const int64_t* __restrict__ offsets,
                                                           int tiles, int32_t* __restrict__ order) {
  __shared__ int count[kOrderBuckets];
  for (int b = threadIdx.x; b < kOrderBuckets; b += blockDim.x) count[b] = 0;
  __syncthreads();
  for (int t = threadIdx.x; t < tiles; t += blockDim.x)
    atomicAdd(&count[length_bucket(offsets[t + 1] - offsets[t])], 1);
  __syncthreads();
  if (threadIdx.x == 0) {  // exclusive starts, longest bucket first
    int start = 0;
    for (int b = kOrderBuckets - 1; b >= 0; --b) {
      const int c = count[b];
      count[b] = start;
      start += c;
    }
  }
  __syncthreads();
  for (int t = threadIdx.x; t < tiles; t += blockDim.x)
    order[atomicAdd(&count[length_bucket(offsets[t + 1] - offsets[t])], 1)] = t;
}

}  // namespace

cudaError_t heavy_first_order_cuda_launch(const int64_t* tile_offsets, int tiles, int32_t* order,
                                          cudaStream_t stream) {
  if (tiles <= 0) return cudaSuccess;
  heavy_first_kernel<<<1, 1024, 0, stream>>>(tile_offsets, tiles, order);
  return cudaGetLastError();
}

}  // namespace tiger

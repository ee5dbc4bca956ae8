// CUDA kernels of the nms family (raw pointers, no torch headers).
#include <cuda_runtime.h>

#include "nms/nms.h"

namespace tiger {
namespace nms {
namespace {

constexpr int kBoxBlock = 64;  // boxes per block side: one 64-bit word of the suppression mask

template <typename scalar_t>
__device__ __forceinline__ double box_iou(const scalar_t* a, const scalar_t* b) {
  const double w = fmax(0.0, double(fmin(a[2], b[2])) - double(fmax(a[0], b[0])));
  const double h = fmax(0.0, double(fmin(a[3], b[3])) - double(fmax(a[1], b[1])));
  const double inter = w * h;
  const double uni = double(a[2] - a[0]) * double(a[3] - a[1]) + double(b[2] - b[0]) * double(b[3] - b[1]) - inter;
  return uni > 0 ? inter / uni : 0.0;
}

template <typename scalar_t>
__global__ void box_iou_bits_kernel(const scalar_t* __restrict__ boxes, int64_t n, double thr,
                                    uint64_t* __restrict__ mask, int64_t words) {
  const int64_t row_block = blockIdx.y, col_block = blockIdx.x;
  if (row_block > col_block) return;
  const int64_t row_n = min(static_cast<int64_t>(kBoxBlock), n - row_block * kBoxBlock);
  const int64_t col_n = min(static_cast<int64_t>(kBoxBlock), n - col_block * kBoxBlock);
  __shared__ scalar_t cols[kBoxBlock * 4];
  if (threadIdx.x < col_n)
    for (int k = 0; k < 4; ++k) cols[threadIdx.x * 4 + k] = boxes[(col_block * kBoxBlock + threadIdx.x) * 4 + k];
  __syncthreads();
  if (threadIdx.x >= row_n) return;
  const int64_t i = row_block * kBoxBlock + threadIdx.x;
  const scalar_t* bi = boxes + i * 4;
  uint64_t bits = 0;
  const int start = row_block == col_block ? threadIdx.x + 1 : 0;
  for (int c = start; c < col_n; ++c)
    if (box_iou(bi, cols + c * 4) > thr) bits |= uint64_t(1) << c;
  mask[i * words + col_block] = bits;
}

__global__ void pack_kernel(const bool* __restrict__ masks, int64_t m, int64_t length,
                            uint64_t* __restrict__ packed, int64_t words) {
  const int64_t t = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (t >= m * words) return;
  const int64_t mi = t / words, w = t - mi * words;
  const bool* src = masks + mi * length + w * 64;
  const int n = static_cast<int>(min(static_cast<int64_t>(64), length - w * 64));
  uint64_t bits = 0;
  for (int b = 0; b < n; ++b) bits |= static_cast<uint64_t>(src[b]) << b;
  packed[t] = bits;
}

constexpr int kTile = 32;    // masks per tile side
constexpr int kRowsPer = 4;  // pairs per thread along i (block = 32 x 8 threads)
constexpr int kChunk = 32;   // 64-bit words staged in shared memory per step

// One block computes the 32 x 32 tile of pair counts (tile_i, tile_j), tile_j >= tile_i, and
// writes it and its mirror. Rows of both tiles are staged chunk by chunk through shared memory.
__global__ void pair_kernel(const uint64_t* __restrict__ packed, int64_t m, int64_t words,
                            int64_t* __restrict__ out) {
  const int64_t ti = blockIdx.y, tj = blockIdx.x;
  if (ti > tj) return;
  __shared__ uint64_t a_s[kTile][kChunk + 1];
  __shared__ uint64_t b_s[kTile][kChunk + 1];
  const int tx = threadIdx.x, ty = threadIdx.y;  // tx: column j, ty: row group
  const int tid = ty * kTile + tx, nthreads = kTile * (kTile / kRowsPer);
  unsigned long long acc[kRowsPer] = {0, 0, 0, 0};
  for (int64_t w0 = 0; w0 < words; w0 += kChunk) {
    for (int e = tid; e < kTile * kChunk; e += nthreads) {
      const int r = e / kChunk, k = e - r * kChunk;
      const int64_t gi = ti * kTile + r, gj = tj * kTile + r, gw = w0 + k;
      a_s[r][k] = (gi < m && gw < words) ? packed[gi * words + gw] : 0ull;
      b_s[r][k] = (gj < m && gw < words) ? packed[gj * words + gw] : 0ull;
    }
    __syncthreads();
#pragma unroll 4
    for (int k = 0; k < kChunk; ++k) {
      const uint64_t bv = b_s[tx][k];
#pragma unroll
      for (int r = 0; r < kRowsPer; ++r) acc[r] += __popcll(a_s[ty * kRowsPer + r][k] & bv);
    }
    __syncthreads();
  }
  const int64_t j = tj * kTile + tx;
  if (j >= m) return;
  for (int r = 0; r < kRowsPer; ++r) {
    const int64_t i = ti * kTile + ty * kRowsPer + r;
    if (i >= m) continue;
    out[i * m + j] = static_cast<int64_t>(acc[r]);
    out[j * m + i] = static_cast<int64_t>(acc[r]);
  }
}

}  // namespace

template <typename scalar_t>
void launch_box_iou_bits(const scalar_t* boxes, int64_t n, double iou_threshold, uint64_t* mask,
                         void* stream) {
  if (n == 0) return;
  const int64_t blocks = (n + kBoxBlock - 1) / kBoxBlock;
  dim3 grid(static_cast<unsigned>(blocks), static_cast<unsigned>(blocks));
  box_iou_bits_kernel<scalar_t><<<grid, kBoxBlock, 0, static_cast<cudaStream_t>(stream)>>>(
      boxes, n, iou_threshold, mask, blocks);
}

void launch_pack_masks(const bool* masks, int64_t m, int64_t length, uint64_t* packed, int64_t words,
                       void* stream) {
  const int64_t total = m * words;
  if (total == 0) return;
  pack_kernel<<<static_cast<unsigned>((total + 255) / 256), 256, 0, static_cast<cudaStream_t>(stream)>>>(
      masks, m, length, packed, words);
}

void launch_pair_intersections(const uint64_t* packed, int64_t m, int64_t words, int64_t* out,
                               void* stream) {
  if (m == 0) return;
  const unsigned tiles = static_cast<unsigned>((m + kTile - 1) / kTile);
  dim3 grid(tiles, tiles), block(kTile, kTile / kRowsPer);
  pair_kernel<<<grid, block, 0, static_cast<cudaStream_t>(stream)>>>(packed, m, words, out);
}

template void launch_box_iou_bits<float>(const float*, int64_t, double, uint64_t*, void*);
template void launch_box_iou_bits<double>(const double*, int64_t, double, uint64_t*, void*);

}  // namespace nms
}  // namespace tiger

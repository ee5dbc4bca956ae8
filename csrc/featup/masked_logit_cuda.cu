// CUDA kernels of tiger::masked_logit (formula in masked_logit.h; raw pointers, no torch
// headers). A block takes 32 consecutive pixels at a time: the channels-first mask of a chunk of
// 32 channels is staged in shared memory (read coalesced along the pixels), then each warp reads
// its pixels' channels-last rows coalesced along the channels (lane = channel). Sums in a fixed
// order: lanes, then the warp tree; over pixels per block in warp order, then over blocks in
// block order (no atomics: the same result on every run). Grid sizes depend only on the shapes.
#include <cuda_runtime.h>

#include <algorithm>

#include "common/cuda_helpers.cuh"
#include "featup/masked_logit.h"

namespace tiger {
namespace featup {
namespace {

constexpr int kThreads = 256;
constexpr int kWarps = kThreads / 32;
constexpr int kPixels = 32;                     // pixels per block step
constexpr int kPixelsPerWarp = kPixels / kWarps;
constexpr int kMaxLogitBlocks = 1024;

// The multipliers m[kc + r, p0 + c] for r, c < 32 into tile[r][c] (0 past the ends).
template <typename T>
__device__ void stage_keep(const bool* keep, T keep_scale, const LogitDims& d, int64_t kc, int64_t p0,
                           T (*tile)[kPixels + 1]) {
  for (int e = threadIdx.x; e < 32 * kPixels; e += kThreads) {
    const int r = e / kPixels, c = e % kPixels;
    const int64_t k = kc + r, p = p0 + c;
    tile[r][c] = (k < d.U && p < d.P) ? keep_multiplier(keep, keep_scale, k * d.P + p) : T(0);
  }
}

template <typename T>
__global__ void __launch_bounds__(kThreads) masked_logit_forward_kernel(const T* __restrict__ x,
                                                                        const bool* __restrict__ keep, T keep_scale,
                                                                        const T* __restrict__ weight,
                                                                        const T* __restrict__ bias, LogitDims d,
                                                                        T* __restrict__ logit) {
  __shared__ T tile[32][kPixels + 1];
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
  for (int64_t p0 = int64_t(blockIdx.x) * kPixels; p0 < d.P; p0 += int64_t(gridDim.x) * kPixels) {
    T acc[kPixelsPerWarp];
#pragma unroll
    for (int i = 0; i < kPixelsPerWarp; ++i) acc[i] = T(0);
    for (int64_t kc = 0; kc < d.U; kc += 32) {
      stage_keep(keep, keep_scale, d, kc, p0, tile);
      __syncthreads();
      const int64_t k = kc + lane;
      if (k < d.U) {
        const T wk = weight[k];
#pragma unroll
        for (int i = 0; i < kPixelsPerWarp; ++i) {
          const int c = warp * kPixelsPerWarp + i;
          const int64_t p = p0 + c;
          if (p < d.P) acc[i] += wk * (x[p * d.U + k] * tile[lane][c]);
        }
      }
      __syncthreads();
    }
#pragma unroll
    for (int i = 0; i < kPixelsPerWarp; ++i) {
      const T total = cuda::warp_sum(acc[i]);
      const int64_t p = p0 + warp * kPixelsPerWarp + i;
      if (lane == 0 && p < d.P) logit[p] = bias[0] + total;
    }
  }
}

// grad_x per (pixel, channel); per block and channel the partial sums of g x m (and of g,
// column U) over the block's pixels, in warp order.
template <typename T>
__global__ void __launch_bounds__(kThreads) masked_logit_backward_kernel(
    const T* __restrict__ grad, const T* __restrict__ x, const bool* __restrict__ keep, T keep_scale,
    const T* __restrict__ weight, LogitDims d, T* __restrict__ grad_x, T* __restrict__ partials) {
  __shared__ T tile[32][kPixels + 1];
  __shared__ T red[kWarps][33];
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
  T* part = partials + int64_t(blockIdx.x) * (d.U + 1);
  for (int64_t kc = 0; kc < d.U; kc += 32) {
    const int64_t k = kc + lane;
    const T wk = k < d.U ? weight[k] : T(0);
    T acc_w = 0, acc_b = 0;
    for (int64_t p0 = int64_t(blockIdx.x) * kPixels; p0 < d.P; p0 += int64_t(gridDim.x) * kPixels) {
      stage_keep(keep, keep_scale, d, kc, p0, tile);
      __syncthreads();
#pragma unroll
      for (int i = 0; i < kPixelsPerWarp; ++i) {
        const int c = warp * kPixelsPerWarp + i;
        const int64_t p = p0 + c;
        if (p < d.P) {
          const T g = grad[p];
          acc_b += g;
          if (k < d.U) {
            const T m = tile[lane][c];
            if (grad_x) grad_x[p * d.U + k] = g * wk * m;
            acc_w += g * (x[p * d.U + k] * m);
          }
        }
      }
      __syncthreads();
    }
    red[warp][lane] = acc_w;
    if (lane == 0) red[warp][32] = acc_b;
    __syncthreads();
    if (warp == 0) {
      T total = 0;
      for (int v = 0; v < kWarps; ++v) total += red[v][lane];
      if (k < d.U) part[k] = total;
      if (kc == 0 && lane == 0) {
        T gb = 0;
        for (int v = 0; v < kWarps; ++v) gb += red[v][32];
        part[d.U] = gb;
      }
    }
    __syncthreads();
  }
}

template <typename T>
__global__ void masked_logit_param_sum_kernel(const T* __restrict__ partials, int blocks, int64_t U, T* grad_w,
                                              T* grad_b) {
  const int64_t k = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (k > U) return;
  T total = 0;
  for (int b = 0; b < blocks; ++b) total += partials[int64_t(b) * (U + 1) + k];
  if (k < U)
    grad_w[k] = total;
  else
    grad_b[0] = total;
}

}  // namespace

int masked_logit_blocks(int64_t pixels) {
  return static_cast<int>(std::max<int64_t>(1, std::min<int64_t>(kMaxLogitBlocks, cuda::ceil_div(pixels, kPixels))));
}

template <typename T>
void launch_masked_logit_forward(const T* x, const bool* keep, T keep_scale, const T* weight, const T* bias,
                                 LogitDims d, T* logit, void* stream) {
  if (d.P == 0) return;
  masked_logit_forward_kernel<T><<<masked_logit_blocks(d.P), kThreads, 0, static_cast<cudaStream_t>(stream)>>>(
      x, keep, keep_scale, weight, bias, d, logit);
}

template <typename T>
void launch_masked_logit_backward(const T* grad, const T* x, const bool* keep, T keep_scale, const T* weight,
                                  LogitDims d, T* grad_x, T* partials, int blocks, T* grad_weight, T* grad_bias,
                                  void* stream) {
  auto st = static_cast<cudaStream_t>(stream);
  masked_logit_backward_kernel<T><<<blocks, kThreads, 0, st>>>(grad, x, keep, keep_scale, weight, d, grad_x,
                                                               partials);
  masked_logit_param_sum_kernel<T><<<cuda::ceil_div(d.U + 1, 256), 256, 0, st>>>(partials, blocks, d.U, grad_weight,
                                                                                  grad_bias);
}

#define TIGER_MASKED_LOGIT_INSTANTIATE(T)                                                                         \
  template void launch_masked_logit_forward<T>(const T*, const bool*, T, const T*, const T*, LogitDims, T*, void*); \
  template void launch_masked_logit_backward<T>(const T*, const T*, const bool*, T, const T*, LogitDims, T*, T*, int, \
                                                T*, T*, void*);
TIGER_MASKED_LOGIT_INSTANTIATE(float)
TIGER_MASKED_LOGIT_INSTANTIATE(double)
#undef TIGER_MASKED_LOGIT_INSTANTIATE

}  // namespace featup
}  // namespace tiger

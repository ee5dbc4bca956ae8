// CUDA kernels of tiger::magnitude_blur (formula in magnitude_blur.h; raw pointers, no torch
// headers). Channels last throughout: the magnitude is one warp per pixel (lanes over channels);
// the blur and its transpose are one thread per (pixel, channel), a block's threads over
// consecutive (column, channel) of one row, reading and writing consecutive channels
// (coalesced). Every output is a gather of its own taps in a fixed order: no atomics, the same
// result on every run. Grid sizes depend only on the shapes: a CUDA graph may capture the
// launches.
#include <cuda_runtime.h>
#include <math.h>

#include <algorithm>

#include "common/cuda_helpers.cuh"
#include "featup/blur_math.h"
#include "featup/magnitude_blur.h"

namespace tiger {
namespace featup {
namespace {

constexpr int kThreads = 256;
constexpr int kWarps = kThreads / 32;

template <typename X, typename T>
__global__ void __launch_bounds__(kThreads) magnitude_kernel(const X* __restrict__ x, BlurDims d,
                                                             T* __restrict__ magnitude) {
  const int lane = threadIdx.x & 31;
  const int64_t p = int64_t(blockIdx.x) * kWarps + (threadIdx.x >> 5);
  if (p >= d.H * d.W) return;
  T sum = 0;
  for (int64_t c = lane; c < d.C; c += 32) {
    const T v = cuda::load_as<T>(x[p * d.C + c]);
    sum += v * v;
  }
  sum = cuda::warp_sum(sum);
  if (lane == 0) magnitude[p] = sqrt(sum);
}

// kRadius: the taps' radius when fixed at compile time (FeatUp's 2: the tap loops unroll and the
// taps stay in the kernel parameters; a runtime index into them would copy them to local
// memory), or -1: d.radius at run time.
template <int kRadius>
__device__ __forceinline__ int blur_radius(const BlurDims& d) {
  return kRadius >= 0 ? kRadius : d.radius;
}

// blurred[y, x, k]: grid (row chunks, H), a block's threads over consecutive (x, k) of row y
// (32-bit index math: a row holds W (C + 1) < 2^31 elements, checked by the launcher).
template <typename X, typename T, int kRadius>
__global__ void __launch_bounds__(kThreads) blur_forward_kernel(const X* __restrict__ x,
                                                                const T* __restrict__ magnitude, BlurDims d,
                                                                BlurTaps<T> taps, T* __restrict__ blurred) {
  const int U = static_cast<int>(d.C) + 1, W = static_cast<int>(d.W), H = static_cast<int>(d.H);
  const int r = blockIdx.x * kThreads + threadIdx.x, y = blockIdx.y;
  if (r >= W * U) return;
  const int xo = r / U, k = r - xo * U, R = blur_radius<kRadius>(d), C = U - 1;
  T acc = 0;
  if (y >= R && y < H - R && xo >= R && xo < W - R) {
    // no tap reflects: walk pointers (the general path's per-tap index math costs more than
    // its load and multiply-add); the same taps in the same order as the general path
#pragma unroll
    for (int a = 0; a <= 2 * R; ++a) {
      const int64_t q0 = static_cast<int64_t>(y - R + a) * W + (xo - R);
      T sum = 0;
      if (k == 0) {
        const T* src = magnitude + q0;
#pragma unroll
        for (int b = 0; b <= 2 * R; ++b) sum += taps.g[b] * src[b];
      } else {
        const X* src = x + q0 * C + (k - 1);
#pragma unroll
        for (int b = 0; b <= 2 * R; ++b) sum += taps.g[b] * cuda::load_as<T>(src[b * C]);
      }
      acc += taps.g[a] * sum;
    }
    blurred[(static_cast<int64_t>(y) * W) * U + r] = acc;
    return;
  }
#pragma unroll
  for (int a = -R; a <= R; ++a) {
    const int64_t row = static_cast<int64_t>(reflect_index(y + a, H)) * W;
    T sum = 0;
#pragma unroll
    for (int b = -R; b <= R; ++b) {
      const int64_t q = row + reflect_index(xo + b, W);
      const T v = k == 0 ? magnitude[q] : cuda::load_as<T>(x[q * C + k - 1]);
      sum += taps.g[b + R] * v;
    }
    acc += taps.g[a + R] * sum;
  }
  blurred[(static_cast<int64_t>(y) * W) * U + r] = acc;
}

// gu[y, x, k] = (B^T grad_blurred)[y, x, k]: away from the borders the transposed taps are the
// direct ones (i = j - t), gathered without the general (reflected) tap lists.
template <int kRadius, typename T>
__device__ __forceinline__ T adjoint_blur(const T* __restrict__ grad_blurred, int y, int xo, int k,
                                          const BlurDims& d, const BlurTaps<T>& taps) {
  const int64_t U = d.C + 1;
  const int R = blur_radius<kRadius>(d), H = static_cast<int>(d.H), W = static_cast<int>(d.W);
  T acc = 0;
  if (y > R && y < H - 1 - R && xo > R && xo < W - 1 - R) {
#pragma unroll
    for (int a = 0; a <= 2 * R; ++a) {
      const T* row = grad_blurred + (static_cast<int64_t>(y - R + a) * W + xo - R) * U + k;
      T sum = 0;
#pragma unroll
      for (int b = 0; b <= 2 * R; ++b) sum += taps.g[2 * R - b] * row[b * U];
      acc += taps.g[2 * R - a] * sum;
    }
    return acc;
  }
  T g[2 * kMaxBlurRadius + 1];  // a local copy only on this (border) path
#pragma unroll
  for (int t = 0; t <= 2 * kMaxBlurRadius; ++t) g[t] = taps.g[t];
  AdjointTaps<T> ty, tx;
  adjoint_taps<T>(y, d.H, g, R, ty);
  adjoint_taps<T>(xo, d.W, g, R, tx);
  for (int a = 0; a < ty.count; ++a) {
    const T* row = grad_blurred + ty.index[a] * d.W * U + k;
    T sum = 0;
    for (int b = 0; b < tx.count; ++b) sum += tx.weight[b] * row[tx.index[b] * U];
    acc += ty.weight[a] * sum;
  }
  return acc;
}

template <typename T, int kRadius>
__global__ void __launch_bounds__(kThreads) magnitude_scale_kernel(const T* __restrict__ grad_blurred,
                                                                   const T* __restrict__ grad_magnitude,
                                                                   const T* __restrict__ magnitude, BlurDims d,
                                                                   BlurTaps<T> taps, T* __restrict__ scale) {
  const int xo = blockIdx.x * kThreads + threadIdx.x, y = blockIdx.y;
  if (xo >= d.W) return;
  const int64_t p = static_cast<int64_t>(y) * d.W + xo;
  const T g = adjoint_blur<kRadius>(grad_blurred, y, xo, 0, d, taps) + (grad_magnitude ? grad_magnitude[p] : T(0));
  const T m = magnitude[p];
  scale[p] = m > T(0) ? g / m : T(0);
}

// grad_x[y, x, c]: grid (row chunks, H) as the forward's.
template <typename X, typename T, int kRadius>
__global__ void __launch_bounds__(kThreads) grad_features_kernel(const T* __restrict__ grad_blurred,
                                                                 const X* __restrict__ x,
                                                                 const T* __restrict__ scale, BlurDims d,
                                                                 BlurTaps<T> taps, X* __restrict__ grad_x) {
  const int C = static_cast<int>(d.C), W = static_cast<int>(d.W);
  const int r = blockIdx.x * kThreads + threadIdx.x, y = blockIdx.y;
  if (r >= W * C) return;
  const int xo = r / C, c = r - xo * C;
  const int64_t idx = static_cast<int64_t>(y) * W * C + r;
  const T g = adjoint_blur<kRadius>(grad_blurred, y, xo, c + 1, d, taps);
  grad_x[idx] = cuda::convert_to<X>(g + scale[static_cast<int64_t>(y) * W + xo] * cuda::load_as<T>(x[idx]));
}

// FeatUp's radius with the taps unrolled; any other through the runtime-radius kernels.
constexpr int kFitRadius = 2;

template <typename X, typename T, int kRadius>
void launch_blur_backward(const T* grad_blurred, const T* grad_magnitude, const X* x, const T* magnitude,
                          const BlurDims& d, const BlurTaps<T>& taps, T* scale, X* grad_x, cudaStream_t st) {
  const unsigned rows = static_cast<unsigned>(d.H);
  magnitude_scale_kernel<T, kRadius><<<dim3(cuda::ceil_div(d.W, kThreads), rows), kThreads, 0, st>>>(
      grad_blurred, grad_magnitude, magnitude, d, taps, scale);
  grad_features_kernel<X, T, kRadius><<<dim3(cuda::ceil_div(d.W * d.C, kThreads), rows), kThreads, 0, st>>>(
      grad_blurred, x, scale, d, taps, grad_x);
}

}  // namespace

template <typename X, typename T>
void launch_magnitude_blur_forward(const X* x, BlurDims d, BlurTaps<T> taps, T* blurred, T* magnitude,
                                   void* stream) {
  const int64_t P = d.H * d.W;
  if (P == 0) return;
  auto st = static_cast<cudaStream_t>(stream);
  magnitude_kernel<X, T><<<cuda::ceil_div(P, kWarps), kThreads, 0, st>>>(x, d, magnitude);
  const dim3 grid(cuda::ceil_div(d.W * (d.C + 1), kThreads), static_cast<unsigned>(d.H));
  if (d.radius == kFitRadius)
    blur_forward_kernel<X, T, kFitRadius><<<grid, kThreads, 0, st>>>(x, magnitude, d, taps, blurred);
  else
    blur_forward_kernel<X, T, -1><<<grid, kThreads, 0, st>>>(x, magnitude, d, taps, blurred);
}

template <typename X, typename T>
void launch_magnitude_blur_backward(const T* grad_blurred, const T* grad_magnitude, const X* x, const T* magnitude,
                                    BlurDims d, BlurTaps<T> taps, T* scale, X* grad_x, void* stream) {
  const int64_t P = d.H * d.W;
  if (P == 0) return;
  auto st = static_cast<cudaStream_t>(stream);
  if (d.radius == kFitRadius)
    launch_blur_backward<X, T, kFitRadius>(grad_blurred, grad_magnitude, x, magnitude, d, taps, scale, grad_x, st);
  else
    launch_blur_backward<X, T, -1>(grad_blurred, grad_magnitude, x, magnitude, d, taps, scale, grad_x, st);
}

#define TIGER_MAGNITUDE_BLUR_INSTANTIATE(X, T)                                                                   \
  template void launch_magnitude_blur_forward<X, T>(const X*, BlurDims, BlurTaps<T>, T*, T*, void*);            \
  template void launch_magnitude_blur_backward<X, T>(const T*, const T*, const X*, const T*, BlurDims, BlurTaps<T>, \
                                                     T*, X*, void*);
TIGER_MAGNITUDE_BLUR_INSTANTIATE(float, float)
TIGER_MAGNITUDE_BLUR_INSTANTIATE(double, double)
TIGER_MAGNITUDE_BLUR_INSTANTIATE(__nv_bfloat16, float)
TIGER_MAGNITUDE_BLUR_INSTANTIATE(__half, float)
#undef TIGER_MAGNITUDE_BLUR_INSTANTIATE

}  // namespace featup
}  // namespace tiger

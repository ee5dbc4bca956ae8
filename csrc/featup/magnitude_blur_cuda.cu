// CUDA kernels of tiger::magnitude_blur (formula in magnitude_blur.h; raw pointers, no torch
// headers). Channels last throughout: the magnitude is one warp per pixel (lanes over channels);
// the blur and its transpose are one thread per (pixel, channel), consecutive threads reading
// and writing consecutive channels of a pixel (coalesced). Every output is a gather of its own
// taps in a fixed order: no atomics, the same result on every run. Grid sizes depend only on the
// shapes: a CUDA graph may capture the launches.
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

template <typename X, typename T>
__global__ void __launch_bounds__(kThreads) blur_forward_kernel(const X* __restrict__ x,
                                                                const T* __restrict__ magnitude, BlurDims d,
                                                                BlurTaps<T> taps, T* __restrict__ blurred) {
  const int64_t U = d.C + 1, idx = int64_t(blockIdx.x) * kThreads + threadIdx.x;
  if (idx >= d.H * d.W * U) return;
  const int64_t p = idx / U, k = idx - p * U, y = p / d.W, xo = p - y * d.W;
  const int R = d.radius;
  T acc = 0;
  for (int a = -R; a <= R; ++a) {
    const int64_t row = reflect_index(y + a, d.H) * d.W;
    T sum = 0;
    for (int b = -R; b <= R; ++b) {
      const int64_t q = row + reflect_index(xo + b, d.W);
      const T v = k == 0 ? magnitude[q] : cuda::load_as<T>(x[q * d.C + k - 1]);
      sum += taps.g[b + R] * v;
    }
    acc += taps.g[a + R] * sum;
  }
  blurred[idx] = acc;
}

// gu[p, k] = (B^T grad_blurred)[p, k]: the transposed taps of p gathered over channel k.
template <typename T>
__device__ __forceinline__ T adjoint_blur(const T* __restrict__ grad_blurred, int64_t y, int64_t xo, int64_t k,
                                          const BlurDims& d, const BlurTaps<T>& taps) {
  AdjointTaps<T> ty, tx;
  adjoint_taps(y, d.H, taps.g, d.radius, ty);
  adjoint_taps(xo, d.W, taps.g, d.radius, tx);
  const int64_t U = d.C + 1;
  T acc = 0;
  for (int a = 0; a < ty.count; ++a) {
    const T* row = grad_blurred + ty.index[a] * d.W * U + k;
    T sum = 0;
    for (int b = 0; b < tx.count; ++b) sum += tx.weight[b] * row[tx.index[b] * U];
    acc += ty.weight[a] * sum;
  }
  return acc;
}

template <typename T>
__global__ void __launch_bounds__(kThreads) magnitude_scale_kernel(const T* __restrict__ grad_blurred,
                                                                   const T* __restrict__ grad_magnitude,
                                                                   const T* __restrict__ magnitude, BlurDims d,
                                                                   BlurTaps<T> taps, T* __restrict__ scale) {
  const int64_t p = int64_t(blockIdx.x) * kThreads + threadIdx.x;
  if (p >= d.H * d.W) return;
  const int64_t y = p / d.W, xo = p - y * d.W;
  const T g = adjoint_blur(grad_blurred, y, xo, 0, d, taps) + (grad_magnitude ? grad_magnitude[p] : T(0));
  const T m = magnitude[p];
  scale[p] = m > T(0) ? g / m : T(0);
}

template <typename X, typename T>
__global__ void __launch_bounds__(kThreads) grad_features_kernel(const T* __restrict__ grad_blurred,
                                                                 const X* __restrict__ x,
                                                                 const T* __restrict__ scale, BlurDims d,
                                                                 BlurTaps<T> taps, X* __restrict__ grad_x) {
  const int64_t idx = int64_t(blockIdx.x) * kThreads + threadIdx.x;
  if (idx >= d.H * d.W * d.C) return;
  const int64_t p = idx / d.C, c = idx - p * d.C, y = p / d.W, xo = p - y * d.W;
  const T g = adjoint_blur(grad_blurred, y, xo, c + 1, d, taps);
  grad_x[idx] = cuda::convert_to<X>(g + scale[p] * cuda::load_as<T>(x[idx]));
}

}  // namespace

template <typename X, typename T>
void launch_magnitude_blur_forward(const X* x, BlurDims d, BlurTaps<T> taps, T* blurred, T* magnitude,
                                   void* stream) {
  const int64_t P = d.H * d.W;
  if (P == 0) return;
  auto st = static_cast<cudaStream_t>(stream);
  magnitude_kernel<X, T><<<cuda::ceil_div(P, kWarps), kThreads, 0, st>>>(x, d, magnitude);
  blur_forward_kernel<X, T><<<cuda::ceil_div(P * (d.C + 1), kThreads), kThreads, 0, st>>>(x, magnitude, d, taps,
                                                                                           blurred);
}

template <typename X, typename T>
void launch_magnitude_blur_backward(const T* grad_blurred, const T* grad_magnitude, const X* x, const T* magnitude,
                                    BlurDims d, BlurTaps<T> taps, T* scale, X* grad_x, void* stream) {
  const int64_t P = d.H * d.W;
  if (P == 0) return;
  auto st = static_cast<cudaStream_t>(stream);
  magnitude_scale_kernel<T><<<cuda::ceil_div(P, kThreads), kThreads, 0, st>>>(grad_blurred, grad_magnitude,
                                                                               magnitude, d, taps, scale);
  grad_features_kernel<X, T><<<cuda::ceil_div(P * d.C, kThreads), kThreads, 0, st>>>(grad_blurred, x, scale, d,
                                                                                      taps, grad_x);
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

// CUDA kernels of tiger::relu_scale_layer_norm (formula in relu_norm.h; raw pointers, no torch
// headers). One warp per pixel, lane l holding channels l, l + 32, ... in registers (K per lane,
// D <= 32 K); the backward's weight and bias sums accumulate per lane over the warp's pixels,
// per block in warp order, then over the blocks in block order (no atomics: the same result on
// every run). Block counts depend only on the shapes: a CUDA graph may capture the launches.
#include <cuda_runtime.h>
#include <math.h>

#include <algorithm>
#include <type_traits>

#include "common/cuda_helpers.cuh"
#include "featup/relu_norm.h"

namespace tiger {
namespace featup {
namespace {

constexpr int kWarps = 8;
constexpr int kThreads = kWarps * 32;
constexpr int kForwardBlocksPerSm = 8;
constexpr int kMaxBackwardBlocks = 1024;
constexpr int kBackwardPixelsPerWarp = 4;

template <typename X, typename T, int K>
__global__ void __launch_bounds__(kThreads) relu_norm_forward_kernel(const X* __restrict__ x, const T* __restrict__ scale,
                                                                    const T* __restrict__ weight,
                                                                    const T* __restrict__ bias, NormDims d, T eps,
                                                                    X* __restrict__ out, T* mean, T* rstd) {
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5, D = static_cast<int>(d.D);
  const int64_t P = d.B * d.N;
  for (int64_t p = int64_t(blockIdx.x) * kWarps + warp; p < P; p += int64_t(gridDim.x) * kWarps) {
    const T* sc = scale ? scale + (p / d.N) * D : nullptr;
    T z[K];
    T sum = 0;
#pragma unroll
    for (int k = 0; k < K; ++k) {
      const int c = lane + 32 * k;
      z[k] = T(0);
      if (c < D) {
        const T v = cuda::load_as<T>(x[p * D + c]);
        z[k] = (v > T(0) ? v : T(0)) * (sc ? sc[c] : T(1));
        sum += z[k];
      }
    }
    const T m = cuda::warp_sum(sum) / T(D);
    T var = 0;
#pragma unroll
    for (int k = 0; k < K; ++k)
      if (lane + 32 * k < D) var += (z[k] - m) * (z[k] - m);
    const T r = cuda::reciprocal_sqrt(cuda::warp_sum(var) / T(D) + eps);
#pragma unroll
    for (int k = 0; k < K; ++k) {
      const int c = lane + 32 * k;
      if (c < D) out[p * D + c] = cuda::convert_to<X>((z[k] - m) * r * weight[c] + bias[c]);
    }
    if (lane == 0) {
      mean[p] = m;
      rstd[p] = r;
    }
  }
}

template <typename X, typename T, int K>
__global__ void __launch_bounds__(kThreads) relu_norm_backward_kernel(
    const X* __restrict__ grad, const X* __restrict__ x, const T* __restrict__ scale, const T* __restrict__ weight,
    const T* __restrict__ mean, const T* __restrict__ rstd, NormDims d, X* __restrict__ grad_x,
    T* __restrict__ partials) {
  extern __shared__ __align__(16) unsigned char smem_raw[];
  T* red = reinterpret_cast<T*>(smem_raw);  // [2D]: the block's sums
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5, D = static_cast<int>(d.D);
  const int64_t P = d.B * d.N;
  T acc_w[K], acc_b[K];
#pragma unroll
  for (int k = 0; k < K; ++k) acc_w[k] = acc_b[k] = T(0);
  for (int64_t p = int64_t(blockIdx.x) * kWarps + warp; p < P; p += int64_t(gridDim.x) * kWarps) {
    const T* sc = scale ? scale + (p / d.N) * D : nullptr;
    const T m = mean[p], r = rstd[p];
    T zh[K], gw[K];
    bool positive[K];
    T sum_gw = 0, sum_gwzh = 0;
#pragma unroll
    for (int k = 0; k < K; ++k) {
      const int c = lane + 32 * k;
      zh[k] = gw[k] = T(0);
      positive[k] = false;
      if (c < D) {
        const T v = cuda::load_as<T>(x[p * D + c]);
        positive[k] = v > T(0);
        zh[k] = ((positive[k] ? v : T(0)) * (sc ? sc[c] : T(1)) - m) * r;
        const T g = cuda::load_as<T>(grad[p * D + c]);
        acc_w[k] += g * zh[k];
        acc_b[k] += g;
        gw[k] = g * weight[c];
        sum_gw += gw[k];
        sum_gwzh += gw[k] * zh[k];
      }
    }
    const T mg = cuda::warp_sum(sum_gw) / T(D), mgzh = cuda::warp_sum(sum_gwzh) / T(D);
#pragma unroll
    for (int k = 0; k < K; ++k) {
      const int c = lane + 32 * k;
      if (c < D) {
        const T dz = r * (gw[k] - mg - zh[k] * mgzh);
        grad_x[p * D + c] = cuda::convert_to<X>(positive[k] ? dz * (sc ? sc[c] : T(1)) : T(0));
      }
    }
  }
  for (int w = 0; w < kWarps; ++w) {  // the warps' sums added in warp order
    if (warp == w) {
#pragma unroll
      for (int k = 0; k < K; ++k) {
        const int c = lane + 32 * k;
        if (c < D) {
          red[c] = w == 0 ? acc_w[k] : red[c] + acc_w[k];
          red[D + c] = w == 0 ? acc_b[k] : red[D + c] + acc_b[k];
        }
      }
    }
    __syncthreads();
  }
  for (int j = threadIdx.x; j < 2 * D; j += blockDim.x) partials[int64_t(blockIdx.x) * 2 * D + j] = red[j];
}

template <typename T>
__global__ void relu_norm_param_sum_kernel(const T* __restrict__ partials, int blocks, int D, T* grad_w, T* grad_b) {
  const int j = blockIdx.x * blockDim.x + threadIdx.x;
  if (j >= 2 * D) return;
  T total = 0;
  for (int k = 0; k < blocks; ++k) total += partials[int64_t(k) * 2 * D + j];
  (j < D ? grad_w[j] : grad_b[j - D]) = total;
}

// Calls f(std::integral_constant K) with the registers per lane that D needs.
template <typename Fn>
void with_lanes(int64_t D, Fn&& f) {
  if (D <= 128) {
    f(std::integral_constant<int, 4>{});
  } else if (D <= 256) {
    f(std::integral_constant<int, 8>{});
  } else {
    f(std::integral_constant<int, kMaxNormChannels / 32>{});
  }
}

}  // namespace

int relu_norm_backward_blocks(int64_t pixels) {
  return static_cast<int>(std::max<int64_t>(
      1, std::min<int64_t>(kMaxBackwardBlocks, cuda::ceil_div(pixels, kWarps * kBackwardPixelsPerWarp))));
}

template <typename X, typename T>
void launch_relu_norm_forward(const X* x, const T* scale, const T* weight, const T* bias, NormDims d, double eps,
                              X* out, T* mean, T* rstd, void* stream) {
  const int64_t P = d.B * d.N;
  if (P == 0) return;
  int device = 0, sms = 0;
  cudaGetDevice(&device);
  cudaDeviceGetAttribute(&sms, cudaDevAttrMultiProcessorCount, device);
  const int blocks = static_cast<int>(
      std::min<int64_t>(cuda::ceil_div(P, kWarps), int64_t(std::max(sms, 1)) * kForwardBlocksPerSm));
  auto st = static_cast<cudaStream_t>(stream);
  with_lanes(d.D, [&](auto k) {
    relu_norm_forward_kernel<X, T, decltype(k)::value><<<blocks, kThreads, 0, st>>>(
        x, scale, weight, bias, d, static_cast<T>(eps), out, mean, rstd);
  });
}

template <typename X, typename T>
void launch_relu_norm_backward(const X* grad_out, const X* x, const T* scale, const T* weight, const T* mean,
                               const T* rstd, NormDims d, X* grad_x, T* partials, int blocks, T* grad_weight,
                               T* grad_bias, void* stream) {
  auto st = static_cast<cudaStream_t>(stream);
  with_lanes(d.D, [&](auto k) {
    relu_norm_backward_kernel<X, T, decltype(k)::value><<<blocks, kThreads, 2 * d.D * sizeof(T), st>>>(
        grad_out, x, scale, weight, mean, rstd, d, grad_x, partials);
  });
  const int threads = 256, D = static_cast<int>(d.D);
  relu_norm_param_sum_kernel<T><<<cuda::ceil_div(2 * D, threads), threads, 0, st>>>(partials, blocks, D, grad_weight,
                                                                                    grad_bias);
}

#define TIGER_RELU_NORM_INSTANTIATE(X, T)                                                                       \
  template void launch_relu_norm_forward<X, T>(const X*, const T*, const T*, const T*, NormDims, double, X*, T*, \
                                               T*, void*);                                                       \
  template void launch_relu_norm_backward<X, T>(const X*, const X*, const T*, const T*, const T*, const T*,      \
                                                NormDims, X*, T*, int, T*, T*, void*);
TIGER_RELU_NORM_INSTANTIATE(float, float)
TIGER_RELU_NORM_INSTANTIATE(double, double)
TIGER_RELU_NORM_INSTANTIATE(__nv_bfloat16, float)
TIGER_RELU_NORM_INSTANTIATE(__half, float)
#undef TIGER_RELU_NORM_INSTANTIATE

}  // namespace featup
}  // namespace tiger

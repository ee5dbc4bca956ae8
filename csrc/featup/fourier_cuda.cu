// CUDA kernels of tiger::fourier_layer_norm (formula in fourier.h; raw pointers, no torch headers).
//
// One warp per pixel: lane l holds channels l, l + 32, ... in registers (K per lane, C <= 32 K),
// so the LayerNorm's sums are warp shuffles and each channel row is read or written once,
// coalesced, in the output dtype. The backward recomputes the features from the pixel's five
// inputs; its sums over pixels (phase, weight, bias gradients) accumulate per lane over the
// warp's pixels, then per block in warp order into one partial row per block, then over the
// blocks in block order (a second kernel): no atomics, the same result on every run. The
// numbers of blocks depend only on the shapes, so a CUDA graph may capture both launches.
#include <cuda_runtime.h>
#include <math.h>

#include <algorithm>
#include <type_traits>

#include "common/cuda_helpers.cuh"
#include "featup/fourier.h"
#include "featup/fourier_math.h"

namespace tiger {
namespace featup {
namespace {

constexpr int kWarps = 8;                 // pixels in flight per block
constexpr int kThreads = kWarps * 32;
constexpr int kForwardBlocksPerSm = 8;
constexpr int kMaxBackwardBlocks = 1024;  // partial rows of the backward
constexpr int kBackwardPixelsPerWarp = 4; // at least, before the block count grows

// The channel parameters every warp of a block reads, staged once per block in shared memory.
template <typename T>
struct SharedParams {
  T *weight, *bias, *phase, *freqs;
};

template <typename T>
__device__ SharedParams<T> stage_params(T* smem, const T* freqs, const T* phase, const T* weight, const T* bias,
                                        const FourierDims& d) {
  const int C = static_cast<int>(d.C), F = static_cast<int>(d.F), fourier = C - 3;
  SharedParams<T> s{smem, smem + C, smem + 2 * C, smem + 3 * C};
  for (int i = threadIdx.x; i < C; i += blockDim.x) {
    s.weight[i] = weight[i];
    s.bias[i] = bias ? bias[i] : T(0);
    s.phase[i] = i < fourier ? phase[i] : T(0);
    if (i < F) s.freqs[i] = freqs[i];
  }
  __syncthreads();
  return s;
}

// Feature x and, for a Fourier channel, dx/da of channel c of a pixel with inputs v.
template <typename T>
__device__ __forceinline__ void channel_value(const T* v, const SharedParams<T>& s, int c, int F,
                                              FourierChannel& ch, T& x, T& dxda) {
  ch = fourier_channel(c, F);
  if (ch.kind == 2) {
    x = select_input(v, ch.input);
    dxda = T(0);
    return;
  }
  T sn, cs;
  sin_cos(fourier_phase(v, s.freqs, s.phase, ch, c), &sn, &cs);
  x = ch.kind == 0 ? sn : cs;
  dxda = ch.kind == 0 ? cs : -sn;
}

template <typename T, typename O, int K>
__global__ void __launch_bounds__(kThreads) fourier_forward_kernel(const T* __restrict__ in, const T* freqs,
                                                                  const T* phase, const T* weight, const T* bias,
                                                                  const T* __restrict__ scale, FourierDims d, T eps,
                                                                  O* __restrict__ out, T* mean, T* rstd) {
  extern __shared__ __align__(16) unsigned char smem_raw[];
  const SharedParams<T> s = stage_params(reinterpret_cast<T*>(smem_raw), freqs, phase, weight, bias, d);
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5, C = static_cast<int>(d.C), F = static_cast<int>(d.F);
  const int64_t P = d.B * d.N;
  for (int64_t p = int64_t(blockIdx.x) * kWarps + warp; p < P; p += int64_t(gridDim.x) * kWarps) {
    T v[kFourierInputs];
#pragma unroll
    for (int i = 0; i < kFourierInputs; ++i) v[i] = in[p * kFourierInputs + i];
    T x[K];
    T sum = 0;
#pragma unroll
    for (int k = 0; k < K; ++k) {
      const int c = lane + 32 * k;
      x[k] = T(0);
      if (c < C) {
        FourierChannel ch;
        T dxda;
        channel_value(v, s, c, F, ch, x[k], dxda);
        sum += x[k];
      }
    }
    const T m = cuda::warp_sum(sum) / T(C);
    T var = 0;
#pragma unroll
    for (int k = 0; k < K; ++k)
      if (lane + 32 * k < C) var += (x[k] - m) * (x[k] - m);
    const T r = cuda::reciprocal_sqrt(cuda::warp_sum(var) / T(C) + eps);
    const T* sc = scale ? scale + (p / d.N) * C : nullptr;
    O* o = out + p * C;
#pragma unroll
    for (int k = 0; k < K; ++k) {
      const int c = lane + 32 * k;
      if (c < C) {
        T y = (x[k] - m) * r * s.weight[c] + s.bias[c];
        if (sc) y *= sc[c];
        o[c] = cuda::convert_to<O>(y);
      }
    }
    if (lane == 0) {
      mean[p] = m;
      rstd[p] = r;
    }
  }
}

// Two blocks per SM (at most 128 registers a thread): one block of 8 warps leaves too few
// loads in flight for a memory-bound pass.
template <typename T, typename O, int K>
__global__ void __launch_bounds__(kThreads, 2) fourier_backward_kernel(
    const O* __restrict__ grad, const T* __restrict__ in, const T* freqs, const T* phase, const T* weight,
    const T* __restrict__ scale, const T* __restrict__ mean, const T* __restrict__ rstd, FourierDims d,
    T* __restrict__ grad_in, T* __restrict__ partials) {
  extern __shared__ __align__(16) unsigned char smem_raw[];
  T* smem = reinterpret_cast<T*>(smem_raw);
  const SharedParams<T> s = stage_params<T>(smem, freqs, phase, weight, nullptr, d);
  T* red = smem + 4 * d.C;  // [3C]: the block's sums
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5, C = static_cast<int>(d.C), F = static_cast<int>(d.F);
  const int64_t P = d.B * d.N;
  T acc_phase[K], acc_w[K], acc_b[K];
#pragma unroll
  for (int k = 0; k < K; ++k) acc_phase[k] = acc_w[k] = acc_b[k] = T(0);
  for (int64_t p = int64_t(blockIdx.x) * kWarps + warp; p < P; p += int64_t(gridDim.x) * kWarps) {
    T v[kFourierInputs];
#pragma unroll
    for (int i = 0; i < kFourierInputs; ++i) v[i] = in[p * kFourierInputs + i];
    const T m = mean[p], r = rstd[p];
    const T* sc = scale ? scale + (p / d.N) * C : nullptr;
    const O* g_row = grad + p * C;
    T xh[K], gw[K], dxda[K];
    T sum_gw = 0, sum_gwxh = 0;
#pragma unroll
    for (int k = 0; k < K; ++k) {
      const int c = lane + 32 * k;
      xh[k] = gw[k] = dxda[k] = T(0);
      if (c < C) {
        FourierChannel ch;
        T x;
        channel_value(v, s, c, F, ch, x, dxda[k]);
        xh[k] = (x - m) * r;
        T g = cuda::load_as<T>(g_row[c]);
        if (sc) g *= sc[c];
        acc_w[k] += g * xh[k];
        acc_b[k] += g;
        gw[k] = g * s.weight[c];
        sum_gw += gw[k];
        sum_gwxh += gw[k] * xh[k];
      }
    }
    const T mg = cuda::warp_sum(sum_gw) / T(C), mgxh = cuda::warp_sum(sum_gwxh) / T(C);
    T gi[kFourierInputs] = {T(0), T(0), T(0), T(0), T(0)};
#pragma unroll
    for (int k = 0; k < K; ++k) {
      const int c = lane + 32 * k;
      if (c < C) {
        const FourierChannel ch = fourier_channel(c, F);
        const T dx = r * (gw[k] - mg - xh[k] * mgxh);
        T to_input = dx;
        if (ch.kind != 2) {
          const T da = dx * dxda[k];
          acc_phase[k] += da;
          to_input = s.freqs[ch.freq] * da;
        }
#pragma unroll
        for (int i = 0; i < kFourierInputs; ++i) gi[i] += ch.input == i ? to_input : T(0);
      }
    }
    if (grad_in) {
#pragma unroll
      for (int i = 0; i < kFourierInputs; ++i) {
        const T total = cuda::warp_sum(gi[i]);
        if (lane == 0) grad_in[p * kFourierInputs + i] = total;
      }
    }
  }
  // the warps' sums added in warp order (one [3C] buffer: 7C values of shared memory in all)
  for (int w = 0; w < kWarps; ++w) {
    if (warp == w) {
#pragma unroll
      for (int k = 0; k < K; ++k) {
        const int c = lane + 32 * k;
        if (c < C) {
          red[c] = w == 0 ? acc_phase[k] : red[c] + acc_phase[k];
          red[C + c] = w == 0 ? acc_w[k] : red[C + c] + acc_w[k];
          red[2 * C + c] = w == 0 ? acc_b[k] : red[2 * C + c] + acc_b[k];
        }
      }
    }
    __syncthreads();
  }
  for (int j = threadIdx.x; j < 3 * C; j += blockDim.x) partials[int64_t(blockIdx.x) * 3 * C + j] = red[j];
}

// grad_phase / grad_weight / grad_bias: the partial rows summed in block order.
template <typename T>
__global__ void fourier_param_sum_kernel(const T* __restrict__ partials, int blocks, FourierDims d, T* grad_phase,
                                         T* grad_weight, T* grad_bias) {
  const int C = static_cast<int>(d.C), j = blockIdx.x * blockDim.x + threadIdx.x;
  if (j >= 3 * C || (j >= C - 3 && j < C)) return;  // the colour channels have no phase
  T total = 0;
  for (int k = 0; k < blocks; ++k) total += partials[int64_t(k) * 3 * C + j];
  if (j < C) {
    grad_phase[j] = total;
  } else if (j < 2 * C) {
    grad_weight[j - C] = total;
  } else {
    grad_bias[j - 2 * C] = total;
  }
}

int forward_blocks(int64_t pixels) {
  int device = 0, sms = 0;
  cudaGetDevice(&device);
  cudaDeviceGetAttribute(&sms, cudaDevAttrMultiProcessorCount, device);
  return static_cast<int>(std::min<int64_t>(cuda::ceil_div(pixels, kWarps), int64_t(std::max(sms, 1)) * kForwardBlocksPerSm));
}

}  // namespace

int fourier_backward_blocks(int64_t pixels) {
  return static_cast<int>(
      std::max<int64_t>(1, std::min<int64_t>(kMaxBackwardBlocks, cuda::ceil_div(pixels, kWarps * kBackwardPixelsPerWarp))));
}

template <typename T, typename O>
void launch_fourier_forward(const T* inputs, const T* freqs, const T* phase, const T* weight, const T* bias,
                            const T* scale, FourierDims d, double eps, O* out, T* mean, T* rstd, void* stream) {
  const int64_t P = d.B * d.N;
  if (P == 0) return;
  const size_t smem = 4 * d.C * sizeof(T);
  auto st = static_cast<cudaStream_t>(stream);
  const int blocks = forward_blocks(P);
  if (d.C <= 32 * 10) {
    fourier_forward_kernel<T, O, 10><<<blocks, kThreads, smem, st>>>(inputs, freqs, phase, weight, bias, scale, d,
                                                                     static_cast<T>(eps), out, mean, rstd);
  } else {
    fourier_forward_kernel<T, O, kMaxFourierChannels / 32><<<blocks, kThreads, smem, st>>>(
        inputs, freqs, phase, weight, bias, scale, d, static_cast<T>(eps), out, mean, rstd);
  }
}

template <typename T, typename O>
void launch_fourier_backward(const O* grad_out, const T* inputs, const T* freqs, const T* phase, const T* weight,
                             const T* scale, const T* mean, const T* rstd, FourierDims d, T* grad_inputs,
                             T* partials, int blocks, T* grad_phase, T* grad_weight, T* grad_bias, void* stream) {
  auto st = static_cast<cudaStream_t>(stream);
  const size_t smem = 7 * d.C * sizeof(T);  // <= 28 KiB (C <= 512, double)
  if (d.C <= 32 * 10) {
    fourier_backward_kernel<T, O, 10><<<blocks, kThreads, smem, st>>>(grad_out, inputs, freqs, phase, weight, scale,
                                                                      mean, rstd, d, grad_inputs, partials);
  } else {
    fourier_backward_kernel<T, O, kMaxFourierChannels / 32><<<blocks, kThreads, smem, st>>>(
        grad_out, inputs, freqs, phase, weight, scale, mean, rstd, d, grad_inputs, partials);
  }
  const int threads = 256;
  fourier_param_sum_kernel<T><<<cuda::ceil_div(3 * d.C, threads), threads, 0, st>>>(partials, blocks, d, grad_phase,
                                                                                   grad_weight, grad_bias);
}

#define TIGER_FOURIER_INSTANTIATE(T, O)                                                                           \
  template void launch_fourier_forward<T, O>(const T*, const T*, const T*, const T*, const T*, const T*,           \
                                             FourierDims, double, O*, T*, T*, void*);                              \
  template void launch_fourier_backward<T, O>(const O*, const T*, const T*, const T*, const T*, const T*, const T*, \
                                              const T*, FourierDims, T*, T*, int, T*, T*, T*, void*);
TIGER_FOURIER_INSTANTIATE(float, float)
TIGER_FOURIER_INSTANTIATE(float, __nv_bfloat16)
TIGER_FOURIER_INSTANTIATE(float, __half)
TIGER_FOURIER_INSTANTIATE(double, double)
TIGER_FOURIER_INSTANTIATE(double, __nv_bfloat16)
TIGER_FOURIER_INSTANTIATE(double, __half)
#undef TIGER_FOURIER_INSTANTIATE

}  // namespace featup
}  // namespace tiger

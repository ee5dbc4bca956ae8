// y = x + bias[(n,) c] (+ residual) for NCHW and NHWC tensors. ATen's broadcast add takes its
// generic, unvectorised path for a [1, C, 1, 1] operand (an index computation per element); here
// every thread moves 16-byte vectors whose V elements share one channel (NCHW, H·W % V == 0) or
// hold V consecutive channels (NHWC, C % V == 0), with a scalar kernel for the other shapes. A
// vector never spans two samples, so a per-sample bias ([N, C]: a convolution's bias plus a
// ResNet block's time embedding) costs one index more. The residual (a ResNet block's shortcut)
// is read in the same pass: bias and residual cost one read-write of the map instead of two. An NHWC
// output may have rows longer than C (a channel slice of a wider channels-last map: the UNet up
// blocks' skip concatenations written in place), and the bias may be absent (a plain copy).
#include <cuda_bf16.h>
#include <cuda_fp16.h>
#include <cuda_runtime.h>

#include <algorithm>

#include "channel_bias/channel_bias_cuda.h"
#include "common/cuda_helpers.cuh"

namespace tiger {
namespace channel_bias {
namespace {

using tiger::cuda::load_as;
using tiger::cuda::store_as;
using tiger::cuda::Vec;

constexpr int kThreads = 256;

template <typename T, int V>
__global__ void __launch_bounds__(kThreads) bias_kernel(const T* __restrict__ x, const T* __restrict__ bias,
                                                        const T* __restrict__ residual, T* __restrict__ y,
                                                        int64_t n_vec, int64_t C, int64_t inner, int64_t plane,
                                                        int64_t out_row, bool per_sample, bool nhwc) {
  const int64_t stride = static_cast<int64_t>(gridDim.x) * blockDim.x;
  for (int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x; i < n_vec; i += stride) {
    const int64_t e = i * V;  // first element of the vector
    const T* b = bias == nullptr ? nullptr : per_sample ? bias + (e / plane) * C : bias;
    const Vec<T, V> xv = reinterpret_cast<const Vec<T, V>*>(x)[i];
    float acc[V];
    int64_t o = e;  // the output's first element
    if (b == nullptr) {
#pragma unroll
      for (int j = 0; j < V; ++j) acc[j] = load_as<float>(xv.v[j]);
      if (nhwc) o = (e / C) * out_row + e % C;
    } else if (nhwc) {
      const int64_t c0 = e % C;  // V consecutive channels (V divides C and out_row, or V == 1)
      o = (e / C) * out_row + c0;
#pragma unroll
      for (int j = 0; j < V; ++j) acc[j] = load_as<float>(xv.v[j]) + load_as<float>(b[c0 + j]);
    } else {
      const float bc = load_as<float>(b[(e / inner) % C]);  // one channel (V divides H·W, or V == 1)
#pragma unroll
      for (int j = 0; j < V; ++j) acc[j] = load_as<float>(xv.v[j]) + bc;
    }
    if (residual != nullptr) {
      const Vec<T, V> rv = reinterpret_cast<const Vec<T, V>*>(residual)[i];
#pragma unroll
      for (int j = 0; j < V; ++j) acc[j] += load_as<float>(rv.v[j]);
    }
    Vec<T, V> out;
#pragma unroll
    for (int j = 0; j < V; ++j) out.v[j] = store_as<T>(acc[j]);
    *reinterpret_cast<Vec<T, V>*>(y + o) = out;
  }
}

template <typename T, int V>
void launch(const T* x, const T* bias, const T* residual, T* y, int64_t n, int64_t C, int64_t inner, int64_t plane,
            int64_t out_row, bool per_sample, bool nhwc, cudaStream_t st) {
  const int64_t n_vec = n / V;
  const int64_t blocks = std::min<int64_t>((n_vec + kThreads - 1) / kThreads, 65535LL * 8);
  if (blocks > 0)
    bias_kernel<T, V><<<static_cast<unsigned>(blocks), kThreads, 0, st>>>(x, bias, residual, y, n_vec, C, inner, plane,
                                                                         out_row, per_sample, nhwc);
}

bool aligned(const void* p, int bytes) { return reinterpret_cast<uintptr_t>(p) % bytes == 0; }

// The sub-pixel upsampling's interleave: output row (n, oy, ox) (C values, rows out_row apart) is
// z's channel block 2a+b at pixel (n, i+a, j+b), oy = 2i+a, ox = 2j+b, plus the bias; z is NHWC
// [N, H+1, W+1, 4C]. Every thread moves 16-byte vectors of one row.
template <typename T, int V>
__global__ void __launch_bounds__(kThreads) interleave_kernel(const T* __restrict__ z, const T* __restrict__ bias,
                                                              T* __restrict__ y, int64_t n_vec, int64_t C, int64_t H,
                                                              int64_t W, int64_t out_row) {
  const int64_t stride = static_cast<int64_t>(gridDim.x) * blockDim.x;
  const int64_t cv = C / V;  // vectors per row
  for (int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x; i < n_vec; i += stride) {
    const int64_t c0 = (i % cv) * V;
    int64_t p = i / cv;  // output pixel
    const int64_t ox = p % (2 * W);
    p /= 2 * W;
    const int64_t oy = p % (2 * H);
    const int64_t n = p / (2 * H);
    const int a = static_cast<int>(oy & 1), b = static_cast<int>(ox & 1);
    const int64_t src = ((n * (H + 1) + (oy >> 1) + a) * (W + 1) + (ox >> 1) + b) * 4 * C + (2 * a + b) * C + c0;
    const Vec<T, V> zv = *reinterpret_cast<const Vec<T, V>*>(z + src);
    Vec<T, V> out;
#pragma unroll
    for (int j = 0; j < V; ++j) {
      const float v = load_as<float>(zv.v[j]) + (bias == nullptr ? 0.f : load_as<float>(bias[c0 + j]));
      out.v[j] = bias == nullptr ? zv.v[j] : store_as<T>(v);
    }
    *reinterpret_cast<Vec<T, V>*>(y + ((n * 2 * H + oy) * 2 * W + ox) * out_row + c0) = out;
  }
}

template <typename T, int V>
void launch_interleave_v(const T* z, const T* bias, T* y, int64_t N, int64_t C, int64_t H, int64_t W, int64_t out_row,
                         cudaStream_t st) {
  const int64_t n_vec = N * 4 * H * W * C / V;
  const int64_t blocks = std::min<int64_t>((n_vec + kThreads - 1) / kThreads, 65535LL * 8);
  if (blocks > 0)
    interleave_kernel<T, V><<<static_cast<unsigned>(blocks), kThreads, 0, st>>>(z, bias, y, n_vec, C, H, W, out_row);
}

}  // namespace

template <typename T>
void launch_subpixel_interleave(const T* z, const T* bias, T* y, int64_t N, int64_t C, int64_t H, int64_t W,
                                int64_t out_row, void* stream) {
  constexpr int V = 16 / sizeof(T);
  const auto st = static_cast<cudaStream_t>(stream);
  if (C % V == 0 && out_row % V == 0 && aligned(z, 16) && aligned(y, 16))
    launch_interleave_v<T, V>(z, bias, y, N, C, H, W, out_row, st);
  else
    launch_interleave_v<T, 1>(z, bias, y, N, C, H, W, out_row, st);
}

template <typename T>
void launch_channel_bias(const T* x, const T* bias, const T* residual, T* y, int64_t n, int64_t C, int64_t inner,
                         int64_t plane, int64_t out_row, bool per_sample, bool nhwc, void* stream) {
  constexpr int V = 16 / sizeof(T);
  const auto st = static_cast<cudaStream_t>(stream);
  const bool vec = (nhwc ? C % V == 0 && out_row % V == 0 : inner % V == 0) && aligned(x, 16) && aligned(y, 16) &&
                   (residual == nullptr || aligned(residual, 16));
  if (vec)
    launch<T, V>(x, bias, residual, y, n, C, inner, plane, out_row, per_sample, nhwc, st);
  else
    launch<T, 1>(x, bias, residual, y, n, C, inner, plane, out_row, per_sample, nhwc, st);
}

#define TIGER_CHANNEL_BIAS_INSTANTIATE(T)                                                                   \
  template void launch_channel_bias<T>(const T*, const T*, const T*, T*, int64_t, int64_t, int64_t, int64_t, \
                                       int64_t, bool, bool, void*);
#define TIGER_INTERLEAVE_INSTANTIATE(T) \
  template void launch_subpixel_interleave<T>(const T*, const T*, T*, int64_t, int64_t, int64_t, int64_t, int64_t, void*);
TIGER_INTERLEAVE_INSTANTIATE(float)
TIGER_INTERLEAVE_INSTANTIATE(__half)
TIGER_INTERLEAVE_INSTANTIATE(__nv_bfloat16)
#undef TIGER_INTERLEAVE_INSTANTIATE
TIGER_CHANNEL_BIAS_INSTANTIATE(float)
TIGER_CHANNEL_BIAS_INSTANTIATE(__half)
TIGER_CHANNEL_BIAS_INSTANTIATE(__nv_bfloat16)
#undef TIGER_CHANNEL_BIAS_INSTANTIATE

}  // namespace channel_bias
}  // namespace tiger

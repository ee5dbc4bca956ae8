// CUDA kernels of the fp8_rows family (formulas in ops.cpp).
//
// quantize_rows: one warp per row. Pass 1 reads the row (16-byte vectors) and reduces max |h|
// over the warp; pass 2 reads it again (from L2: a row is at most a few tens of KB) and writes
// V float8 bytes per vector. One read of x and a quarter/half-size write instead of the eager
// abs, amax, division and cast passes; amax and the scale stay on the device (no host sync, so
// CUDA-graph capturable). Divisions use __fdiv_rn: the library builds with --use_fast_math, and
// the scale must round as the CPU reference's IEEE division does.
//
// geglu: element-wise over [M, F], V outputs per thread from one vector of each half.
#include <cuda_bf16.h>
#include <cuda_fp16.h>
#include <cuda_fp8.h>
#include <cuda_runtime.h>

#include <algorithm>

#include "common/cuda_helpers.cuh"
#include "fp8_rows/fp8_rows.h"

namespace tiger {
namespace fp8_rows {
namespace {

using tiger::cuda::kFullMask;
using tiger::cuda::load_as;
using tiger::cuda::store_as;
using tiger::cuda::Vec;

constexpr int kThreads = 256;
constexpr int kWarps = kThreads / 32;

__device__ __forceinline__ float gelu(float g) { return 0.5f * g * (1.f + erff(g * 0.70710678118654752f)); }

// V values of h at vector v of a row (GEGLU: value half times gelu of the gate half).
template <typename T, int V, bool GEGLU>
__device__ __forceinline__ void load_h(const T* row, int64_t cols, int64_t v, float (&h)[V]) {
  const Vec<T, V> a = reinterpret_cast<const Vec<T, V>*>(row)[v];
  if (GEGLU) {
    const Vec<T, V> g = reinterpret_cast<const Vec<T, V>*>(row + cols)[v];
#pragma unroll
    for (int j = 0; j < V; ++j) h[j] = load_as<float>(a.v[j]) * gelu(load_as<float>(g.v[j]));
  } else {
#pragma unroll
    for (int j = 0; j < V; ++j) h[j] = load_as<float>(a.v[j]);
  }
}

template <typename T, int V, bool GEGLU>
__global__ void __launch_bounds__(kThreads) quantize_rows_kernel(const T* __restrict__ x, int64_t M, int64_t cols,
                                                                 unsigned char* __restrict__ q,
                                                                 float* __restrict__ scale) {
  const int lane = threadIdx.x % 32;
  const int64_t in_cols = GEGLU ? 2 * cols : cols;
  const int64_t n_vec = cols / V;
  const int64_t warp_stride = static_cast<int64_t>(gridDim.x) * kWarps;
  for (int64_t r = static_cast<int64_t>(blockIdx.x) * kWarps + threadIdx.x / 32; r < M; r += warp_stride) {
    const T* row = x + r * in_cols;
    float amax = 0.f;
    for (int64_t v = lane; v < n_vec; v += 32) {
      float h[V];
      load_h<T, V, GEGLU>(row, cols, v, h);
#pragma unroll
      for (int j = 0; j < V; ++j) amax = fmaxf(amax, fabsf(h[j]));
    }
#pragma unroll
    for (int o = 16; o >= 1; o >>= 1) amax = fmaxf(amax, __shfl_xor_sync(kFullMask, amax, o));
    const bool positive = amax > 0.f;
    const float inv = positive ? __fdiv_rn(kE4M3Max, amax) : 1.f;
    if (lane == 0) scale[r] = positive ? __fdiv_rn(amax, kE4M3Max) : 1.f;
    unsigned char* qrow = q + r * cols;
    for (int64_t v = lane; v < n_vec; v += 32) {
      float h[V];
      load_h<T, V, GEGLU>(row, cols, v, h);
      Vec<unsigned char, V> out;
#pragma unroll
      for (int j = 0; j < V; ++j)
        out.v[j] = static_cast<unsigned char>(__nv_cvt_float_to_fp8(__fmul_rn(h[j], inv), __NV_SATFINITE, __NV_E4M3));
      reinterpret_cast<Vec<unsigned char, V>*>(qrow)[v] = out;
    }
  }
}

template <typename T, int V>
__global__ void __launch_bounds__(kThreads) geglu_kernel(const T* __restrict__ x, int64_t M, int64_t F,
                                                         T* __restrict__ y) {
  const int64_t per_row = F / V, n_vec = M * per_row;
  const int64_t stride = static_cast<int64_t>(gridDim.x) * blockDim.x;
  for (int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x; i < n_vec; i += stride) {
    const int64_t r = i / per_row, v = i % per_row;
    float h[V];
    load_h<T, V, true>(x + r * 2 * F, F, v, h);
    Vec<T, V> out;
#pragma unroll
    for (int j = 0; j < V; ++j) out.v[j] = store_as<T>(h[j]);
    reinterpret_cast<Vec<T, V>*>(y + r * F)[v] = out;
  }
}

bool aligned(const void* p, int bytes) { return reinterpret_cast<uintptr_t>(p) % bytes == 0; }

unsigned blocks_for(int64_t work, int64_t per_block) {
  return static_cast<unsigned>(std::max<int64_t>(1, std::min<int64_t>((work + per_block - 1) / per_block, 65535LL * 8)));
}

template <typename T, int V>
void quantize_impl(const T* x, int64_t M, int64_t cols, bool geglu, unsigned char* q, float* scale, cudaStream_t st) {
  const unsigned blocks = blocks_for(M, kWarps);
  if (geglu)
    quantize_rows_kernel<T, V, true><<<blocks, kThreads, 0, st>>>(x, M, cols, q, scale);
  else
    quantize_rows_kernel<T, V, false><<<blocks, kThreads, 0, st>>>(x, M, cols, q, scale);
}

}  // namespace

template <typename T>
void launch_quantize_rows(const T* x, int64_t M, int64_t cols, bool geglu, unsigned char* q, float* scale,
                          void* stream) {
  if (M == 0) return;
  constexpr int V = 16 / sizeof(T);
  const auto st = static_cast<cudaStream_t>(stream);
  // Vectors need every row (and, for GEGLU, the gate half) to start 16-byte aligned in x and
  // V-byte aligned in q: cols % V == 0 and aligned base pointers.
  if (cols % V == 0 && aligned(x, 16) && aligned(q, V))
    quantize_impl<T, V>(x, M, cols, geglu, q, scale, st);
  else
    quantize_impl<T, 1>(x, M, cols, geglu, q, scale, st);
}

template <typename T>
void launch_geglu(const T* x, int64_t M, int64_t F, T* y, void* stream) {
  if (M == 0 || F == 0) return;
  constexpr int V = 16 / sizeof(T);
  const auto st = static_cast<cudaStream_t>(stream);
  if (F % V == 0 && aligned(x, 16) && aligned(y, 16))
    geglu_kernel<T, V><<<blocks_for(M * (F / V), kThreads), kThreads, 0, st>>>(x, M, F, y);
  else
    geglu_kernel<T, 1><<<blocks_for(M * F, kThreads), kThreads, 0, st>>>(x, M, F, y);
}

#define TIGER_FP8_ROWS_INSTANTIATE(T)                                                                         \
  template void launch_quantize_rows<T>(const T*, int64_t, int64_t, bool, unsigned char*, float*, void*); \
  template void launch_geglu<T>(const T*, int64_t, int64_t, T*, void*);
TIGER_FP8_ROWS_INSTANTIATE(float)
TIGER_FP8_ROWS_INSTANTIATE(__half)
TIGER_FP8_ROWS_INSTANTIATE(__nv_bfloat16)
#undef TIGER_FP8_ROWS_INSTANTIATE

}  // namespace fp8_rows
}  // namespace tiger

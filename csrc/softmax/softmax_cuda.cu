// Softmax over rows of L contiguous values (and its backward), one block per row, the row held in
// registers as float: one read and one write of the map forward, two reads and one write backward.
// Written for the VAE attention's scores (4 x 4096 rows of 4096 bf16 values at 512² renders), where
// torch's kernels ran at 0.42x (forward) and 0.51x (backward) of the H100's copy bandwidth
// (benchmarks/gpu/results/guidance_roofline_h100.txt). Each thread keeps K 16-byte vectors; the
// block's max and sums go through warp shuffles and one shared-memory step. Values as torch's
// softmax: float arithmetic with expf and a division by the row sum, rounded once.
#include <cuda_bf16.h>
#include <cuda_fp16.h>
#include <cuda_runtime.h>

#include <cmath>
#include <cstdint>

#include "common/cuda_helpers.cuh"
#include "softmax/softmax_cuda.h"

namespace tiger {
namespace softmax {
namespace {

using tiger::cuda::kFullMask;
using tiger::cuda::load_as;
using tiger::cuda::store_as;
using tiger::cuda::Vec;

constexpr int kMaxThreads = 256;
constexpr int kMaxVecs = 8;  // vectors a thread keeps: rows of up to 256 x 8 vectors (16384 bf16 values)

template <typename T>
constexpr int vec_width() {
  return 16 / static_cast<int>(sizeof(T));
}

// The block's max (MAX) or sum of v, returned to every thread; `shm` holds one value per warp.
template <bool MAX>
__device__ __forceinline__ float block_reduce(float v, float* shm) {
  for (int o = 16; o > 0; o >>= 1) {
    const float u = __shfl_xor_sync(kFullMask, v, o);
    v = MAX ? fmaxf(v, u) : v + u;
  }
  const int warps = blockDim.x / 32;
  if ((threadIdx.x & 31) == 0) shm[threadIdx.x / 32] = v;
  __syncthreads();
  float r = shm[0];
  for (int w = 1; w < warps; ++w) r = MAX ? fmaxf(r, shm[w]) : r + shm[w];  // the same order in every thread
  return r;
}

template <typename T, int K>
__global__ void __launch_bounds__(kMaxThreads) forward_kernel(const T* __restrict__ x, T* __restrict__ y, int nv) {
  constexpr int V = vec_width<T>();
  __shared__ float shm_max[kMaxThreads / 32], shm_sum[kMaxThreads / 32];
  const int64_t row = blockIdx.x;
  const auto* xr = reinterpret_cast<const Vec<T, V>*>(x) + row * nv;
  auto* yr = reinterpret_cast<Vec<T, V>*>(y) + row * nv;
  float e[K][V];
  float m = -INFINITY;
#pragma unroll
  for (int k = 0; k < K; ++k) {
    const int i = threadIdx.x + k * blockDim.x;
    if (i < nv) {
      const Vec<T, V> v = xr[i];
#pragma unroll
      for (int j = 0; j < V; ++j) {
        e[k][j] = load_as<float>(v.v[j]);
        m = fmaxf(m, e[k][j]);
      }
    }
  }
  m = block_reduce<true>(m, shm_max);
  float s = 0.f;
#pragma unroll
  for (int k = 0; k < K; ++k) {
    if (threadIdx.x + k * blockDim.x < nv) {
#pragma unroll
      for (int j = 0; j < V; ++j) {
        e[k][j] = expf(e[k][j] - m);
        s += e[k][j];
      }
    }
  }
  s = block_reduce<false>(s, shm_sum);
#pragma unroll
  for (int k = 0; k < K; ++k) {
    const int i = threadIdx.x + k * blockDim.x;
    if (i < nv) {
      Vec<T, V> out;
#pragma unroll
      for (int j = 0; j < V; ++j) out.v[j] = store_as<T>(e[k][j] / s);
      yr[i] = out;
    }
  }
}

template <typename T, int K>
__global__ void __launch_bounds__(kMaxThreads) backward_kernel(const T* __restrict__ y, const T* __restrict__ dy,
                                                               T* __restrict__ dx, int nv) {
  constexpr int V = vec_width<T>();
  __shared__ float shm[kMaxThreads / 32];
  const int64_t row = blockIdx.x;
  const auto* yr = reinterpret_cast<const Vec<T, V>*>(y) + row * nv;
  const auto* gr = reinterpret_cast<const Vec<T, V>*>(dy) + row * nv;
  auto* dr = reinterpret_cast<Vec<T, V>*>(dx) + row * nv;
  float p[K][V], g[K][V];
  float dot = 0.f;
#pragma unroll
  for (int k = 0; k < K; ++k) {
    const int i = threadIdx.x + k * blockDim.x;
    if (i < nv) {
      const Vec<T, V> a = yr[i], b = gr[i];
#pragma unroll
      for (int j = 0; j < V; ++j) {
        p[k][j] = load_as<float>(a.v[j]);
        g[k][j] = load_as<float>(b.v[j]);
        dot = fmaf(p[k][j], g[k][j], dot);
      }
    }
  }
  dot = block_reduce<false>(dot, shm);
#pragma unroll
  for (int k = 0; k < K; ++k) {
    const int i = threadIdx.x + k * blockDim.x;
    if (i < nv) {
      Vec<T, V> out;
#pragma unroll
      for (int j = 0; j < V; ++j) out.v[j] = store_as<T>(p[k][j] * (g[k][j] - dot));
      dr[i] = out;
    }
  }
}

// Vectors a thread keeps (1, 2, 4 or 8) and threads a block (a multiple of 32, at most 256) for nv vectors.
void plan(int64_t nv, int& vecs, int& threads) {
  vecs = 1;
  while (nv > static_cast<int64_t>(kMaxThreads) * vecs) vecs *= 2;
  const int64_t per = (nv + vecs - 1) / vecs;
  threads = static_cast<int>((per + 31) / 32 * 32);
}

bool aligned(const void* p) { return p == nullptr || reinterpret_cast<uintptr_t>(p) % 16 == 0; }

}  // namespace

template <typename T>
bool rows_supported(int64_t L, const void* a, const void* b, const void* c) {
  constexpr int V = vec_width<T>();
  return L % V == 0 && L / V <= static_cast<int64_t>(kMaxThreads) * kMaxVecs && aligned(a) && aligned(b) && aligned(c);
}

#define TIGER_SOFTMAX_DISPATCH(KERNEL, ...)                                                     \
  switch (vecs) {                                                                               \
    case 1: KERNEL<T, 1><<<static_cast<unsigned>(M), threads, 0, st>>>(__VA_ARGS__); break;    \
    case 2: KERNEL<T, 2><<<static_cast<unsigned>(M), threads, 0, st>>>(__VA_ARGS__); break;    \
    case 4: KERNEL<T, 4><<<static_cast<unsigned>(M), threads, 0, st>>>(__VA_ARGS__); break;    \
    default: KERNEL<T, 8><<<static_cast<unsigned>(M), threads, 0, st>>>(__VA_ARGS__); break;   \
  }

template <typename T>
void launch_softmax_rows(const T* x, T* y, int64_t M, int64_t L, void* stream) {
  const auto st = static_cast<cudaStream_t>(stream);
  const int nv = static_cast<int>(L / vec_width<T>());
  int vecs, threads;
  plan(nv, vecs, threads);
  TIGER_SOFTMAX_DISPATCH(forward_kernel, x, y, nv)
}

template <typename T>
void launch_softmax_rows_backward(const T* y, const T* dy, T* dx, int64_t M, int64_t L, void* stream) {
  const auto st = static_cast<cudaStream_t>(stream);
  const int nv = static_cast<int>(L / vec_width<T>());
  int vecs, threads;
  plan(nv, vecs, threads);
  TIGER_SOFTMAX_DISPATCH(backward_kernel, y, dy, dx, nv)
}
#undef TIGER_SOFTMAX_DISPATCH

#define TIGER_SOFTMAX_INSTANTIATE(T)                                                                   \
  template bool rows_supported<T>(int64_t, const void*, const void*, const void*);                  \
  template void launch_softmax_rows<T>(const T*, T*, int64_t, int64_t, void*);                      \
  template void launch_softmax_rows_backward<T>(const T*, const T*, T*, int64_t, int64_t, void*);
TIGER_SOFTMAX_INSTANTIATE(float)
TIGER_SOFTMAX_INSTANTIATE(__half)
TIGER_SOFTMAX_INSTANTIATE(__nv_bfloat16)
#undef TIGER_SOFTMAX_INSTANTIATE

}  // namespace softmax
}  // namespace tiger

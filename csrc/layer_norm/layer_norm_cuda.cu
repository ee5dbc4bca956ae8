// LayerNorm over rows of C contiguous values. PyTorch's CUDA LayerNorm gives every row a block of
// 128 threads; the UNets' rows are short (320-1280 channels, 40-160 16-byte vectors), so most of
// those threads idle and the blocks are too short-lived to keep the memory system busy (48 norms
// of InstructPix2Pix's UNet took 1.7 ms, about 3.5x their read-and-write floor on an H100). Here a
// group of G lanes of one warp owns a row (G the power of two that gives each lane at most 4
// vectors, at most 32), keeps its vectors in registers (up to 4 a lane where G < 32, else up to
// 8; longer rows are re-read), and reduces over the group with shuffles: mean first, then the
// sum of squared deviations (two passes over registers, no cancellation), then the output,
// rounded once. An optional input bias (a per-channel vector the residual stream has not added
// yet) is added in float wherever a value is read, so the biased row is never written.
#include <cuda_bf16.h>
#include <cuda_fp16.h>
#include <cuda_runtime.h>

#include <algorithm>
#include <type_traits>

#include "common/cuda_helpers.cuh"
#include "layer_norm/layer_norm_cuda.h"

namespace tiger {
namespace layer_norm {
namespace {

using tiger::cuda::convert_to;
using tiger::cuda::kFullMask;
using tiger::cuda::load_as;
using tiger::cuda::reciprocal_sqrt;
using tiger::cuda::Vec;

constexpr int kThreads = 256;
// Vectors a lane keeps in registers: 4 where the row's lanes number fewer than 32 (G is chosen to
// give each at most 4), 8 for the longest rows. Registers sized for 8 on every row left the
// 64² transformer rows (49152 x 320, bf16) at ~45 % of the H100's bandwidth: the unused slots
// held registers (bf16 instances 99-104 a thread, two blocks per SM; with 4: 48 without an input
// bias, 72 with one, five and three blocks). A minimum of four blocks a SM (64 registers) spilled
// the input-bias instance and gained nothing net (benchmarks/gpu/NOTES.md).
constexpr int kMaxVecs = 8;

template <typename T>
using Acc = std::conditional_t<std::is_same_v<T, double>, double, float>;

// Sum over the G aligned lanes of a group (G a power of two <= 32), returned to each of them.
template <typename A>
__device__ __forceinline__ A group_sum(A v, int G) {
  for (int o = G / 2; o > 0; o >>= 1) v += __shfl_xor_sync(kFullMask, v, o);
  return v;
}

template <typename T, int V>
__device__ __forceinline__ Vec<T, V> load_vec(const T* p, int64_t i) {
  return reinterpret_cast<const Vec<T, V>*>(p)[i];
}

// SHIFT: input_bias is given. A separate instance, so that rows without one keep a kernel with
// no trace of it (the runtime test and its loads cost ~10% on the UNets' rows, H100).
template <typename T, int V, bool SHIFT, int VECS>
__global__ void __launch_bounds__(kThreads) rows_kernel(const T* __restrict__ x, const T* __restrict__ weight,
                                                        const T* __restrict__ bias,
                                                        const T* __restrict__ input_bias, T* __restrict__ y,
                                                        int64_t M, int nv, int C, int G, Acc<T> eps) {
  using A = Acc<T>;
  const int lane = threadIdx.x & 31;
  const int rows_per_warp = 32 / G;
  const int64_t warp = static_cast<int64_t>(blockIdx.x) * (kThreads / 32) + threadIdx.x / 32;
  const int64_t row = warp * rows_per_warp + lane / G;
  const int sub = lane % G;
  const bool valid = row < M;  // every lane takes part in the shuffles
  const T* xr = x + (valid ? row : 0) * C;
  const bool in_regs = nv <= G * VECS;

  // Vector i of the row plus the input bias, in float.
  auto widen = [&](const Vec<T, V>& v, int i, A (&u)[V]) {
#pragma unroll
    for (int j = 0; j < V; ++j) u[j] = load_as<A>(v.v[j]);
    if constexpr (SHIFT) {
      const Vec<T, V> b = load_vec<T, V>(input_bias, i);
#pragma unroll
      for (int j = 0; j < V; ++j) u[j] += load_as<A>(b.v[j]);
    }
  };

  Vec<T, V> reg[VECS];
  A u[V];
  A sum = A(0);
  if (in_regs) {
#pragma unroll
    for (int k = 0; k < VECS; ++k) {
      const int i = sub + k * G;
      if (valid && i < nv) {
        reg[k] = load_vec<T, V>(xr, i);
        widen(reg[k], i, u);
#pragma unroll
        for (int j = 0; j < V; ++j) sum += u[j];
      }
    }
  } else if (valid) {
    for (int i = sub; i < nv; i += G) {
      widen(load_vec<T, V>(xr, i), i, u);
#pragma unroll
      for (int j = 0; j < V; ++j) sum += u[j];
    }
  }
  const A mean = group_sum(sum, G) / A(C);

  // Every vector of the row: from the registers, or read again when the row is longer.
  auto each_vector = [&](auto&& use) {
    if (in_regs) {
#pragma unroll
      for (int k = 0; k < VECS; ++k) {
        const int i = sub + k * G;
        if (valid && i < nv) use(reg[k], i);
      }
    } else if (valid) {
      for (int i = sub; i < nv; i += G) use(load_vec<T, V>(xr, i), i);
    }
  };

  A sq = A(0);
  each_vector([&](const Vec<T, V>& v, int i) {
    widen(v, i, u);
#pragma unroll
    for (int j = 0; j < V; ++j) {
      const A d = u[j] - mean;
      sq += d * d;
    }
  });
  const A rstd = reciprocal_sqrt(group_sum(sq, G) / A(C) + eps);
  if (!valid) return;

  T* yr = y + row * C;
  auto write = [&](const Vec<T, V>& v, int i) {
    const Vec<T, V> wv = load_vec<T, V>(weight, i);
    Vec<T, V> bv;
    if (bias != nullptr) bv = load_vec<T, V>(bias, i);
    A w[V];
    widen(v, i, w);
    Vec<T, V> out;
#pragma unroll
    for (int j = 0; j < V; ++j) {
      A r = (w[j] - mean) * rstd * load_as<A>(wv.v[j]);
      if (bias != nullptr) r += load_as<A>(bv.v[j]);
      out.v[j] = convert_to<T>(r);
    }
    reinterpret_cast<Vec<T, V>*>(yr)[i] = out;
  };
  each_vector(write);
}

template <typename T, int V>
void launch(const T* x, const T* weight, const T* bias, const T* input_bias, T* y, int64_t M, int64_t C, double eps,
            cudaStream_t st) {
  const int nv = static_cast<int>(C / V);
  int G = 1;  // the power of two giving each lane at most 4 vectors, at most a warp
  while (G < 32 && static_cast<int64_t>(G) * 4 < nv) G *= 2;
  const int64_t rows_per_block = (kThreads / 32) * (32 / G);
  const int64_t blocks = (M + rows_per_block - 1) / rows_per_block;
  if (blocks <= 0) return;
  const auto grid = static_cast<unsigned>(blocks);
  const int c = static_cast<int>(C);
  const auto e = static_cast<Acc<T>>(eps);
#define TIGER_LN_ROWS(SHIFT, VECS) \
  rows_kernel<T, V, SHIFT, VECS><<<grid, kThreads, 0, st>>>(x, weight, bias, input_bias, y, M, nv, c, G, e)
  if (G < 32) {  // nv <= 4·G
    if (input_bias != nullptr) TIGER_LN_ROWS(true, 4); else TIGER_LN_ROWS(false, 4);
  } else {
    if (input_bias != nullptr) TIGER_LN_ROWS(true, kMaxVecs); else TIGER_LN_ROWS(false, kMaxVecs);
  }
#undef TIGER_LN_ROWS
}

bool aligned(const void* p) { return p == nullptr || reinterpret_cast<uintptr_t>(p) % 16 == 0; }

}  // namespace

template <typename T>
void launch_layer_norm_rows(const T* x, const T* weight, const T* bias, const T* input_bias, T* y, int64_t M,
                            int64_t C, double eps, void* stream) {
  constexpr int V = 16 / sizeof(T);
  const auto st = static_cast<cudaStream_t>(stream);
  if (C % V == 0 && aligned(x) && aligned(y) && aligned(weight) && aligned(bias) && aligned(input_bias))
    launch<T, V>(x, weight, bias, input_bias, y, M, C, eps, st);
  else
    launch<T, 1>(x, weight, bias, input_bias, y, M, C, eps, st);
}

#define TIGER_LAYER_NORM_ROWS(T) \
  template void launch_layer_norm_rows<T>(const T*, const T*, const T*, const T*, T*, int64_t, int64_t, double, void*);
TIGER_LAYER_NORM_ROWS(float)
TIGER_LAYER_NORM_ROWS(double)
TIGER_LAYER_NORM_ROWS(__half)
TIGER_LAYER_NORM_ROWS(__nv_bfloat16)
#undef TIGER_LAYER_NORM_ROWS

}  // namespace layer_norm
}  // namespace tiger

#pragma once
// Device helpers shared by the group_norm kernels (group_norm_cuda.cu: the three-kernel walks;
// group_norm_sliced_cuda.cu: the L2-sliced forward).
#include <cuda_runtime.h>

#include "common/cuda_helpers.cuh"
#include "group_norm/group_norm.h"

namespace tiger {
namespace group_norm {
namespace walk {

using tiger::cuda::load_as;

constexpr int kFinalThreads = 128;

template <typename T>
__device__ __forceinline__ float param_at(const Params& p, const void* ptr, int64_t c, float fill) {
  if (ptr == nullptr) return fill;
  return p.params_float ? static_cast<const float*>(ptr)[c] : load_as<float>(static_cast<const T*>(ptr)[c]);
}

__device__ __forceinline__ float sigmoid(float z) { return 1.f / (1.f + __expf(-z)); }

// Chan's merge of (count, mean, M2) b into a.
__device__ __forceinline__ void merge(float& n, float& mean, float& m2, float nb, float meanb, float m2b) {
  if (nb == 0.f) return;
  const float tot = n + nb;
  const float f = nb / tot;
  const float delta = meanb - mean;
  mean += delta * f;
  m2 += m2b + delta * delta * n * f;
  n = tot;
}

// Tree over the R thread rows of a block (slot = ty·cvt + tx), fixed order; after it slot tx
// (ty = 0) holds the column's result. P is the power of two >= R.
__device__ __forceinline__ int pow2_at_least(int r) {
  int p = 1;
  while (p < r) p <<= 1;
  return p;
}

// Rows r0, r0 + step, ... < r1 in order, loading B rows before using them: the loads of a batch
// are in flight together (one 16-byte load per thread at a time left the walks latency bound at
// 50-70 % of the H100's bandwidth). The use order is the plain loop's: same results. B = 4 for
// the one-tensor walks, 2 for the two-tensor ones (x and dy: 4 loads in flight either way; 4 rows
// of both took ~160 registers a thread, one block per SM).
template <int B, typename Load, typename Use>
__device__ __forceinline__ void walk_rows(int64_t r0, int64_t r1, int64_t step, Load load, Use use) {
  int64_t r = r0;
  for (; r + (B - 1) * step < r1; r += B * step) {
    decltype(load(r)) v[B];
#pragma unroll
    for (int u = 0; u < B; ++u) v[u] = load(r + u * step);
#pragma unroll
    for (int u = 0; u < B; ++u) use(r + u * step, v[u]);
  }
  for (; r < r1; r += step) use(r, load(r));
}

// Input bias of (n, c) (0 when absent): added to every element of the channel, shifts included,
// so the per-channel moments (relative to the shift) need no change.
__device__ __forceinline__ float input_bias_at(const float* ib, int64_t C, int64_t n, int64_t c) {
  return ib == nullptr ? 0.f : ib[n * C + c];
}

}  // namespace walk
}  // namespace group_norm
}  // namespace tiger

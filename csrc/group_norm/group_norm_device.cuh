#pragma once
// Per-element helpers shared by tiger::group_norm's kernel files (group_norm_cuda.cu's walks and
// group_norm_small_cuda.cu's one-launch kernels).
#include <cuda_runtime.h>

#include "common/cuda_helpers.cuh"
#include "group_norm/group_norm.h"

namespace tiger {
namespace group_norm {

// Affine parameter c (x's dtype T or float32, Params::params_float); fill where absent.
template <typename T>
__device__ __forceinline__ float param_at(const Params& p, const void* ptr, int64_t c, float fill) {
  if (ptr == nullptr) return fill;
  return p.params_float ? static_cast<const float*>(ptr)[c]
                        : tiger::cuda::load_as<float>(static_cast<const T*>(ptr)[c]);
}

// Input bias of (n, c) (0 when absent); row_stride: Params::input_bias_stride.
__device__ __forceinline__ float input_bias_at(const float* ib, int64_t row_stride, int64_t n, int64_t c) {
  return ib == nullptr ? 0.f : ib[n * row_stride + c];
}

__device__ __forceinline__ float sigmoid(float z) { return 1.f / (1.f + __expf(-z)); }

// dz of one element from d = x − m (m = mean − input bias), a = rstd·w and b: dy·SiLU'(z) at
// z = d·a + b, or dy without SiLU.
template <bool SILU>
__device__ __forceinline__ float dz_of(float d, float dy, float a, float b) {
  if (!SILU) return dy;
  const float z = d * a + b, s = sigmoid(z);
  return dy * s * (1.f + z * (1.f - s));
}

}  // namespace group_norm
}  // namespace tiger

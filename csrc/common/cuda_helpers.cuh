#pragma once
// Device helpers shared by the CUDA kernels (no torch headers: CI compiles every
// .cu with nvcc alone). The formulas themselves live in the *_math.h headers.
#include <cuda_bf16.h>
#include <cuda_fp16.h>
#include <cuda_runtime.h>
#include <stdint.h>

#include <type_traits>

namespace tiger {
namespace cuda {

constexpr unsigned kFullMask = 0xffffffffu;

inline int ceil_div(int64_t a, int64_t b) { return static_cast<int>((a + b - 1) / b); }

// Storage type of per-Gaussian channels -> accumulation type (cast at load).
template <typename T>
__device__ __forceinline__ T load_as(float v) { return T(v); }
template <typename T>
__device__ __forceinline__ T load_as(double v) { return T(v); }
template <typename T>
__device__ __forceinline__ T load_as(__half v) { return T(__half2float(v)); }
template <typename T>
__device__ __forceinline__ T load_as(__nv_bfloat16 v) { return T(__bfloat162float(v)); }

// float -> storage type, rounded once (the inverse of load_as for the reduced types).
template <typename T>
__device__ __forceinline__ T store_as(float v);
template <>
__device__ __forceinline__ float store_as<float>(float v) { return v; }
template <>
__device__ __forceinline__ __half store_as<__half>(float v) { return __float2half(v); }
template <>
__device__ __forceinline__ __nv_bfloat16 store_as<__nv_bfloat16>(float v) { return __float2bfloat16(v); }

// An accumulation value (float or double) -> storage type O: itself when O is T or both are
// float / double, else through float (half, bf16).
template <typename O, typename T>
__device__ __forceinline__ O convert_to(T v) {
  if constexpr (std::is_same_v<O, T> || (std::is_floating_point_v<O> && std::is_floating_point_v<T>)) {
    return static_cast<O>(v);
  } else {
    return store_as<O>(static_cast<float>(v));
  }
}

// Sum over the 32 lanes of a warp, returned to every lane.
template <typename T>
__device__ __forceinline__ T warp_sum(T v) {
  for (int o = 16; o > 0; o >>= 1) v += __shfl_xor_sync(kFullMask, v, o);
  return v;
}

// 1 / sqrt(v), correctly rounded in float (fast-math builds would approximate 1 / sqrtf).
template <typename T>
__device__ __forceinline__ T reciprocal_sqrt(T v) {
  if constexpr (sizeof(T) == 4) {
    return 1.0f / __fsqrt_rn(v);
  } else {
    return 1.0 / sqrt(v);
  }
}

// V elements moved as one aligned vector (16 bytes for V = 16 / sizeof(T)).
template <typename T, int V>
struct alignas(sizeof(T) * V) Vec {
  T v[V];
};

// One halving exchange of the reduce-scatter below: lanes whose bit H is set keep the
// upper half v[H..2H) and send the lower half, the others the opposite. Recursion (not a
// run-time loop) keeps every index a compile-time constant, so v stays in registers.
template <int H, int N, typename T>
__device__ __forceinline__ void reduce_scatter_step(T (&v)[N], int lane) {
  if constexpr (H >= 1) {
    const bool upper = (lane & H) != 0;
#pragma unroll
    for (int i = 0; i < H; ++i) {
      const T send = upper ? v[i] : v[i + H];
      const T keep = upper ? v[i + H] : v[i];
      v[i] = keep + __shfl_xor_sync(kFullMask, send, H);
    }
    reduce_scatter_step<H / 2>(v, lane);
  }
}

// Reduce-scatter of N values held by every lane of a full warp: afterwards lane L holds
// the warp-wide sum of value (L % N). Halving exchanges cost N-1 shuffles plus
// log2(32/N) for the final reduction, instead of 5 shuffles per value for N separate
// butterfly reductions. N must be a power of two <= 32; v is clobbered.
template <int N, typename T>
__device__ __forceinline__ T warp_reduce_scatter(T (&v)[N], int lane) {
  static_assert(N >= 1 && N <= 32 && (N & (N - 1)) == 0, "N must be a power of two <= 32");
  reduce_scatter_step<N / 2>(v, lane);
  T s = v[0];
#pragma unroll
  for (int m = N; m < 32; m *= 2) s += __shfl_xor_sync(kFullMask, s, m);
  return s;
}

// Order-preserving map of a float depth to unsigned bits (negative depths too).
__device__ __forceinline__ uint32_t depth_key_bits(float d) {
  const uint32_t b = __float_as_uint(d);
  return (b & 0x80000000u) ? ~b : (b | 0x80000000u);
}
__device__ __forceinline__ uint64_t depth_key_bits64(double d) {
  const uint64_t b = static_cast<uint64_t>(__double_as_longlong(d));
  return (b & 0x8000000000000000ull) ? ~b : (b | 0x8000000000000000ull);
}

}  // namespace cuda
}  // namespace tiger

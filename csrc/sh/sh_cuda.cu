// CUDA kernels of the spherical-harmonics ops: one thread per Gaussian, the same
// sh_eval / sh_eval_vjp as the CPU kernels (optionally with rows staged in shared memory).
#include <cstdlib>
#include <type_traits>

#include "common/cuda_helpers.cuh"
#include "common/sh_math.h"
#include "sh_cuda.h"

namespace tiger {
namespace {

template <typename T>
__global__ void sh_kernel(const T* dirs, const T* coeffs, int64_t n, int64_t k, int degree,
                          const bool* visible, T* colors) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n || (visible && !visible[i])) return;
  sh_eval<T>(degree, dirs + 3 * i, coeffs + i * k * 3, colors + 3 * i);
}

template <typename T>
__global__ void sh_backward_kernel(const T* dirs, const T* coeffs, int64_t n, int64_t k,
                                   int degree, const bool* visible, const T* v_colors, T* v_dirs,
                                   T* v_coeffs) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n || (visible && !visible[i])) return;
  sh_eval_vjp<T>(degree, dirs + 3 * i, coeffs + i * k * 3, v_colors + 3 * i, v_coeffs + i * k * 3,
                 v_dirs + 3 * i);
}

constexpr int kThreads = 256;

// Staged variants (float; the default, TIGER_SH_STAGED=0 selects the plain kernels): a block copies its
// Gaussians' coefficient rows [rows, k, 3] between global and shared memory with consecutive
// threads on consecutive words, so the 4·3·k-byte rows of neighbouring threads are read and
// written in coalesced transactions instead of one strided row per thread. The shared row is
// padded to an odd length (3k + 1 words): thread t's row starts in bank (t·(3k+1)) mod 32, all
// different within a warp. Every row of the block is written (zeros for invisible Gaussians and
// unused bases), like the zero-initialised output of the plain kernel.
constexpr int kStagedThreads = 64;

// Block-local indices are 32-bit (kStagedThreads rows of 3k words, within 48 KiB): a 64-bit
// division per copied word cost more than the copy (the first device run of these kernels).
__device__ __forceinline__ int staged_rows(int64_t n) {
  return static_cast<int>(min(static_cast<int64_t>(blockDim.x), n - static_cast<int64_t>(blockIdx.x) * blockDim.x));
}

__device__ __forceinline__ void stage_in(const float* g, float* s, int rows, int width, int row) {
  const float* src = g + static_cast<int64_t>(blockIdx.x) * blockDim.x * width;
  for (int e = threadIdx.x; e < rows * width; e += blockDim.x) {
    const int r = e / width;
    s[r * row + (e - r * width)] = src[e];
  }
}

__device__ __forceinline__ void stage_out(const float* s, float* g, int rows, int width, int row) {
  float* dst = g + static_cast<int64_t>(blockIdx.x) * blockDim.x * width;
  for (int e = threadIdx.x; e < rows * width; e += blockDim.x) {
    const int r = e / width;
    dst[e] = s[r * row + (e - r * width)];
  }
}

__global__ void __launch_bounds__(kStagedThreads) sh_staged_kernel(const float* dirs, const float* coeffs, int64_t n,
                                                                   int64_t k, int degree, const bool* visible,
                                                                   float* colors) {
  extern __shared__ float s_coeffs[];  // [blockDim][3k + 1]
  const int width = static_cast<int>(3 * k), row = width + 1, rows = staged_rows(n);
  stage_in(coeffs, s_coeffs, rows, width, row);
  __syncthreads();
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (threadIdx.x < rows && !(visible && !visible[i]))
    sh_eval<float>(degree, dirs + 3 * i, s_coeffs + threadIdx.x * row, colors + 3 * i);
}

__global__ void __launch_bounds__(kStagedThreads) sh_backward_staged_kernel(const float* dirs, const float* coeffs,
                                                                            int64_t n, int64_t k, int degree,
                                                                            const bool* visible, const float* v_colors,
                                                                            float* v_dirs, float* v_coeffs) {
  extern __shared__ float s_mem[];  // coefficients, then their gradients: [blockDim][3k + 1] each
  const int width = static_cast<int>(3 * k), row = width + 1, rows = staged_rows(n);
  float* s_coeffs = s_mem;
  float* s_grad = s_mem + blockDim.x * row;
  stage_in(coeffs, s_coeffs, rows, width, row);
  for (int e = threadIdx.x; e < static_cast<int>(blockDim.x) * row; e += blockDim.x) s_grad[e] = 0.f;
  __syncthreads();
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (threadIdx.x < rows && !(visible && !visible[i]))
    sh_eval_vjp<float>(degree, dirs + 3 * i, s_coeffs + threadIdx.x * row, v_colors + 3 * i,
                       s_grad + threadIdx.x * row, v_dirs + 3 * i);
  __syncthreads();
  stage_out(s_grad, v_coeffs, rows, width, row);
}

bool staged_enabled() {
  static const bool on = [] {
    // measured on the H100 at 1M Gaussians, degree 3: forward+backward 2.05 ms plain, 0.97 staged
    const char* v = std::getenv("TIGER_SH_STAGED");
    return v == nullptr || v[0] != '0';
  }();
  return on;
}

size_t staged_bytes(int64_t k, int buffers) {
  return static_cast<size_t>(buffers) * kStagedThreads * (3 * k + 1) * sizeof(float);
}

}  // namespace

template <typename T>
cudaError_t sh_to_color_cuda_launch(const T* dirs, const T* coeffs, int64_t n, int64_t k,
                                    int degree, const bool* visible, T* colors,
                                    cudaStream_t stream) {
  if (n == 0) return cudaSuccess;
  if constexpr (std::is_same<T, float>::value) {
    if (staged_enabled() && staged_bytes(k, 1) <= 48 * 1024) {
      sh_staged_kernel<<<cuda::ceil_div(n, kStagedThreads), kStagedThreads, staged_bytes(k, 1), stream>>>(
          dirs, coeffs, n, k, degree, visible, colors);
      return cudaGetLastError();
    }
  }
  sh_kernel<T><<<cuda::ceil_div(n, kThreads), kThreads, 0, stream>>>(dirs, coeffs, n, k, degree,
                                                                      visible, colors);
  return cudaGetLastError();
}

template <typename T>
cudaError_t sh_to_color_backward_cuda_launch(const T* dirs, const T* coeffs, int64_t n, int64_t k,
                                             int degree, const bool* visible, const T* v_colors,
                                             T* v_dirs, T* v_coeffs, cudaStream_t stream) {
  if (n == 0) return cudaSuccess;
  if constexpr (std::is_same<T, float>::value) {
    if (staged_enabled() && staged_bytes(k, 2) <= 48 * 1024) {
      sh_backward_staged_kernel<<<cuda::ceil_div(n, kStagedThreads), kStagedThreads, staged_bytes(k, 2), stream>>>(
          dirs, coeffs, n, k, degree, visible, v_colors, v_dirs, v_coeffs);
      return cudaGetLastError();
    }
  }
  sh_backward_kernel<T><<<cuda::ceil_div(n, kThreads), kThreads, 0, stream>>>(
      dirs, coeffs, n, k, degree, visible, v_colors, v_dirs, v_coeffs);
  return cudaGetLastError();
}

#define TIGER_INSTANTIATE(T)                                                                    \
  template cudaError_t sh_to_color_cuda_launch<T>(const T*, const T*, int64_t, int64_t, int,    \
                                                  const bool*, T*, cudaStream_t);               \
  template cudaError_t sh_to_color_backward_cuda_launch<T>(const T*, const T*, int64_t, int64_t, \
                                                           int, const bool*, const T*, T*, T*,  \
                                                           cudaStream_t);
TIGER_INSTANTIATE(float)
TIGER_INSTANTIATE(double)
#undef TIGER_INSTANTIATE

}  // namespace tiger

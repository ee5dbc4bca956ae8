// CUDA kernels of the spherical-harmonics ops: one thread per Gaussian, the same
// sh_eval / sh_eval_vjp as the CPU kernels.
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

}  // namespace

template <typename T>
cudaError_t sh_to_color_cuda_launch(const T* dirs, const T* coeffs, int64_t n, int64_t k,
                                    int degree, const bool* visible, T* colors,
                                    cudaStream_t stream) {
  if (n == 0) return cudaSuccess;
  sh_kernel<T><<<cuda::ceil_div(n, kThreads), kThreads, 0, stream>>>(dirs, coeffs, n, k, degree,
                                                                      visible, colors);
  return cudaGetLastError();
}

template <typename T>
cudaError_t sh_to_color_backward_cuda_launch(const T* dirs, const T* coeffs, int64_t n, int64_t k,
                                             int degree, const bool* visible, const T* v_colors,
                                             T* v_dirs, T* v_coeffs, cudaStream_t stream) {
  if (n == 0) return cudaSuccess;
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

#pragma once
// Raw-pointer launchers of the CUDA spherical-harmonics kernels (no torch headers).
#include <cuda_runtime_api.h>
#include <stdint.h>

namespace tiger {

// colors [N,3] must be zero-filled by the caller (invisible Gaussians keep 0).
template <typename T>
cudaError_t sh_to_color_cuda_launch(const T* dirs, const T* coeffs, int64_t n, int64_t k,
                                    int degree, const bool* visible, T* colors,
                                    cudaStream_t stream);

// v_dirs [N,3], v_coeffs [N,K,3] zero-filled by the caller.
template <typename T>
cudaError_t sh_to_color_backward_cuda_launch(const T* dirs, const T* coeffs, int64_t n, int64_t k,
                                             int degree, const bool* visible, const T* v_colors,
                                             T* v_dirs, T* v_coeffs, cudaStream_t stream);

}  // namespace tiger

#pragma once
// Raw-pointer launchers of the CUDA spherical-harmonics kernels (no torch headers).
#include <cuda_runtime_api.h>
#include <stdint.h>

namespace tiger {

// The plain kernels: colors [N,3] must be zero-filled by the caller (invisible Gaussians keep 0).
template <typename T>
cudaError_t sh_to_color_cuda_launch(const T* dirs, const T* coeffs, int64_t n, int64_t k,
                                    int degree, const bool* visible, T* colors,
                                    cudaStream_t stream);

// The plain kernels. v_dirs [N,3] and v_coeffs [N,K,3] zero-filled by the caller (invisible rows
// are skipped).
template <typename T>
cudaError_t sh_to_color_backward_cuda_launch(const T* dirs, const T* coeffs, int64_t n, int64_t k,
                                             int degree, const bool* visible, const T* v_colors,
                                             T* v_dirs, T* v_coeffs, cudaStream_t stream);

// Whether float32 rows of k bases fit the staged kernels (shared memory must hold them).
bool sh_staged_fits(int64_t k);

// The staged kernels (float; only when sh_staged_fits(k0 + k1)): the coefficient row of
// Gaussian i is cat(c0[i], c1[i]) with c0 [N,k0,3] and c1 [N,k1,3] (c1 may be null with k1 = 0),
// each a contiguous [k,3] block per row, rows pitch0 / pitch1 words apart: e.g. a scene's DC and
// higher bands without building the [N,K,3] tensor. colors [N,3] zero-filled by the caller. The
// backward writes contiguous v0 [N,k0,3] and v1 [N,k1,3], every row (v_dirs [N,3] zero-filled by
// the caller).
cudaError_t sh_to_color_staged_cuda_launch(const float* dirs, const float* c0, int64_t pitch0, int64_t k0,
                                          const float* c1, int64_t pitch1, int64_t k1, int64_t n, int degree,
                                          const bool* visible, float* colors, cudaStream_t stream);
cudaError_t sh_to_color_backward_staged_cuda_launch(const float* dirs, const float* c0, int64_t pitch0, int64_t k0,
                                                   const float* c1, int64_t pitch1, int64_t k1, int64_t n,
                                                   int degree, const bool* visible, const float* v_colors,
                                                   float* v_dirs, float* v0, float* v1, cudaStream_t stream);

}  // namespace tiger

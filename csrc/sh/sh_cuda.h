#pragma once
// Raw-pointer launchers of the CUDA spherical-harmonics kernels (no torch headers).
//
// Every kernel takes V views of the same N Gaussians (V = 1: one view): dirs, colors, v_colors
// and v_dirs are [V,N,3] and visible [V,N] (null: every row of every view), contiguous; the
// coefficients [N,K,3] are shared by the views. One thread per Gaussian loops its views
// (sh_eval_views / sh_eval_vjp_views of common/sh_math.h, as the CPU kernels), so each
// coefficient row is read once and its gradient written once, the views' sum.
#include <cuda_runtime_api.h>
#include <stdint.h>

namespace tiger {

// The plain kernels: colors [V,N,3] must be zero-filled by the caller (invisible rows keep 0).
template <typename T>
cudaError_t sh_to_color_cuda_launch(const T* dirs, const T* coeffs, int64_t views, int64_t n, int64_t k,
                                    int degree, const bool* visible, T* colors, cudaStream_t stream);

// The plain kernels. v_dirs [V,N,3] and v_coeffs [N,K,3] zero-filled by the caller: the rows with
// trainable[i] false (trainable [N], null: all) and the (view, row) pairs with visible false are
// skipped.
template <typename T>
cudaError_t sh_to_color_backward_cuda_launch(const T* dirs, const T* coeffs, int64_t views, int64_t n,
                                             int64_t k, int degree, const bool* visible,
                                             const bool* trainable, const T* v_colors, T* v_dirs,
                                             T* v_coeffs, cudaStream_t stream);

// Whether float32 rows of k bases fit the staged kernels (shared memory must hold them).
bool sh_staged_fits(int64_t k);

// The staged kernels (float; only when sh_staged_fits(k0 + k1)): the coefficient row of
// Gaussian i is cat(c0[i], c1[i]) with c0 [N,k0,3] and c1 [N,k1,3] (c1 may be null with k1 = 0),
// each a contiguous [k,3] block per row, rows pitch0 / pitch1 words apart: e.g. a scene's DC and
// higher bands without building the [N,K,3] tensor. A row is staged once and serves all V views.
// colors [V,N,3] zero-filled by the caller. The backward writes contiguous v0 [N,k0,3] and
// v1 [N,k1,3], every row (v_dirs [V,N,3] zero-filled by the caller).
cudaError_t sh_to_color_staged_cuda_launch(const float* dirs, const float* c0, int64_t pitch0, int64_t k0,
                                          const float* c1, int64_t pitch1, int64_t k1, int64_t views, int64_t n,
                                          int degree, const bool* visible, float* colors, cudaStream_t stream);
cudaError_t sh_to_color_backward_staged_cuda_launch(const float* dirs, const float* c0, int64_t pitch0, int64_t k0,
                                                   const float* c1, int64_t pitch1, int64_t k1, int64_t views,
                                                   int64_t n, int degree, const bool* visible,
                                                   const bool* trainable, const float* v_colors, float* v_dirs,
                                                   float* v0, float* v1, cudaStream_t stream);

}  // namespace tiger

#pragma once
// Spherical harmonics (degree 0-3, INRIA order) -> RGB for a view direction.
//
// sh_to_color: dirs [N,3] (any length; normalised inside), coeffs [N,K,3] with
//   K >= (degree+1)^2, degree in [0,3], optional visible [N] bool (others give 0), optional
//   rest [N,K1,3]: the coefficients are then cat(coeffs, rest) along K (a scene's DC band and
//   its higher bands, read where they are: float32 CUDA reads both in place)
//   -> colors [N,3] = sum_k coeffs[:,k] * Y_k(dir)   (no +0.5 offset, no clamp).
// sh_to_color_backward: v_colors [N,3] -> (v_dirs [N,3], v_coeffs [N,K,3], v_rest [N,K1,3]
//   or [0] without rest).
// trainable (both ops; optional [N] bool): the rows whose gradients the backward computes; the
//   others get zero gradients and cost no gradient work (an edit's frozen Gaussians). The forward
//   only carries it to the backward (its values do not depend on it).
// _staged (both ops; a CUDA choice, the CPU ignores it): float32 rows that fit go through the
//   staged kernels (the default); False sends them through the plain kernels, which float64 and
//   very long rows always take (same arithmetic, bit for bit: kept for comparisons).
#include <ATen/ATen.h>

#include <optional>
#include <tuple>

namespace tiger {

void check_sh_inputs(const char* op, const at::Tensor& dirs, const at::Tensor& coeffs, int64_t degree,
                     const std::optional<at::Tensor>& visible, const std::optional<at::Tensor>& rest);

// The rows the backward walks: visible and trainable (either may be absent).
std::optional<at::Tensor> backward_rows(const std::optional<at::Tensor>& visible,
                                        const std::optional<at::Tensor>& trainable);

// The coefficients as one [N,K,3] tensor (cat with rest), and the backward's split of its
// gradient into (v_coeffs, v_rest) (v_rest: [0] without rest): the paths that do not read the
// two tensors in place.
at::Tensor joined_coeffs(const at::Tensor& coeffs, const std::optional<at::Tensor>& rest);
std::tuple<at::Tensor, at::Tensor> split_coeff_grads(const at::Tensor& v_all, const at::Tensor& coeffs,
                                                     const std::optional<at::Tensor>& rest);

at::Tensor sh_to_color_cpu(const at::Tensor& dirs, const at::Tensor& coeffs, int64_t degree,
                           const std::optional<at::Tensor>& visible, const std::optional<at::Tensor>& rest,
                           bool staged, const std::optional<at::Tensor>& trainable);

std::tuple<at::Tensor, at::Tensor, at::Tensor> sh_to_color_backward_cpu(
    const at::Tensor& dirs, const at::Tensor& coeffs, int64_t degree, const std::optional<at::Tensor>& visible,
    const at::Tensor& v_colors, const std::optional<at::Tensor>& rest, bool staged,
    const std::optional<at::Tensor>& trainable);

}  // namespace tiger

#pragma once
// Spherical harmonics (degree 0-3, INRIA order) -> RGB for a view direction.
//
// sh_to_color: dirs [N,3] (any length; normalised inside), coeffs [N,K,3] with
//   K >= (degree+1)^2, degree in [0,3], optional visible [N] bool (others give 0)
//   -> colors [N,3] = sum_k coeffs[:,k] * Y_k(dir)   (no +0.5 offset, no clamp).
// sh_to_color_backward: v_colors [N,3] -> (v_dirs [N,3], v_coeffs [N,K,3]).
#include <ATen/ATen.h>

#include <optional>
#include <tuple>

namespace tiger {

void check_sh_inputs(const char* op, const at::Tensor& dirs, const at::Tensor& coeffs, int64_t degree,
                     const std::optional<at::Tensor>& visible);

at::Tensor sh_to_color_cpu(const at::Tensor& dirs, const at::Tensor& coeffs, int64_t degree,
                           const std::optional<at::Tensor>& visible);

std::tuple<at::Tensor, at::Tensor> sh_to_color_backward_cpu(const at::Tensor& dirs,
                                                            const at::Tensor& coeffs, int64_t degree,
                                                            const std::optional<at::Tensor>& visible,
                                                            const at::Tensor& v_colors);

}  // namespace tiger

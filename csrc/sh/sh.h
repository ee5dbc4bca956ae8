#pragma once
// Spherical harmonics (degree 0-3, INRIA order) -> RGB for a view direction.
//
// sh_to_color: dirs [N,3] (one view) or [V,N,3] (V views of the same N Gaussians; any length,
//   normalised inside), coeffs [N,K,3] with K >= (degree+1)^2, degree in [0,3], optional visible
//   bool of dirs' leading shape, [N] or [V,N] (others give 0), optional rest [N,K1,3]: the
//   coefficients are then cat(coeffs, rest) along K (a scene's DC band and its higher bands, read
//   where they are: float32 CUDA reads both in place)
//   -> colors of dirs' shape, [N,3] or [V,N,3] = sum_k coeffs[:,k] * Y_k(dir)   (no +0.5 offset,
//   no clamp). A V-view call reads each coefficient row once for all its views.
// sh_to_color_backward: v_colors of dirs' shape -> (v_dirs of dirs' shape, v_coeffs [N,K,3],
//   v_rest [N,K1,3] or [0] without rest). With V views the coefficient gradients are the sums
//   over the views, added in view order inside the kernel (sh_eval_vjp_views): one [N,K,3]
//   gradient instead of V of them summed by autograd. One view: the one-view op, bit for bit.
// trainable (both ops; optional [N] bool, shared by the views): the rows whose gradients the
//   backward computes; the others get zero gradients and cost no gradient work (an edit's frozen
//   Gaussians). The forward only carries it to the backward (its values do not depend on it).
// _staged (both ops; a CUDA choice, the CPU ignores it): float32 rows that fit go through the
//   staged kernels (the default); False sends them through the plain kernels, which float64 and
//   very long rows always take (same arithmetic, bit for bit: kept for comparisons).
#include <ATen/ATen.h>

#include <optional>
#include <tuple>

namespace tiger {

// A call's views (1 for dirs [N, 3]) and Gaussians.
struct ShViews {
  int64_t views, n;
};

// Checks the inputs shared by both ops (dirs, coeffs, degree, visible, rest): one error naming
// the op, the tensor and the shape expected.
ShViews check_sh_inputs(const char* op, const at::Tensor& dirs, const at::Tensor& coeffs, int64_t degree,
                        const std::optional<at::Tensor>& visible, const std::optional<at::Tensor>& rest);

// A per-view tensor: dirs' shape (xyz: v_colors) or dirs' shape without its last dimension
// (visible), the given dtype, dirs' device.
void check_per_view(const at::Tensor& t, const at::Tensor& dirs, const char* op, const char* name,
                    at::ScalarType dtype, bool xyz);

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

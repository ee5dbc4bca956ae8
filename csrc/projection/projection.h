#pragma once
// EWA projection of 3D Gaussians to the image plane.
//
// project_gaussians
//   means [N,3], quats [N,4] (w,x,y,z, any norm), scales [N,3] (linear), opacities [N] in [0,1],
//   viewmat [4,4] world->camera (OpenCV axes), K [3,3] pinhole intrinsics; all one float dtype.
//   -> means2d [N,2] px, conics [N,3] (a, b, c of the inverse dilated 2D covariance),
//      depths [N] camera z, opacities_out [N] (after antialias compensation),
//      radii [N,2] int32 opacity-aware half extents in px (0 = culled).
//   trainable (optional [N] bool, not read by the forward): the rows whose gradients the
//   backward computes; its autograd formula hands the backward op radii with the other rows
//   zeroed, so they are skipped like culled ones (zero gradients, nothing added to the camera's).
// project_gaussians_backward: gradients of the above w.r.t. means, quats, scales,
//   opacities, viewmat [4,4] (rows 0-2) and K [3,3] (fx, fy, cx, cy); culled Gaussians get 0.
#include <ATen/ATen.h>

#include <optional>
#include <tuple>

namespace tiger {

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> project_gaussians_cpu(
    const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
    const at::Tensor& opacities, const at::Tensor& viewmat, const at::Tensor& K, int64_t width,
    int64_t height, double eps2d, double near_plane, double far_plane, double alpha_threshold,
    bool antialiased, const std::optional<at::Tensor>& trainable);

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor>
project_gaussians_backward_cpu(const at::Tensor& means, const at::Tensor& quats,
                               const at::Tensor& scales, const at::Tensor& opacities,
                               const at::Tensor& viewmat, const at::Tensor& K, const at::Tensor& radii,
                               int64_t width, int64_t height, double eps2d, bool antialiased,
                               const at::Tensor& v_means2d, const at::Tensor& v_conics,
                               const at::Tensor& v_depths, const at::Tensor& v_opacities,
                               bool camera_grad);

// viewmat [4,4] and K [3,3] gradients from per-Gaussian rows [N,16] (R row-major with t in
// column 3, then fx, fy, cx, cy), summed in double: the per-Gaussian terms cancel strongly.
// Zeros when camera_grad is false.
std::tuple<at::Tensor, at::Tensor> camera_grads_from_rows(const at::Tensor& rows, bool camera_grad,
                                                          const at::TensorOptions& options);

// Shared argument validation (CPU and CUDA glue).
void check_projection_inputs(const char* op, const at::Tensor& means, const at::Tensor& quats,
                             const at::Tensor& scales, const at::Tensor& opacities,
                             const at::Tensor& viewmat, const at::Tensor& K, int64_t width,
                             int64_t height);

}  // namespace tiger

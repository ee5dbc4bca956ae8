// Torch glue of the CUDA projection kernels (built only with CUDA on).
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <torch/library.h>

#include "common/torch_checks.h"
#include "projection.h"
#include "projection_cuda.h"

namespace tiger {

namespace {
template <typename T>
ProjectLaunch<T> make_launch(const at::Tensor& m, const at::Tensor& q, const at::Tensor& s,
                             const at::Tensor& o, const at::Tensor& V, const at::Tensor& K,
                             int64_t width, int64_t height, double eps2d, double near_plane,
                             double far_plane, double alpha_threshold, bool antialiased) {
  return {m.data_ptr<T>(), q.data_ptr<T>(), s.data_ptr<T>(), o.data_ptr<T>(), V.data_ptr<T>(),
          K.data_ptr<T>(), m.size(0), int(width), int(height), T(eps2d), T(near_plane),
          T(far_plane), T(alpha_threshold), antialiased};
}

// An incoming gradient [N] or [N, k] in dtype dt whose last dimension is contiguous (rows may
// be strided: the rasterizer's backward returns views of its [N, 8] buffer, read in place).
at::Tensor gradient_rows(const at::Tensor& g, at::ScalarType dt) {
  at::Tensor t = g.to(dt);
  if (t.dim() == 2 && t.stride(1) != 1) t = t.contiguous();
  if (t.size(0) <= 1) t = t.contiguous();  // stride(0) of a 1-row view may be arbitrary
  return t;
}
}  // namespace

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> project_gaussians_cuda(
    const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
    const at::Tensor& opacities, const at::Tensor& viewmat, const at::Tensor& K, int64_t width,
    int64_t height, double eps2d, double near_plane, double far_plane, double alpha_threshold,
    bool antialiased, const std::optional<at::Tensor>& trainable) {
  const char* op = "tiger.project_gaussians";
  check_projection_inputs(op, means, quats, scales, opacities, viewmat, K, width, height);
  check_row_mask(trainable, means.size(0), means, op, "trainable", "means");  // for the backward (autograd formula)
  const c10::cuda::CUDAGuard guard(means.device());
  const int64_t n = means.size(0);
  // The kernel writes every row (zeros for culled Gaussians): no zero fills to launch.
  auto means2d = at::empty({n, 2}, means.options());
  auto conics = at::empty({n, 3}, means.options());
  auto depths = at::empty({n}, means.options());
  auto opac_out = at::empty({n}, means.options());
  auto radii = at::empty({n, 2}, means.options().dtype(at::kInt));
  const auto m = means.contiguous(), q = quats.contiguous(), s = scales.contiguous(),
             o = opacities.contiguous(), V = viewmat.contiguous(), Kc = K.contiguous();
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "project_gaussians_cuda", [&] {
    using T = scalar_t;
    const auto a = make_launch<T>(m, q, s, o, V, Kc, width, height, eps2d, near_plane, far_plane,
                                  alpha_threshold, antialiased);
    const cudaError_t err = project_gaussians_cuda_launch<T>(
        a, means2d.data_ptr<T>(), conics.data_ptr<T>(), depths.data_ptr<T>(),
        opac_out.data_ptr<T>(), radii.data_ptr<int32_t>(), c10::cuda::getCurrentCUDAStream().stream());
    TORCH_CHECK(err == cudaSuccess, op, ": CUDA kernel failed: ", cudaGetErrorString(err));
  });
  return {means2d, conics, depths, opac_out, radii};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor>
project_gaussians_backward_cuda(const at::Tensor& means, const at::Tensor& quats,
                                const at::Tensor& scales, const at::Tensor& opacities,
                                const at::Tensor& viewmat, const at::Tensor& K,
                                const at::Tensor& radii, int64_t width, int64_t height,
                                double eps2d, bool antialiased, const at::Tensor& v_means2d,
                                const at::Tensor& v_conics, const at::Tensor& v_depths,
                                const at::Tensor& v_opacities, bool camera_grad) {
  const char* op = "tiger.project_gaussians_backward";
  check_projection_inputs(op, means, quats, scales, opacities, viewmat, K, width, height);
  const int64_t n = means.size(0);
  check_shape(radii, op, "radii", {n, 2});
  check_dtype(radii, at::kInt, op, "radii");
  check_shape(v_means2d, op, "v_means2d", {n, 2});
  check_shape(v_conics, op, "v_conics", {n, 3});
  check_shape(v_depths, op, "v_depths", {n});
  check_shape(v_opacities, op, "v_opacities_out", {n});
  for (const auto* t : {&radii, &v_means2d, &v_conics, &v_depths, &v_opacities})
    TORCH_CHECK(t->device() == means.device(), op, ": all tensors must be on ", means.device());
  const c10::cuda::CUDAGuard guard(means.device());
  // Every row is written by the kernel (zeros for culled Gaussians).
  auto v_means = at::empty({n, 3}, means.options());
  auto v_quats = at::empty({n, 4}, means.options());
  auto v_scales = at::empty({n, 3}, means.options());
  auto v_opac = at::empty({n}, means.options());
  auto v_cam = camera_grad ? at::empty({n, 16}, means.options()) : at::Tensor();
  const auto m = means.contiguous(), q = quats.contiguous(), s = scales.contiguous(),
             o = opacities.contiguous(), V = viewmat.contiguous(), Kc = K.contiguous(),
             r = radii.contiguous(), vm = gradient_rows(v_means2d, means.scalar_type()),
             vc = gradient_rows(v_conics, means.scalar_type()),
             vd = gradient_rows(v_depths, means.scalar_type()),
             vo = gradient_rows(v_opacities, means.scalar_type());
  const VRowStrides strides{vm.stride(0), vc.stride(0), vd.stride(0), vo.stride(0)};
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "project_gaussians_backward_cuda", [&] {
    using T = scalar_t;
    const auto a = make_launch<T>(m, q, s, o, V, Kc, width, height, eps2d, 0.0, 0.0, 0.0,
                                  antialiased);
    const cudaError_t err = project_gaussians_backward_cuda_launch<T>(
        a, r.data_ptr<int32_t>(), vm.data_ptr<T>(), vc.data_ptr<T>(), vd.data_ptr<T>(),
        vo.data_ptr<T>(), strides, v_means.data_ptr<T>(), v_quats.data_ptr<T>(), v_scales.data_ptr<T>(),
        v_opac.data_ptr<T>(), camera_grad ? v_cam.data_ptr<T>() : nullptr,
        c10::cuda::getCurrentCUDAStream().stream());
    TORCH_CHECK(err == cudaSuccess, op, ": CUDA kernel failed: ", cudaGetErrorString(err));
  });
  auto [v_viewmat, v_K] = camera_grads_from_rows(v_cam, camera_grad, means.options());
  return {v_means, v_quats, v_scales, v_opac, v_viewmat, v_K};
}

TORCH_LIBRARY_IMPL(tiger, CUDA, m) {
  m.impl("project_gaussians", &project_gaussians_cuda);
  m.impl("project_gaussians_backward", &project_gaussians_backward_cuda);
}

}  // namespace tiger

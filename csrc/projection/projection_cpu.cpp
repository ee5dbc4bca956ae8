// CPU kernels of the projection ops: one Gaussian per iteration, parallel over N.
#include <ATen/Parallel.h>
#include <torch/library.h>

#include "common/projection_math.h"
#include "common/torch_checks.h"
#include "projection.h"

namespace tiger {

template <typename T>
static Camera<T> read_camera(const at::Tensor& viewmat, const at::Tensor& K, int64_t width,
                             int64_t height) {
  const auto V = viewmat.contiguous();
  const auto Kc = K.contiguous();
  const T* v = V.data_ptr<T>();
  const T* k = Kc.data_ptr<T>();
  Camera<T> cam;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) cam.R.m[i][j] = v[i * 4 + j];
  cam.t = {v[3], v[7], v[11]};
  cam.fx = k[0];
  cam.fy = k[4];
  cam.cx = k[2];
  cam.cy = k[5];
  cam.width = static_cast<int>(width);
  cam.height = static_cast<int>(height);
  return cam;
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> project_gaussians_cpu(
    const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
    const at::Tensor& opacities, const at::Tensor& viewmat, const at::Tensor& K, int64_t width,
    int64_t height, double eps2d, double near_plane, double far_plane, double alpha_threshold,
    bool antialiased, const std::optional<at::Tensor>& trainable) {
  const char* op = "tiger.project_gaussians";
  check_projection_inputs(op, means, quats, scales, opacities, viewmat, K, width, height);
  check_row_mask(trainable, means.size(0), means, op, "trainable", "means");  // for the backward (autograd formula)
  const int64_t n = means.size(0);
  auto means2d = at::zeros({n, 2}, means.options());
  auto conics = at::zeros({n, 3}, means.options());
  auto depths = at::zeros({n}, means.options());
  auto opac_out = at::zeros({n}, means.options());
  auto radii = at::zeros({n, 2}, means.options().dtype(at::kInt));
  const auto m_c = means.contiguous(), q_c = quats.contiguous(), s_c = scales.contiguous(),
             o_c = opacities.contiguous();
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "project_gaussians_cpu", [&] {
    using T = scalar_t;
    const Camera<T> cam = read_camera<T>(viewmat, K, width, height);
    const ProjectOptions<T> opt{T(eps2d), T(near_plane), T(far_plane), T(alpha_threshold),
                                antialiased};
    const T* mp = m_c.data_ptr<T>();
    const T* qp = q_c.data_ptr<T>();
    const T* sp = s_c.data_ptr<T>();
    const T* op_ = o_c.data_ptr<T>();
    T* m2 = means2d.data_ptr<T>();
    T* cn = conics.data_ptr<T>();
    T* dp = depths.data_ptr<T>();
    T* oo = opac_out.data_ptr<T>();
    int32_t* rp = radii.data_ptr<int32_t>();
    at::parallel_for(0, n, 2048, [&](int64_t b, int64_t e) {
      for (int64_t i = b; i < e; ++i) {
        Projected<T> pr;
        if (!project_gaussian<T>(mp + 3 * i, qp + 4 * i, sp + 3 * i, op_[i], cam, opt, pr)) continue;
        store_projected(pr, i, m2, cn, dp, oo, rp);
      }
    });
  });
  return {means2d, conics, depths, opac_out, radii};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor>
project_gaussians_backward_cpu(const at::Tensor& means, const at::Tensor& quats,
                               const at::Tensor& scales, const at::Tensor& opacities,
                               const at::Tensor& viewmat, const at::Tensor& K, const at::Tensor& radii,
                               int64_t width, int64_t height, double eps2d, bool antialiased,
                               const at::Tensor& v_means2d, const at::Tensor& v_conics,
                               const at::Tensor& v_depths, const at::Tensor& v_opacities,
                               bool camera_grad) {
  const char* op = "tiger.project_gaussians_backward";
  check_projection_inputs(op, means, quats, scales, opacities, viewmat, K, width, height);
  const int64_t n = means.size(0);
  check_shape(radii, op, "radii", {n, 2});
  check_shape(v_means2d, op, "v_means2d", {n, 2});
  check_shape(v_conics, op, "v_conics", {n, 3});
  check_shape(v_depths, op, "v_depths", {n});
  check_shape(v_opacities, op, "v_opacities_out", {n});
  auto v_means = at::zeros({n, 3}, means.options());
  auto v_quats = at::zeros({n, 4}, means.options());
  auto v_scales = at::zeros({n, 3}, means.options());
  auto v_opac = at::zeros({n}, means.options());
  // Per-Gaussian camera gradients, summed after the parallel loop (deterministic).
  auto v_cam = camera_grad ? at::zeros({n, 16}, means.options()) : at::Tensor();
  const auto m_c = means.contiguous(), q_c = quats.contiguous(), s_c = scales.contiguous(),
             o_c = opacities.contiguous(), r_c = radii.contiguous(), vm_c = v_means2d.contiguous(),
             vc_c = v_conics.contiguous(), vd_c = v_depths.contiguous(),
             vo_c = v_opacities.contiguous();
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "project_gaussians_backward_cpu", [&] {
    using T = scalar_t;
    const Camera<T> cam = read_camera<T>(viewmat, K, width, height);
    const ProjectOptions<T> opt{T(eps2d), T(0), T(0), T(0), antialiased};
    const T *mp = m_c.data_ptr<T>(), *qp = q_c.data_ptr<T>(), *sp = s_c.data_ptr<T>(),
            *op_ = o_c.data_ptr<T>();
    const int32_t* rp = r_c.data_ptr<int32_t>();
    const T *vm = vm_c.data_ptr<T>(), *vc = vc_c.data_ptr<T>(), *vd = vd_c.data_ptr<T>(),
            *vo = vo_c.data_ptr<T>();
    T *gm = v_means.data_ptr<T>(), *gq = v_quats.data_ptr<T>(), *gs = v_scales.data_ptr<T>(),
      *go = v_opac.data_ptr<T>();
    T* gc = camera_grad ? v_cam.data_ptr<T>() : nullptr;
    at::parallel_for(0, n, 1024, [&](int64_t b, int64_t e) {
      for (int64_t i = b; i < e; ++i) {
        if (rp[2 * i] == 0) continue;
        ProjectionGrads<T> g{};
        g.R = mat3_zero<T>();
        project_gaussian_vjp<T>(mp + 3 * i, qp + 4 * i, sp + 3 * i, op_[i], cam, opt, vm[2 * i],
                                vm[2 * i + 1], vc[3 * i], vc[3 * i + 1], vc[3 * i + 2], vd[i], vo[i],
                                g);
        for (int k = 0; k < 3; ++k) {
          gm[3 * i + k] = g.mean[k];
          gs[3 * i + k] = g.scale[k];
        }
        for (int k = 0; k < 4; ++k) gq[4 * i + k] = g.quat[k];
        go[i] = g.opacity;
        if (gc) {
          T* c = gc + 16 * i;
          for (int r = 0; r < 3; ++r) {
            for (int k = 0; k < 3; ++k) c[r * 4 + k] = g.R.m[r][k];
            c[r * 4 + 3] = g.t[r];
          }
          for (int k = 0; k < 4; ++k) c[12 + k] = g.K[k];
        }
      }
    });
  });
  auto [v_viewmat, v_K] = camera_grads_from_rows(v_cam, camera_grad, means.options());
  return {v_means, v_quats, v_scales, v_opac, v_viewmat, v_K};
}

TORCH_LIBRARY_IMPL(tiger, CPU, m) {
  m.impl("project_gaussians", &project_gaussians_cpu);
  m.impl("project_gaussians_backward", &project_gaussians_backward_cpu);
}

}  // namespace tiger

// Schemas of the projection ops (kernels: projection_cpu.cpp, projection_cuda.cpp).
#include <torch/library.h>

#include "common/torch_checks.h"
#include "projection.h"

namespace tiger {

void check_projection_inputs(const char* op, const at::Tensor& means, const at::Tensor& quats,
                             const at::Tensor& scales, const at::Tensor& opacities,
                             const at::Tensor& viewmat, const at::Tensor& K, int64_t width,
                             int64_t height) {
  TORCH_CHECK(means.is_floating_point() && (means.scalar_type() == at::kFloat ||
                                            means.scalar_type() == at::kDouble),
              op, ": means must be float32 or float64, got ", means.scalar_type());
  check_shape(means, op, "means", {-1, 3});
  const int64_t n = means.size(0);
  check_shape(quats, op, "quats", {n, 4});
  check_shape(scales, op, "scales", {n, 3});
  check_shape(opacities, op, "opacities", {n});
  check_shape(viewmat, op, "viewmat", {4, 4});
  check_shape(K, op, "K", {3, 3});
  check_same(quats, means, op, "quats");
  check_same(scales, means, op, "scales");
  check_same(opacities, means, op, "opacities");
  check_same(viewmat, means, op, "viewmat");
  check_same(K, means, op, "K");
  TORCH_CHECK(width > 0 && height > 0, op, ": width and height must be positive, got ", width, "x",
              height);
}

std::tuple<at::Tensor, at::Tensor> camera_grads_from_rows(const at::Tensor& rows, bool camera_grad,
                                                          const at::TensorOptions& options) {
  auto v_viewmat = at::zeros({4, 4}, options);
  auto v_K = at::zeros({3, 3}, options);
  if (camera_grad && rows.defined() && rows.size(0) > 0) {
    const auto s = rows.sum(0, /*keepdim=*/false, at::kDouble).to(options.dtype());
    v_viewmat.view(-1).narrow(0, 0, 12).copy_(s.narrow(0, 0, 12));
    v_K.view(-1)[0] = s[12];
    v_K.view(-1)[4] = s[13];
    v_K.view(-1)[2] = s[14];
    v_K.view(-1)[5] = s[15];
  }
  return {v_viewmat, v_K};
}

TORCH_LIBRARY_FRAGMENT(tiger, m) {
  m.def(
      "project_gaussians(Tensor means, Tensor quats, Tensor scales, Tensor opacities, "
      "Tensor viewmat, Tensor K, int width, int height, float eps2d, float near_plane, "
      "float far_plane, float alpha_threshold, bool antialiased, Tensor? trainable=None) "
      "-> (Tensor means2d, Tensor conics, Tensor depths, Tensor opacities_out, Tensor radii)");
  m.def(
      "project_gaussians_backward(Tensor means, Tensor quats, Tensor scales, Tensor opacities, "
      "Tensor viewmat, Tensor K, Tensor radii, int width, int height, float eps2d, "
      "bool antialiased, Tensor v_means2d, Tensor v_conics, Tensor v_depths, "
      "Tensor v_opacities_out, bool camera_grad) "
      "-> (Tensor v_means, Tensor v_quats, Tensor v_scales, Tensor v_opacities, "
      "Tensor v_viewmat, Tensor v_K)");
}

}  // namespace tiger

// Schemas of the spherical-harmonics ops (kernels: sh_cpu.cpp, sh_cuda.cpp).
#include <torch/library.h>

#include "common/torch_checks.h"
#include "sh.h"

namespace tiger {

void check_sh_inputs(const char* op, const at::Tensor& dirs, const at::Tensor& coeffs, int64_t degree,
                     const std::optional<at::Tensor>& visible) {
  TORCH_CHECK(degree >= 0 && degree <= 3, op, ": sh degree must be in [0, 3], got ", degree);
  TORCH_CHECK(dirs.scalar_type() == at::kFloat || dirs.scalar_type() == at::kDouble, op,
              ": dirs must be float32 or float64, got ", dirs.scalar_type());
  check_shape(dirs, op, "dirs", {-1, 3});
  const int64_t nb = (degree + 1) * (degree + 1);
  check_shape(coeffs, op, "coeffs", {dirs.size(0), -1, 3});
  TORCH_CHECK(coeffs.size(1) >= nb, op, ": coeffs has ", coeffs.size(1),
              " SH coefficients per Gaussian but degree ", degree, " needs ", nb);
  check_same(coeffs, dirs, op, "coeffs");
  if (visible.has_value()) {
    check_shape(*visible, op, "visible", {dirs.size(0)});
    check_dtype(*visible, at::kBool, op, "visible");
    TORCH_CHECK(visible->device() == dirs.device(), op, ": visible must be on ", dirs.device());
  }
}

TORCH_LIBRARY_FRAGMENT(tiger, m) {
  m.def("sh_to_color(Tensor dirs, Tensor coeffs, int degree, Tensor? visible) -> Tensor");
  m.def(
      "sh_to_color_backward(Tensor dirs, Tensor coeffs, int degree, Tensor? visible, "
      "Tensor v_colors) -> (Tensor v_dirs, Tensor v_coeffs)");
}

}  // namespace tiger

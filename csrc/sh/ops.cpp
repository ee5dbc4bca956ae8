// Schemas of the spherical-harmonics ops (kernels: sh_cpu.cpp, sh_cuda.cpp).
#include <torch/library.h>

#include "common/torch_checks.h"
#include "sh.h"

namespace tiger {

ShViews check_sh_inputs(const char* op, const at::Tensor& dirs, const at::Tensor& coeffs, int64_t degree,
                        const std::optional<at::Tensor>& visible, const std::optional<at::Tensor>& rest) {
  TORCH_CHECK(degree >= 0 && degree <= 3, op, ": sh degree must be in [0, 3], got ", degree);
  TORCH_CHECK(dirs.scalar_type() == at::kFloat || dirs.scalar_type() == at::kDouble, op,
              ": dirs must be float32 or float64, got ", dirs.scalar_type());
  TORCH_CHECK((dirs.dim() == 2 || dirs.dim() == 3) && dirs.size(-1) == 3, op,
              ": dirs must have shape [N, 3] (one view) or [V, N, 3] (V views), got ", shape_str(dirs.sizes()));
  const ShViews s{dirs.dim() == 3 ? dirs.size(0) : 1, dirs.size(-2)};
  const int64_t nb = (degree + 1) * (degree + 1);
  check_shape(coeffs, op, "coeffs", {s.n, -1, 3});
  check_same(coeffs, dirs, op, "coeffs");
  int64_t k = coeffs.size(1);
  if (rest.has_value()) {
    check_shape(*rest, op, "rest", {s.n, -1, 3});
    check_same(*rest, dirs, op, "rest");
    k += rest->size(1);
  }
  TORCH_CHECK(k >= nb, op, ": coeffs", rest.has_value() ? " + rest" : "", " hold ", k,
              " SH coefficients per Gaussian but degree ", degree, " needs ", nb);
  if (visible.has_value()) check_per_view(*visible, dirs, op, "visible", at::kBool, false);
  return s;
}

void check_per_view(const at::Tensor& t, const at::Tensor& dirs, const char* op, const char* name,
                    at::ScalarType dtype, bool xyz) {
  const at::IntArrayRef want = xyz ? dirs.sizes() : dirs.sizes().slice(0, dirs.dim() - 1);
  const char* dims = dirs.dim() == 3 ? (xyz ? "[V, N, 3]" : "[V, N]") : (xyz ? "[N, 3]" : "[N]");
  TORCH_CHECK(t.sizes() == want, op, ": ", name, " must have shape ", shape_str(want), " (", dims,
              " like dirs ", shape_str(dirs.sizes()), "), got ", shape_str(t.sizes()));
  check_dtype(t, dtype, op, name);
  TORCH_CHECK(t.device() == dirs.device(), op, ": ", name, " is on ", t.device(), " but dirs is on ",
              dirs.device());
}

at::Tensor joined_coeffs(const at::Tensor& coeffs, const std::optional<at::Tensor>& rest) {
  return rest.has_value() ? at::cat({coeffs, *rest}, 1) : coeffs;
}

std::tuple<at::Tensor, at::Tensor> split_coeff_grads(const at::Tensor& v_all, const at::Tensor& coeffs,
                                                     const std::optional<at::Tensor>& rest) {
  if (!rest.has_value()) return {v_all, v_all.new_empty({0})};
  const int64_t k0 = coeffs.size(1);
  return {v_all.narrow(1, 0, k0).contiguous(), v_all.narrow(1, k0, rest->size(1)).contiguous()};
}

TORCH_LIBRARY_FRAGMENT(tiger, m) {
  // dirs [N, 3] or [V, N, 3] (V views of the same Gaussians, sh.h): the schema is the one-view
  // op's, unchanged. _staged=False: float32 rows through the plain kernels too (comparisons; sh.h).
  m.def(
      "sh_to_color(Tensor dirs, Tensor coeffs, int degree, Tensor? visible, Tensor? rest=None, "
      "bool _staged=True, Tensor? trainable=None) -> Tensor");
  m.def(
      "sh_to_color_backward(Tensor dirs, Tensor coeffs, int degree, Tensor? visible, "
      "Tensor v_colors, Tensor? rest=None, bool _staged=True, Tensor? trainable=None) "
      "-> (Tensor v_dirs, Tensor v_coeffs, Tensor v_rest)");
}

}  // namespace tiger

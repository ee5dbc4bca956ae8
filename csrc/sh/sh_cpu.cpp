// CPU kernels of the spherical-harmonics ops, parallel over Gaussians.
#include <ATen/Parallel.h>
#include <torch/library.h>

#include "common/sh_math.h"
#include "common/torch_checks.h"
#include "sh.h"

namespace tiger {

at::Tensor sh_to_color_cpu(const at::Tensor& dirs, const at::Tensor& coeffs_in, int64_t degree,
                           const std::optional<at::Tensor>& visible, const std::optional<at::Tensor>& rest,
                           bool /*staged: a CUDA choice*/, const std::optional<at::Tensor>& trainable) {
  check_sh_inputs("tiger.sh_to_color", dirs, coeffs_in, degree, visible, rest);
  check_row_mask(trainable, dirs.size(0), dirs, "tiger.sh_to_color", "trainable", "dirs");
  const at::Tensor coeffs = joined_coeffs(coeffs_in, rest);
  const int64_t n = dirs.size(0), k = coeffs.size(1);
  auto out = at::zeros({n, 3}, dirs.options());
  const auto d_c = dirs.contiguous(), c_c = coeffs.contiguous();
  const auto v_c = visible.has_value() ? visible->contiguous() : at::Tensor();
  AT_DISPATCH_FLOATING_TYPES(dirs.scalar_type(), "sh_to_color_cpu", [&] {
    using T = scalar_t;
    const T *dp = d_c.data_ptr<T>(), *cp = c_c.data_ptr<T>();
    const bool* vis = visible.has_value() ? v_c.data_ptr<bool>() : nullptr;
    T* op = out.data_ptr<T>();
    at::parallel_for(0, n, 4096, [&](int64_t b, int64_t e) {
      for (int64_t i = b; i < e; ++i) {
        if (vis && !vis[i]) continue;
        sh_eval<T>(static_cast<int>(degree), dp + 3 * i, cp + i * k * 3, op + 3 * i);
      }
    });
  });
  return out;
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> sh_to_color_backward_cpu(
    const at::Tensor& dirs, const at::Tensor& coeffs_in, int64_t degree, const std::optional<at::Tensor>& visible,
    const at::Tensor& v_colors, const std::optional<at::Tensor>& rest, bool /*staged: a CUDA choice*/,
    const std::optional<at::Tensor>& trainable) {
  const char* op = "tiger.sh_to_color_backward";
  check_sh_inputs(op, dirs, coeffs_in, degree, visible, rest);
  check_row_mask(trainable, dirs.size(0), dirs, op, "trainable", "dirs");
  const std::optional<at::Tensor> rows = backward_rows(visible, trainable);
  const at::Tensor coeffs = joined_coeffs(coeffs_in, rest);
  check_shape(v_colors, op, "v_colors", {dirs.size(0), 3});
  const int64_t n = dirs.size(0), k = coeffs.size(1);
  auto v_dirs = at::zeros({n, 3}, dirs.options());
  auto v_coeffs = at::zeros({n, k, 3}, dirs.options());
  const auto d_c = dirs.contiguous(), c_c = coeffs.contiguous(), g_c = v_colors.contiguous();
  const auto v_c = rows.has_value() ? rows->contiguous() : at::Tensor();
  AT_DISPATCH_FLOATING_TYPES(dirs.scalar_type(), "sh_to_color_backward_cpu", [&] {
    using T = scalar_t;
    const T *dp = d_c.data_ptr<T>(), *cp = c_c.data_ptr<T>(), *gp = g_c.data_ptr<T>();
    const bool* vis = rows.has_value() ? v_c.data_ptr<bool>() : nullptr;
    T *vd = v_dirs.data_ptr<T>(), *vc = v_coeffs.data_ptr<T>();
    at::parallel_for(0, n, 2048, [&](int64_t b, int64_t e) {
      for (int64_t i = b; i < e; ++i) {
        if (vis && !vis[i]) continue;
        sh_eval_vjp<T>(static_cast<int>(degree), dp + 3 * i, cp + i * k * 3, gp + 3 * i,
                       vc + i * k * 3, vd + 3 * i);
      }
    });
  });
  auto [v_c0, v_rest] = split_coeff_grads(v_coeffs, coeffs_in, rest);
  return {v_dirs, v_c0, v_rest};
}

TORCH_LIBRARY_IMPL(tiger, CPU, m) {
  m.impl("sh_to_color", &sh_to_color_cpu);
  m.impl("sh_to_color_backward", &sh_to_color_backward_cpu);
}

}  // namespace tiger

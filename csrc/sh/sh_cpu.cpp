// CPU kernels of the spherical-harmonics ops, parallel over Gaussians (each row loops its views).
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>

#include "common/sh_math.h"
#include "common/torch_checks.h"
#include "sh.h"

namespace tiger {

namespace {
// Rows per parallel chunk: a row costs one evaluation per view.
int64_t grain(int64_t rows_one_view, int64_t views) {
  return std::max<int64_t>(1, rows_one_view / std::max<int64_t>(views, 1));
}
}  // namespace

at::Tensor sh_to_color_cpu(const at::Tensor& dirs, const at::Tensor& coeffs_in, int64_t degree,
                           const std::optional<at::Tensor>& visible, const std::optional<at::Tensor>& rest,
                           bool /*staged: a CUDA choice*/, const std::optional<at::Tensor>& trainable) {
  const char* op = "tiger.sh_to_color";
  const ShViews s = check_sh_inputs(op, dirs, coeffs_in, degree, visible, rest);
  const int64_t views = s.views, n = s.n;
  check_row_mask(trainable, n, dirs, op, "trainable", "dirs");
  const at::Tensor coeffs = joined_coeffs(coeffs_in, rest);
  const int64_t k = coeffs.size(1);
  auto out = at::zeros(dirs.sizes(), dirs.options());  // [N,3] or [V,N,3]; invisible rows keep 0
  const auto d_c = dirs.contiguous(), c_c = coeffs.contiguous();
  const auto v_c = visible.has_value() ? visible->contiguous() : at::Tensor();
  AT_DISPATCH_FLOATING_TYPES(dirs.scalar_type(), "sh_to_color_cpu", [&] {
    using T = scalar_t;
    const T *dp = d_c.data_ptr<T>(), *cp = c_c.data_ptr<T>();
    const bool* vis = visible.has_value() ? v_c.data_ptr<bool>() : nullptr;
    T* outp = out.data_ptr<T>();
    at::parallel_for(0, n, grain(4096, views), [&](int64_t b, int64_t e) {
      for (int64_t i = b; i < e; ++i)
        sh_eval_views<T>(static_cast<int>(degree), views, n, dp + 3 * i, cp + i * k * 3, vis ? vis + i : nullptr,
                         outp + 3 * i);
    });
  });
  return out;
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> sh_to_color_backward_cpu(
    const at::Tensor& dirs, const at::Tensor& coeffs_in, int64_t degree, const std::optional<at::Tensor>& visible,
    const at::Tensor& v_colors, const std::optional<at::Tensor>& rest, bool /*staged: a CUDA choice*/,
    const std::optional<at::Tensor>& trainable) {
  const char* op = "tiger.sh_to_color_backward";
  const ShViews s = check_sh_inputs(op, dirs, coeffs_in, degree, visible, rest);
  const int64_t views = s.views, n = s.n;
  check_row_mask(trainable, n, dirs, op, "trainable", "dirs");
  check_per_view(v_colors, dirs, op, "v_colors", dirs.scalar_type(), true);
  const at::Tensor coeffs = joined_coeffs(coeffs_in, rest);
  const int64_t k = coeffs.size(1);
  auto v_dirs = at::zeros(dirs.sizes(), dirs.options());
  auto v_coeffs = at::zeros({n, k, 3}, dirs.options());  // once, the views' sum (not one per view)
  const auto d_c = dirs.contiguous(), c_c = coeffs.contiguous(), g_c = v_colors.contiguous();
  const auto v_c = visible.has_value() ? visible->contiguous() : at::Tensor();
  const auto t_c = trainable.has_value() ? trainable->contiguous() : at::Tensor();
  AT_DISPATCH_FLOATING_TYPES(dirs.scalar_type(), "sh_to_color_backward_cpu", [&] {
    using T = scalar_t;
    const T *dp = d_c.data_ptr<T>(), *cp = c_c.data_ptr<T>(), *gp = g_c.data_ptr<T>();
    const bool* vis = visible.has_value() ? v_c.data_ptr<bool>() : nullptr;
    const bool* tr = trainable.has_value() ? t_c.data_ptr<bool>() : nullptr;
    T *vd = v_dirs.data_ptr<T>(), *vc = v_coeffs.data_ptr<T>();
    at::parallel_for(0, n, grain(2048, views), [&](int64_t b, int64_t e) {
      for (int64_t i = b; i < e; ++i) {
        if (tr && !tr[i]) continue;  // frozen: zero gradients, no work
        sh_eval_vjp_views<T>(static_cast<int>(degree), views, n, dp + 3 * i, cp + i * k * 3, vis ? vis + i : nullptr,
                             gp + 3 * i, vc + i * k * 3, vd + 3 * i);
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

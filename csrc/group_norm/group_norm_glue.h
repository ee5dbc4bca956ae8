#pragma once
// ATen-side checks and layout rules shared by the CPU and CUDA implementations.
#include <ATen/ATen.h>

#include <cmath>

#include "common/memory_format.h"
#include "common/torch_checks.h"
#include "group_norm/group_norm.h"

namespace tiger {
namespace group_norm {

// Statistics (mean, rstd) and parameter gradients: float64 for float64 x (CPU), else float32.
inline at::ScalarType stat_dtype(const at::Tensor& x) {
  return x.scalar_type() == at::kDouble ? at::kDouble : at::kFloat;
}

inline void check_param(const at::Tensor& p, const at::Tensor& x, const char* op, const char* name) {
  if (!p.defined()) return;
  TORCH_CHECK(p.dim() == 1 && p.size(0) == x.size(1), op, ": ", name, " must be [C] = [", x.size(1),
              "] (one value per channel of x), got ", shape_str(p.sizes()));
  TORCH_CHECK(p.scalar_type() == x.scalar_type() || p.scalar_type() == at::kFloat, op, ": ", name,
              " must have x's dtype (", x.scalar_type(), ") or float32, got ", p.scalar_type());
  TORCH_CHECK(p.device() == x.device(), op, ": ", name, " is on ", p.device(), " but x is on ", x.device());
}

inline Dims check_inputs(const at::Tensor& x, const c10::optional<at::Tensor>& weight,
                         const c10::optional<at::Tensor>& bias, int64_t num_groups, const char* op) {
  TORCH_CHECK(x.dim() == 4, op, ": x must be [N, C, H, W], got ", shape_str(x.sizes()),
              x.dim() == 3 ? " (view an [N, C, L] input as [N, C, L, 1])" : "");
  const auto dt = x.scalar_type();
  TORCH_CHECK(dt == at::kFloat || dt == at::kBFloat16 || dt == at::kHalf || dt == at::kDouble, op,
              ": x must be float32, bfloat16 or float16 (float64 on the CPU), got ", dt);
  TORCH_CHECK(num_groups >= 1, op, ": num_groups must be >= 1, got ", num_groups);
  TORCH_CHECK(x.size(1) % num_groups == 0, op, ": the C = ", x.size(1), " channels of x are not divisible by num_groups = ",
              num_groups);
  if (weight.has_value()) check_param(*weight, x, op, "weight");
  if (bias.has_value()) check_param(*bias, x, op, "bias");
  return Dims{x.size(0), x.size(1), x.size(2) * x.size(3), num_groups, is_nhwc(x)};
}

inline void check_eps(double eps, const char* op) {
  TORCH_CHECK(std::isfinite(eps) && eps >= 0, op, ": eps must be finite and >= 0, got ", eps);
}

inline void check_backward_inputs(const at::Tensor& grad_y, const at::Tensor& x, const at::Tensor& mean,
                                  const at::Tensor& rstd, const Dims& d, const char* op) {
  TORCH_CHECK(grad_y.sizes() == x.sizes(), op, ": grad_y must have x's shape ", shape_str(x.sizes()), ", got ",
              shape_str(grad_y.sizes()));
  check_same(grad_y, x, op, "grad_y");
  for (const auto* t : {&mean, &rstd}) {
    const char* name = t == &mean ? "mean" : "rstd";
    TORCH_CHECK(t->dim() == 2 && t->size(0) == d.N && t->size(1) == d.G, op, ": ", name, " must be [N, G] = [", d.N,
                ", ", d.G, "], got ", shape_str(t->sizes()));
    check_dtype(*t, stat_dtype(x), op, name);
  }
}

// The residual gradient (undefined when absent), in x's shape, dtype and device, laid out like x's
// kernels read it (channels-last when nhwc, else contiguous).
inline at::Tensor residual_grad_of(const c10::optional<at::Tensor>& r, const at::Tensor& x, bool nhwc, const char* op) {
  if (!r.has_value() || !r->defined()) return at::Tensor();
  TORCH_CHECK(r->sizes() == x.sizes(), op, ": residual_grad must have x's shape ", shape_str(x.sizes()), ", got ",
              shape_str(r->sizes()));
  check_same(*r, x, op, "residual_grad");
  return r->contiguous(memory_format(nhwc));
}

// The input bias as float32 [N, C] (an undefined tensor when absent): [C] or [N, C] of any floating
// dtype, on x's device. Its rows may be strided (a [C] bias is the row stride 0, a slice of a wider
// [N, C'] matrix its width: no copy for either); its channels are made contiguous.
inline at::Tensor input_bias_of(const c10::optional<at::Tensor>& ib, const at::Tensor& x, const char* op) {
  if (!ib.has_value() || !ib->defined()) return at::Tensor();
  const int64_t N = x.size(0), C = x.size(1);
  const bool per_channel = ib->dim() == 1 && ib->size(0) == C;
  const bool per_sample = ib->dim() == 2 && ib->size(0) == N && ib->size(1) == C;
  TORCH_CHECK(per_channel || per_sample, op, ": input_bias must be [C] = [", C, "] or [N, C] = [", N, ", ", C,
              "], got ", shape_str(ib->sizes()));
  TORCH_CHECK(ib->is_floating_point(), op, ": input_bias must be floating point, got ", ib->scalar_type());
  TORCH_CHECK(ib->device() == x.device(), op, ": input_bias is on ", ib->device(), " but x is on ", x.device());
  const auto acc = x.scalar_type() == at::kDouble ? at::kDouble : at::kFloat;
  const auto t = ib->to(acc).expand({N, C});
  return t.stride(1) == 1 ? t : t.contiguous();
}

inline Params params_of(const c10::optional<at::Tensor>& w, const c10::optional<at::Tensor>& b,
                        const at::Tensor& input_bias = at::Tensor()) {
  const bool wf = w.has_value() && w->scalar_type() == at::kFloat;
  const bool bf = b.has_value() && b->scalar_type() == at::kFloat;
  TORCH_CHECK(!(w.has_value() && b.has_value()) || wf == bf,
              "tiger.group_norm: weight and bias must have the same dtype, got ", w->scalar_type(), " and ",
              b->scalar_type());
  const float* ib = input_bias.defined() && input_bias.scalar_type() == at::kFloat ? input_bias.data_ptr<float>()
                                                                                    : nullptr;
  const int64_t ib_stride = ib == nullptr ? 0 : input_bias.stride(0);
  return Params{w.has_value() ? w->data_ptr() : nullptr, b.has_value() ? b->data_ptr() : nullptr, wf || bf, ib,
                ib_stride};
}

}  // namespace group_norm
}  // namespace tiger

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

// The input bias as float32 [N, C] contiguous (an undefined tensor when absent): [C] or [N, C]
// of any floating dtype, on x's device.
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
  return ib->to(acc).expand({N, C}).contiguous();
}

// channel_bias_add_moments' inputs: x [N, C, H, W] floating point, bias [C] or [N, C] and an
// optional residual like x, all of x's dtype and device.
inline void check_bias_add_inputs(const at::Tensor& x, const at::Tensor& bias, const c10::optional<at::Tensor>& residual,
                                  const char* op) {
  TORCH_CHECK(x.dim() == 4, op, ": x must be [N, C, H, W], got ", shape_str(x.sizes()));
  const auto dt = x.scalar_type();
  TORCH_CHECK(dt == at::kFloat || dt == at::kBFloat16 || dt == at::kHalf || dt == at::kDouble, op,
              ": x must be float32, bfloat16 or float16 (float64 on the CPU), got ", dt);
  const bool per_channel = bias.dim() == 1 && bias.size(0) == x.size(1);
  const bool per_sample = bias.dim() == 2 && bias.size(0) == x.size(0) && bias.size(1) == x.size(1);
  TORCH_CHECK(per_channel || per_sample, op, ": bias must be [C] = [", x.size(1), "] or [N, C] = [", x.size(0), ", ",
              x.size(1), "], got ", shape_str(bias.sizes()));
  check_same(bias, x, op, "bias");
  if (residual.has_value() && residual->defined()) {
    TORCH_CHECK(residual->sizes() == x.sizes(), op, ": residual must have x's shape ", shape_str(x.sizes()), ", got ",
                shape_str(residual->sizes()));
    check_same(*residual, x, op, "residual");
  }
}

// The partial moments handed in with x (tiger::channel_bias_add_moments): float [2, N, K, C]
// for channels-last partials, [2, N, C, K, V] for NCHW ones (V lanes of one channel per row of
// H·W / V); K row chunks of ceil(rows / K) rows, none empty. Returns (K, V); the data layout is
// group_norm.h's Moments.
struct MomentsShape {
  int64_t chunks;
  int vector_width;
  bool nhwc;
};

inline MomentsShape check_moments(const at::Tensor& m, const at::Tensor& x, const Dims& d, const char* op) {
  TORCH_CHECK(m.dim() == 4 || m.dim() == 5, op, ": moments must be [2, N, K, C] (channels-last) or "
              "[2, N, C, K, V] (NCHW), got ", shape_str(m.sizes()));
  check_dtype(m, stat_dtype(x), op, "moments");
  TORCH_CHECK(m.device() == x.device(), op, ": moments are on ", m.device(), " but x is on ", x.device());
  TORCH_CHECK(m.is_contiguous(), op, ": moments must be contiguous");
  const bool nhwc = m.dim() == 4;
  const int64_t K = m.size(nhwc ? 2 : 3), V = nhwc ? 1 : m.size(4);
  const bool shape_ok = m.size(0) == 2 && m.size(1) == d.N && m.size(nhwc ? 3 : 2) == d.C && K >= 1 && V >= 1;
  TORCH_CHECK(shape_ok, op, ": moments ", shape_str(m.sizes()), " do not belong to x of shape ", shape_str(x.sizes()),
              " (expected [2, N, K, C] or [2, N, C, K, V] with N = ", d.N, ", C = ", d.C, ")");
  TORCH_CHECK(d.HW % V == 0, op, ": moments of ", V, "-lane rows do not divide x's ", d.HW, " pixels");
  const int64_t rows = d.HW / V, chunk = (rows + K - 1) / K;
  TORCH_CHECK(K <= rows && (rows + chunk - 1) / chunk == K, op, ": moments have ", K, " chunks, which do not split ",
              rows, " rows into non-empty chunks");
  return MomentsShape{K, static_cast<int>(V), nhwc};
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
  return Params{w.has_value() ? w->data_ptr() : nullptr, b.has_value() ? b->data_ptr() : nullptr, wf || bf, ib};
}

}  // namespace group_norm
}  // namespace tiger

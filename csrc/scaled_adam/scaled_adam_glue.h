#pragma once
// Checks shared by the CPU and CUDA implementations of scaled_adam_.
#include <ATen/ATen.h>

#include <optional>

#include "common/torch_checks.h"
#include "scaled_adam/scaled_adam_math.h"

namespace tiger {
namespace scaled_adam {

constexpr const char* kOp = "tiger.scaled_adam_";

// Checks every argument; returns the rows M shared by the params (their first dimension).
inline int64_t check_inputs(at::TensorList params, at::TensorList grads, at::TensorList exp_avgs,
                            at::TensorList exp_avg_sqs, at::TensorList steps, c10::ArrayRef<double> lrs,
                            double beta1, double beta2, double eps, const std::optional<at::Tensor>& weight,
                            at::TensorList targets, const std::optional<at::Tensor>& index) {
  const size_t n = params.size();
  TORCH_CHECK(n >= 1 && n <= size_t(kMaxTensors), kOp, ": params must hold 1 to ", kMaxTensors,
              " tensors, got ", n);
  TORCH_CHECK(grads.size() == n && exp_avgs.size() == n && exp_avg_sqs.size() == n && steps.size() == n &&
                  lrs.size() == n,
              kOp, ": grads, exp_avgs, exp_avg_sqs, steps and lrs need one entry per param (", n, "), got ",
              grads.size(), ", ", exp_avgs.size(), ", ", exp_avg_sqs.size(), ", ", steps.size(), " and ", lrs.size());
  TORCH_CHECK(beta1 >= 0.0 && beta1 < 1.0 && beta2 >= 0.0 && beta2 < 1.0 && eps >= 0.0, kOp,
              ": betas must lie in [0, 1) and eps be >= 0, got (", beta1, ", ", beta2, ") and ", eps);
  const at::Tensor& p0 = params[0];
  TORCH_CHECK(p0.dim() >= 1, kOp, ": params[0] must have a row dimension, got ", shape_str(p0.sizes()));
  TORCH_CHECK(p0.scalar_type() == at::kFloat || p0.scalar_type() == at::kDouble, kOp,
              ": params must be float32 or float64, got ", p0.scalar_type());
  const int64_t M = p0.size(0);
  for (size_t k = 0; k < n; ++k) {
    const at::Tensor& p = params[k];
    TORCH_CHECK(p.dim() >= 1 && p.size(0) == M, kOp, ": params[", k, "] must have ", M, " rows like params[0], got ",
                shape_str(p.sizes()));
    check_same(p, p0, kOp, "params[k]");
    TORCH_CHECK(p.is_contiguous(), kOp, ": params[", k, "] must be contiguous");
    const at::Tensor* same[3] = {&grads[k], &exp_avgs[k], &exp_avg_sqs[k]};
    const char* names[3] = {"grads", "exp_avgs", "exp_avg_sqs"};
    for (int j = 0; j < 3; ++j) {
      const at::Tensor& t = *same[j];
      TORCH_CHECK(t.defined() && t.sizes() == p.sizes(), kOp, ": ", names[j], "[", k, "] must have params[", k,
                  "]'s shape ", shape_str(p.sizes()), ", got ",
                  t.defined() ? shape_str(t.sizes()) : std::string("an undefined tensor"));
      check_same(t, p, kOp, names[j]);
      TORCH_CHECK(t.is_contiguous(), kOp, ": ", names[j], "[", k, "] must be contiguous");
    }
    const at::Tensor& s = steps[k];
    TORCH_CHECK(s.numel() == 1 && (s.scalar_type() == at::kFloat || s.scalar_type() == at::kDouble) &&
                    s.device() == p.device(),
                kOp, ": steps[", k, "] must be one float32/float64 value on ", p.device(), ", got ",
                s.scalar_type(), " ", shape_str(s.sizes()), " on ", s.device());
  }
  if (weight.has_value()) {
    check_shape(*weight, kOp, "weight", {M});
    check_same(*weight, p0, kOp, "weight");
    TORCH_CHECK(weight->is_contiguous(), kOp, ": weight must be contiguous");
  }
  if (index.has_value()) {
    check_shape(*index, kOp, "index", {M});
    check_dtype(*index, at::kLong, kOp, "index");
    TORCH_CHECK(index->device() == p0.device() && index->is_contiguous(), kOp, ": index must be contiguous on ",
                p0.device());
    TORCH_CHECK(targets.size() == n, kOp, ": with an index, targets need one tensor per param (", n, "), got ",
                targets.size());
    for (size_t k = 0; k < n; ++k) {
      const at::Tensor& t = targets[k];
      TORCH_CHECK(t.dim() == params[k].dim() && t.sizes().slice(1) == params[k].sizes().slice(1), kOp,
                  ": targets[", k, "] must be [N, ...] with params[", k, "]'s row shape, got ",
                  shape_str(t.sizes()), " for params ", shape_str(params[k].sizes()));
      check_same(t, p0, kOp, "targets[k]");
      TORCH_CHECK(t.is_contiguous(), kOp, ": targets[", k, "] must be contiguous");
    }
  } else {
    TORCH_CHECK(targets.empty(), kOp, ": targets are written through index: give index or no targets");
  }
  return M;
}

}  // namespace scaled_adam
}  // namespace tiger

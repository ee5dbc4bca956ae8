#pragma once
// Checks and the reference computation shared by the CPU and CUDA implementations of
// tiger::attention_rows.
#include <ATen/ATen.h>

#include <cmath>
#include <optional>
#include <string>

#include "common/torch_checks.h"

namespace tiger {
namespace attention {

constexpr const char* kOp = "tiger.attention_rows";

struct RowsShape {
  int64_t batch, L, heads, D;
};

inline RowsShape check_inputs(const at::Tensor& q, const at::Tensor& k, const at::Tensor& v, int64_t batch,
                              int64_t heads, c10::string_view schedule, int64_t warpgroups) {
  TORCH_CHECK(q.dim() == 2, kOp, ": q must be token rows [batch·L, heads·D], got ", shape_str(q.sizes()));
  TORCH_CHECK(batch > 0 && heads > 0, kOp, ": batch and heads must be positive, got ", batch, " and ", heads);
  TORCH_CHECK(q.size(0) % batch == 0, kOp, ": q has ", q.size(0), " rows, not a multiple of batch = ", batch);
  TORCH_CHECK(q.size(1) % heads == 0, kOp, ": q has ", q.size(1), " columns, not a multiple of heads = ", heads);
  TORCH_CHECK(k.sizes() == q.sizes(), kOp, ": k must have q's shape ", shape_str(q.sizes()),
              " (self-attention), got ", shape_str(k.sizes()));
  TORCH_CHECK(v.sizes() == q.sizes(), kOp, ": v must have q's shape ", shape_str(q.sizes()), ", got ",
              shape_str(v.sizes()));
  TORCH_CHECK(q.is_floating_point(), kOp, ": q must be floating point, got ", q.scalar_type());
  check_same(k, q, kOp, "k");
  check_same(v, q, kOp, "v");
  TORCH_CHECK(schedule == "producer" || schedule == "lockstep", kOp,
              ": schedule must be \"producer\" or \"lockstep\", got \"", std::string(schedule), "\"");
  const int64_t lo = schedule == "producer" ? 2 : 1, hi = schedule == "producer" ? 3 : 4;
  TORCH_CHECK(warpgroups >= lo && warpgroups <= hi, kOp, ": the ", std::string(schedule), " schedule takes ", lo, "-",
              hi, " warpgroups, got ", warpgroups);
  return {batch, q.size(0) / batch, heads, q.size(1) / heads};
}

inline double softmax_scale(const std::optional<double>& scale, int64_t D) {
  return scale.has_value() ? *scale : 1.0 / std::sqrt(static_cast<double>(D));
}

// [batch·L, heads·D] rows (unit column stride or not) → [batch, heads, L, D] view.
inline at::Tensor heads_view(const at::Tensor& t, const RowsShape& s) {
  return t.unflatten(1, {s.heads, s.D}).unflatten(0, {s.batch, s.L}).transpose(1, 2);
}

// softmax(q kᵀ · scale) v accumulated in float (double for float64), rounded once to q's dtype;
// [batch·L, heads·D] contiguous.
inline at::Tensor reference_rows(const at::Tensor& q, const at::Tensor& k, const at::Tensor& v, const RowsShape& s,
                                 double scale) {
  const auto acc = q.scalar_type() == at::kDouble ? at::kDouble : at::kFloat;
  const auto qh = heads_view(q, s).to(acc), kh = heads_view(k, s).to(acc), vh = heads_view(v, s).to(acc);
  const auto weights = at::softmax(at::matmul(qh, kh.transpose(-1, -2)) * scale, -1);
  return at::matmul(weights, vh).transpose(1, 2).reshape({s.batch * s.L, s.heads * s.D}).to(q.scalar_type());
}

}  // namespace attention
}  // namespace tiger

#pragma once
// Checks shared by the CPU and CUDA implementations of the softmax family.
#include <ATen/ATen.h>

#include "common/torch_checks.h"

namespace tiger {
namespace softmax {

constexpr const char* kOp = "tiger.softmax_rows";
constexpr const char* kOpBackward = "tiger.softmax_rows_backward";

inline void check_x(const at::Tensor& x, const char* op, const char* name) {
  TORCH_CHECK(x.dim() >= 1 && x.size(-1) > 0, op, ": ", name, " must be [..., L] with L >= 1, got ",
              shape_str(x.sizes()));
  TORCH_CHECK(x.is_floating_point(), op, ": ", name, " must be a floating-point tensor, got ", x.scalar_type());
}

inline void check_backward(const at::Tensor& y, const at::Tensor& grad_y) {
  check_x(y, kOpBackward, "y");
  TORCH_CHECK(grad_y.sizes() == y.sizes(), kOpBackward, ": grad_y must have y's shape ", shape_str(y.sizes()),
              ", got ", shape_str(grad_y.sizes()));
  check_same(grad_y, y, kOpBackward, "grad_y");
}

}  // namespace softmax
}  // namespace tiger

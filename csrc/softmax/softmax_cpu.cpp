// CPU implementation of the softmax family: torch's own softmax and its backward (which compute
// in float for the reduced types and round once), the reference the CUDA kernels are tested against.
#include <torch/library.h>

#include "softmax/softmax_glue.h"

namespace tiger {
namespace softmax {
namespace {

at::Tensor softmax_rows_cpu(const at::Tensor& x) {
  check_x(x, kOp, "x");
  return at::_softmax(x.contiguous(), -1, false);
}

at::Tensor softmax_rows_backward_cpu(const at::Tensor& y, const at::Tensor& grad_y) {
  check_backward(y, grad_y);
  return at::_softmax_backward_data(grad_y.contiguous(), y.contiguous(), -1, y.scalar_type());
}

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CPU, m) {
  m.impl("softmax_rows", &softmax_rows_cpu);
  m.impl("softmax_rows_backward", &softmax_rows_backward_cpu);
}

}  // namespace softmax
}  // namespace tiger

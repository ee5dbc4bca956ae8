// Torch glue of the CUDA row softmax (built only with CUDA). Rows the kernels do not take (other
// dtypes, lengths that are not whole 16-byte vectors or too long for one block's registers) run
// torch's own softmax. No host synchronisation: CUDA-graph capturable.
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <cuda_bf16.h>
#include <cuda_fp16.h>
#include <torch/library.h>

#include "softmax/softmax_cuda.h"
#include "softmax/softmax_glue.h"

namespace tiger {
namespace softmax {
namespace {

template <typename T>
bool run_forward(const at::Tensor& x, at::Tensor& y) {
  const int64_t L = x.size(-1);
  if (!rows_supported<T>(L, x.data_ptr(), y.data_ptr(), nullptr)) return false;
  launch_softmax_rows<T>(reinterpret_cast<const T*>(x.data_ptr()), reinterpret_cast<T*>(y.data_ptr()), x.numel() / L,
                         L, c10::cuda::getCurrentCUDAStream().stream());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return true;
}

template <typename T>
bool run_backward(const at::Tensor& y, const at::Tensor& dy, at::Tensor& dx) {
  const int64_t L = y.size(-1);
  if (!rows_supported<T>(L, y.data_ptr(), dy.data_ptr(), dx.data_ptr())) return false;
  launch_softmax_rows_backward<T>(reinterpret_cast<const T*>(y.data_ptr()), reinterpret_cast<const T*>(dy.data_ptr()),
                                  reinterpret_cast<T*>(dx.data_ptr()), y.numel() / L, L,
                                  c10::cuda::getCurrentCUDAStream().stream());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return true;
}

at::Tensor softmax_rows_cuda(const at::Tensor& x_in) {
  check_x(x_in, kOp, "x");
  TORCH_CHECK(x_in.is_cuda(), kOp, ": x must be on a CUDA device");
  const c10::cuda::CUDAGuard guard(x_in.device());
  const auto x = x_in.contiguous();
  auto y = at::empty_like(x, at::MemoryFormat::Contiguous);
  if (x.numel() == 0) return y;
  bool done = false;
  switch (x.scalar_type()) {
    case at::kFloat: done = run_forward<float>(x, y); break;
    case at::kHalf: done = run_forward<__half>(x, y); break;
    case at::kBFloat16: done = run_forward<__nv_bfloat16>(x, y); break;
    default: break;
  }
  return done ? y : at::_softmax(x, -1, false);
}

at::Tensor softmax_rows_backward_cuda(const at::Tensor& y_in, const at::Tensor& dy_in) {
  check_backward(y_in, dy_in);
  TORCH_CHECK(y_in.is_cuda(), kOpBackward, ": y must be on a CUDA device");
  const c10::cuda::CUDAGuard guard(y_in.device());
  const auto y = y_in.contiguous();
  const auto dy = dy_in.contiguous();
  auto dx = at::empty_like(y, at::MemoryFormat::Contiguous);
  if (y.numel() == 0) return dx;
  bool done = false;
  switch (y.scalar_type()) {
    case at::kFloat: done = run_backward<float>(y, dy, dx); break;
    case at::kHalf: done = run_backward<__half>(y, dy, dx); break;
    case at::kBFloat16: done = run_backward<__nv_bfloat16>(y, dy, dx); break;
    default: break;
  }
  return done ? dx : at::_softmax_backward_data(dy, y, -1, y.scalar_type());
}

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CUDA, m) {
  m.impl("softmax_rows", &softmax_rows_cuda);
  m.impl("softmax_rows_backward", &softmax_rows_backward_cuda);
}

}  // namespace softmax
}  // namespace tiger

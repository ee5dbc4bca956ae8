// Torch glue of the CUDA fp8_rows kernels (built only with CUDA). Outputs come from the caching
// allocator and every size is known on the host: CUDA-graph capturable.
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <cuda_bf16.h>
#include <cuda_fp16.h>
#include <torch/library.h>

#include <tuple>
#include <type_traits>

#include "fp8_rows/fp8_rows.h"
#include "fp8_rows/fp8_rows_glue.h"

namespace tiger {
namespace fp8_rows {
namespace {

// Calls f(pointer of x as the kernels' type) for float32/float16/bfloat16.
template <typename F>
void dispatch(const at::Tensor& x, const char* op, F&& f) {
  switch (x.scalar_type()) {
    case at::kFloat: f(x.data_ptr<float>()); break;
    case at::kHalf: f(reinterpret_cast<const __half*>(x.data_ptr())); break;
    case at::kBFloat16: f(reinterpret_cast<const __nv_bfloat16*>(x.data_ptr())); break;
    default: TORCH_CHECK(false, op, " (CUDA): x must be float32, bfloat16 or float16, got ", x.scalar_type());
  }
}

std::tuple<at::Tensor, at::Tensor> quantize_rows_fp8_cuda(const at::Tensor& x_in, bool geglu) {
  check_quantize_input(x_in, geglu);
  TORCH_CHECK(x_in.is_cuda(), "tiger.quantize_rows_fp8: x must be on a CUDA device");
  const c10::cuda::CUDAGuard guard(x_in.device());
  const auto x = x_in.contiguous();
  const int64_t M = x.size(0), cols = geglu ? x.size(1) / 2 : x.size(1);
  auto q = at::empty({M, cols}, x.options().dtype(at::kFloat8_e4m3fn));
  auto scale = at::empty({M, 1}, x.options().dtype(at::kFloat));
  void* stream = c10::cuda::getCurrentCUDAStream().stream();
  dispatch(x, "tiger.quantize_rows_fp8", [&](auto ptr) {
    launch_quantize_rows(ptr, M, cols, geglu, static_cast<unsigned char*>(q.data_ptr()), scale.data_ptr<float>(),
                         stream);
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return {q, scale};
}

at::Tensor geglu_cuda(const at::Tensor& x_in) {
  check_geglu_input(x_in);
  TORCH_CHECK(x_in.is_cuda(), "tiger.geglu: x must be on a CUDA device");
  const c10::cuda::CUDAGuard guard(x_in.device());
  const auto x = x_in.contiguous();
  const int64_t F = x.size(-1) / 2, M = F == 0 ? 0 : x.numel() / (2 * F);
  auto sizes = x.sizes().vec();
  sizes.back() = F;
  auto y = at::empty(sizes, x.options());
  void* stream = c10::cuda::getCurrentCUDAStream().stream();
  dispatch(x, "tiger.geglu", [&](auto ptr) {
    using T = std::remove_const_t<std::remove_pointer_t<decltype(ptr)>>;
    launch_geglu<T>(ptr, M, F, reinterpret_cast<T*>(y.data_ptr()), stream);
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return y;
}

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CUDA, m) {
  m.impl("quantize_rows_fp8", &quantize_rows_fp8_cuda);
  m.impl("geglu", &geglu_cuda);
}

}  // namespace fp8_rows
}  // namespace tiger

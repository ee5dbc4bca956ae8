// Torch glue of the CUDA group_norm kernels (built only with CUDA). Allocations come from the
// caching allocator and every size is known on the host: CUDA-graph capturable.
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <cuda_bf16.h>
#include <cuda_fp16.h>
#include <torch/library.h>

#include <tuple>

#include "group_norm/group_norm_glue.h"

namespace tiger {
namespace group_norm {
namespace {

constexpr const char* kOp = "tiger.group_norm (CUDA)";

template <typename T>
struct TypeTag {
  using type = T;
};

// Calls f(TypeTag<T>) with the CUDA type the kernels are instantiated for (float, __half,
// __nv_bfloat16); check_cuda has rejected everything else.
template <typename F>
void dispatch(at::ScalarType dt, F&& f) {
  switch (dt) {
    case at::kFloat: f(TypeTag<float>{}); break;
    case at::kHalf: f(TypeTag<__half>{}); break;
    case at::kBFloat16: f(TypeTag<__nv_bfloat16>{}); break;
    default: TORCH_CHECK(false, "tiger.group_norm (CUDA): unsupported dtype ", dt);
  }
}

void check_cuda(const at::Tensor& x, const char* op) {
  TORCH_CHECK(x.is_cuda(), op, ": x must be on a CUDA device");
  TORCH_CHECK(x.scalar_type() != at::kDouble, op, ": x must be float32, bfloat16 or float16 on CUDA, got float64");
}

c10::optional<at::Tensor> contiguous(const c10::optional<at::Tensor>& p) {
  if (!p.has_value()) return p;
  return p->contiguous();
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> group_norm_cuda(const at::Tensor& x_in,
                                                               const c10::optional<at::Tensor>& weight_in,
                                                               const c10::optional<at::Tensor>& bias_in,
                                                               int64_t num_groups, double eps, bool silu,
                                                               const c10::optional<at::Tensor>& input_bias_in) {
  const Dims d = check_inputs(x_in, weight_in, bias_in, num_groups, kOp);
  check_eps(eps, kOp);
  check_cuda(x_in, kOp);
  const c10::cuda::CUDAGuard guard(x_in.device());
  const auto x = x_in.contiguous(memory_format(d.nhwc));
  const auto weight = contiguous(weight_in), bias = contiguous(bias_in);
  const auto input_bias = input_bias_of(input_bias_in, x_in, kOp);
  const Params p = params_of(weight, bias, input_bias);
  auto y = at::empty_like(x, memory_format(d.nhwc));
  const auto fopts = x.options().dtype(at::kFloat);
  auto mean = at::empty({d.N, d.G}, fopts), rstd = at::empty({d.N, d.G}, fopts);
  if (x.numel() == 0) return {y, mean.zero_(), rstd.fill_(1.0 / std::sqrt(eps))};
  const int vw = choose_vector_width(d, x.element_size(), {x.data_ptr(), y.data_ptr()});
  void* stream = c10::cuda::getCurrentCUDAStream().stream();
  dispatch(x.scalar_type(), [&](auto tag) {
    using T = typename decltype(tag)::type;
    const auto* xp = reinterpret_cast<const T*>(x.data_ptr());
    auto* yp = reinterpret_cast<T*>(y.data_ptr());
    const float e = static_cast<float>(eps);
    if (launch_forward_small<T>(xp, p, d, e, silu, mean.data_ptr<float>(), rstd.data_ptr<float>(), yp, vw, stream))
      return;  // one launch, no partial workspaces
    const int64_t chunks = plan_chunks(d, vw, kForwardBlocksPerSm);
    auto pmean = at::empty({d.N * d.C * chunks * (d.nhwc ? 1 : vw)}, fopts);
    auto pm2 = at::empty_like(pmean);
    launch_forward<T>(xp, p, d, e, silu, chunks, pmean.data_ptr<float>(), pm2.data_ptr<float>(),
                      mean.data_ptr<float>(), rstd.data_ptr<float>(), yp, vw, stream);
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return {y, mean, rstd};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> group_norm_backward_cuda(
    const at::Tensor& grad_y_in, const at::Tensor& x_in, const c10::optional<at::Tensor>& weight_in,
    const c10::optional<at::Tensor>& bias_in, const at::Tensor& mean_in, const at::Tensor& rstd_in,
    int64_t num_groups, bool silu, bool param_grads, const c10::optional<at::Tensor>& input_bias_in,
    const c10::optional<at::Tensor>& residual_grad_in) {
  const char* op = "tiger.group_norm_backward (CUDA)";
  const Dims d = check_inputs(x_in, weight_in, bias_in, num_groups, op);
  check_backward_inputs(grad_y_in, x_in, mean_in, rstd_in, d, op);
  check_cuda(x_in, op);
  const c10::cuda::CUDAGuard guard(x_in.device());
  const auto x = x_in.contiguous(memory_format(d.nhwc));
  const auto dy = grad_y_in.contiguous(memory_format(d.nhwc));
  const auto mean = mean_in.contiguous(), rstd = rstd_in.contiguous();
  const auto weight = contiguous(weight_in), bias = contiguous(bias_in);
  const auto input_bias = input_bias_of(input_bias_in, x_in, op);
  const auto residual = residual_grad_of(residual_grad_in, x_in, d.nhwc, op);
  const Params p = params_of(weight, bias, input_bias);
  auto dx = at::empty_like(x, memory_format(d.nhwc));
  const auto fopts = x.options().dtype(at::kFloat);
  const auto dx_only = [&]() { return std::make_tuple(dx, at::empty({0}, fopts), at::empty({0}, fopts)); };
  if (x.numel() == 0) {
    if (!param_grads) return dx_only();
    return {dx, at::zeros({d.C}, fopts), at::zeros({d.C}, fopts)};
  }
  const int vw = choose_vector_width(d, x.element_size(), {x.data_ptr(), dy.data_ptr(), dx.data_ptr(),
                                                           residual.defined() ? residual.data_ptr() : nullptr});
  void* stream = c10::cuda::getCurrentCUDAStream().stream();
  at::Tensor sum_dz, sum_dzx;  // [N, C], for dw and db; every (n, c) is written by the combine
  dispatch(x.scalar_type(), [&](auto tag) {
    using T = typename decltype(tag)::type;
    const auto* dyp = reinterpret_cast<const T*>(dy.data_ptr());
    const auto* xp = reinterpret_cast<const T*>(x.data_ptr());
    const T* rp = residual.defined() ? reinterpret_cast<const T*>(residual.data_ptr()) : nullptr;
    auto* dxp = reinterpret_cast<T*>(dx.data_ptr());
    if (!param_grads && launch_backward_small<T>(dyp, xp, p, d, mean.data_ptr<float>(), rstd.data_ptr<float>(),
                                                 silu, rp, dxp, vw, stream))
      return;  // only dx asked for: one launch, no sums or partial workspaces
    sum_dz = at::empty({d.N, d.C}, fopts);
    sum_dzx = at::empty({d.N, d.C}, fopts);
    const int64_t chunks = plan_chunks(d, vw, kBackwardBlocksPerSm * kBackwardWaves);
    auto pdz = at::empty({d.N * d.C * chunks * (d.nhwc ? 1 : vw)}, fopts);
    auto pdzx = at::empty_like(pdz);
    auto c1 = at::empty({d.N, d.G}, fopts), c2 = at::empty({d.N, d.G}, fopts);
    launch_backward<T>(dyp, xp, p, d, mean.data_ptr<float>(), rstd.data_ptr<float>(), silu, chunks,
                       pdz.data_ptr<float>(), pdzx.data_ptr<float>(), sum_dz.data_ptr<float>(),
                       sum_dzx.data_ptr<float>(), c1.data_ptr<float>(), c2.data_ptr<float>(), rp, dxp, vw, stream);
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  if (!param_grads) return dx_only();
  return {dx, sum_dzx.sum(0), sum_dz.sum(0)};  // dw = Σ_n Σ dz·x̂, db = Σ_n Σ dz
}

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CUDA, m) {
  m.impl("group_norm", &group_norm_cuda);
  m.impl("group_norm_backward", &group_norm_backward_cuda);
}

}  // namespace group_norm
}  // namespace tiger

// Torch glue of the CUDA scaled-Adam kernel (built only with CUDA). Two launches a step (the
// step counts' increment, then the update); no host synchronisation.
#include <ATen/ops/_foreach_add.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <torch/library.h>

#include <vector>

#include "scaled_adam/scaled_adam_cuda.h"
#include "scaled_adam/scaled_adam_glue.h"

namespace tiger {
namespace scaled_adam {
namespace {

template <typename T>
void launch_typed(at::TensorList params, at::TensorList grads, at::TensorList exp_avgs, at::TensorList exp_avg_sqs,
                  at::TensorList steps, c10::ArrayRef<double> lrs, double beta1, double beta2, double eps,
                  const std::optional<at::Tensor>& weight, at::TensorList targets,
                  const std::optional<at::Tensor>& index) {
  Lists<T> L{};
  L.n = int(params.size());
  L.start[0] = 0;
  for (int k = 0; k < L.n; ++k) {
    const int64_t M = params[k].size(0);
    L.p[k] = params[k].data_ptr<T>();
    L.g[k] = grads[k].data_ptr<T>();
    L.m[k] = exp_avgs[k].data_ptr<T>();
    L.v[k] = exp_avg_sqs[k].data_ptr<T>();
    L.target[k] = index.has_value() ? targets[k].data_ptr<T>() : nullptr;
    L.step[k] = steps[k].data_ptr();
    L.step_double[k] = steps[k].scalar_type() == at::kDouble;
    L.row[k] = M > 0 ? params[k].numel() / M : 1;
    L.start[k + 1] = L.start[k] + params[k].numel();
    L.lr[k] = T(lrs[k]);
  }
  launch_scaled_adam<T>(L, weight.has_value() ? weight->data_ptr<T>() : nullptr,
                        index.has_value() ? index->data_ptr<int64_t>() : nullptr, T(beta1), T(beta2), T(eps),
                        c10::cuda::getCurrentCUDAStream().stream());
}

void scaled_adam_cuda(at::TensorList params, at::TensorList grads, at::TensorList exp_avgs, at::TensorList exp_avg_sqs,
                      at::TensorList steps, c10::ArrayRef<double> lrs, double beta1, double beta2, double eps,
                      const std::optional<at::Tensor>& weight, at::TensorList targets,
                      const std::optional<at::Tensor>& index) {
  check_inputs(params, grads, exp_avgs, exp_avg_sqs, steps, lrs, beta1, beta2, eps, weight, targets, index);
  TORCH_CHECK(params[0].is_cuda(), kOp, ": params must be on a CUDA device");
  const c10::cuda::CUDAGuard guard(params[0].device());
  at::_foreach_add_(steps, 1);  // the step counts as Adam keeps them, then read by the kernel
  if (params[0].scalar_type() == at::kDouble)
    launch_typed<double>(params, grads, exp_avgs, exp_avg_sqs, steps, lrs, beta1, beta2, eps, weight, targets, index);
  else
    launch_typed<float>(params, grads, exp_avgs, exp_avg_sqs, steps, lrs, beta1, beta2, eps, weight, targets, index);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
}

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CUDA, m) { m.impl("scaled_adam_", &scaled_adam_cuda); }

}  // namespace scaled_adam
}  // namespace tiger

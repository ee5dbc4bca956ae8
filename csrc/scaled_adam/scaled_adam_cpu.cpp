// CPU implementation of tiger::scaled_adam_: the reference semantics (scaled_adam_math.h), one
// element at a time, rows in parallel.
#include <ATen/Parallel.h>
#include <torch/library.h>

#include "scaled_adam/scaled_adam_glue.h"
#include "scaled_adam/scaled_adam_math.h"

namespace tiger {
namespace scaled_adam {
namespace {

template <typename T>
void step_tensor(const at::Tensor& p_t, const at::Tensor& g_t, const at::Tensor& m_t, const at::Tensor& v_t, T lr,
                 T t, T beta1, T beta2, T eps, const T* weight, const at::Tensor* target, const int64_t* index) {
  const int64_t M = p_t.size(0), row = M > 0 ? p_t.numel() / M : 0;
  T* p = p_t.data_ptr<T>();
  const T* g = g_t.data_ptr<T>();
  T* m = m_t.data_ptr<T>();
  T* v = v_t.data_ptr<T>();
  T* out = target ? target->data_ptr<T>() : nullptr;
  const StepScalars<T> s = step_scalars(lr, beta1, beta2, t);
  at::parallel_for(0, M, 1024, [&](int64_t r0, int64_t r1) {
    for (int64_t r = r0; r < r1; ++r) {
      const T w = weight ? weight[r] : T(1);
      for (int64_t c = 0; c < row; ++c) {
        const int64_t e = r * row + c;
        update_element(p[e], g[e], m[e], v[e], w, beta1, beta2, eps, s);
        if (out) out[index[r] * row + c] = p[e];
      }
    }
  });
}

void scaled_adam_cpu(at::TensorList params, at::TensorList grads, at::TensorList exp_avgs, at::TensorList exp_avg_sqs,
                     at::TensorList steps, c10::ArrayRef<double> lrs, double beta1, double beta2, double eps,
                     const std::optional<at::Tensor>& weight, at::TensorList targets,
                     const std::optional<at::Tensor>& index) {
  check_inputs(params, grads, exp_avgs, exp_avg_sqs, steps, lrs, beta1, beta2, eps, weight, targets, index);
  if (index.has_value()) {  // every index a row of every target: checked against the shortest once
    size_t shortest = 0;
    for (size_t k = 1; k < targets.size(); ++k)
      if (targets[k].size(0) < targets[shortest].size(0)) shortest = k;
    const auto idx = index->accessor<int64_t, 1>();
    for (int64_t r = 0; r < idx.size(0); ++r)
      TORCH_CHECK(idx[r] >= 0 && idx[r] < targets[shortest].size(0), kOp, ": index[", r, "] = ", idx[r],
                  " is not a row of targets[", shortest, "] (", targets[shortest].size(0), " rows)");
  }
  for (size_t k = 0; k < params.size(); ++k) {
    at::Tensor s = steps[k];
    s.add_(1);
    const double t = s.item<double>();
    AT_DISPATCH_FLOATING_TYPES(params[k].scalar_type(), "scaled_adam_cpu", [&] {
      step_tensor<scalar_t>(params[k], grads[k], exp_avgs[k], exp_avg_sqs[k], scalar_t(lrs[k]), scalar_t(t),
                            scalar_t(beta1), scalar_t(beta2), scalar_t(eps),
                            weight.has_value() ? weight->data_ptr<scalar_t>() : nullptr,
                            index.has_value() ? &targets[k] : nullptr,
                            index.has_value() ? index->data_ptr<int64_t>() : nullptr);
    });
  }
}

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CPU, m) { m.impl("scaled_adam_", &scaled_adam_cpu); }

}  // namespace scaled_adam
}  // namespace tiger

// CPU kernels of tiger::masked_logit (formula in masked_logit.h): pixels in parallel; the
// backward's sums over pixels through fixed blocks of pixels, summed in block order, so the
// result does not depend on the number of threads.
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <optional>
#include <tuple>

#include "common/optional_tensor.h"
#include "featup/masked_logit.h"
#include "featup/masked_logit_glue.h"

namespace tiger {
namespace featup {
namespace {

constexpr int64_t kPixelBlock = 512;

template <typename T>
void forward_cpu(const T* x, const bool* keep, T keep_scale, const T* w, T bias, const LogitDims& d, T* logit) {
  at::parallel_for(0, d.P, 256, [&](int64_t p0, int64_t p1) {
    for (int64_t p = p0; p < p1; ++p) {
      T sum = 0;
      for (int64_t k = 0; k < d.U; ++k) sum += w[k] * (x[p * d.U + k] * keep_multiplier(keep, keep_scale, k * d.P + p));
      logit[p] = bias + sum;
    }
  });
}

template <typename T>
void backward_cpu(const T* g, const T* x, const bool* keep, T keep_scale, const T* w, const LogitDims& d, T* grad_x,
                  T* partials, T* grad_w, T* grad_b) {
  const int64_t U = d.U, blocks = (d.P + kPixelBlock - 1) / kPixelBlock;
  at::parallel_for(0, blocks, 1, [&](int64_t b0, int64_t b1) {
    for (int64_t b = b0; b < b1; ++b) {
      T* part = partials + b * (U + 1);
      std::fill(part, part + U + 1, T(0));
      for (int64_t p = b * kPixelBlock; p < std::min(d.P, (b + 1) * kPixelBlock); ++p) {
        for (int64_t k = 0; k < U; ++k) {
          const T m = keep_multiplier(keep, keep_scale, k * d.P + p);
          if (grad_x) grad_x[p * U + k] = g[p] * w[k] * m;
          part[k] += g[p] * (x[p * U + k] * m);
        }
        part[U] += g[p];
      }
    }
  });
  for (int64_t k = 0; k <= U; ++k) {
    T total = 0;
    for (int64_t b = 0; b < blocks; ++b) total += partials[b * (U + 1) + k];
    (k < U ? grad_w[k] : grad_b[0]) = total;
  }
}

at::Tensor masked_logit_cpu(const at::Tensor& x, const std::optional<at::Tensor>& keep, double keep_scale,
                            const at::Tensor& weight, const at::Tensor& bias) {
  const LogitDims d = check_masked_logit(x, keep, keep_scale, weight, &bias);
  TORCH_CHECK(x.device().is_cpu(), kMaskedLogitOp, "x must be on the CPU here, got ", x.device());
  const auto xc = x.contiguous(), w = weight.contiguous();
  const auto kc = contiguous(keep);
  auto logit = at::empty({x.size(0), x.size(1)}, xc.options());
  AT_DISPATCH_FLOATING_TYPES(xc.scalar_type(), "tiger.masked_logit", [&] {
    forward_cpu<scalar_t>(xc.data_ptr<scalar_t>(), optional_ptr<bool>(kc), static_cast<scalar_t>(keep_scale),
                          w.data_ptr<scalar_t>(),
                          bias.item<scalar_t>(), d, logit.data_ptr<scalar_t>());
  });
  return logit;
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> masked_logit_backward_cpu(const at::Tensor& grad, const at::Tensor& x,
                                                                         const std::optional<at::Tensor>& keep,
                                                                         double keep_scale, const at::Tensor& weight,
                                                                         bool x_grad) {
  const LogitDims d = check_masked_logit(x, keep, keep_scale, weight, nullptr);
  check_masked_logit_grad(grad, x);
  TORCH_CHECK(x.device().is_cpu(), "tiger.masked_logit_backward: x must be on the CPU here, got ", x.device());
  const auto g = grad.contiguous(), xc = x.contiguous(), w = weight.contiguous();
  const auto kc = contiguous(keep);
  auto grad_x = x_grad ? at::empty_like(xc) : at::empty({0}, xc.options());
  const int64_t blocks = (d.P + kPixelBlock - 1) / kPixelBlock;
  auto partials = at::empty({blocks, d.U + 1}, xc.options());
  auto grad_w = at::empty({d.U}, xc.options()), grad_b = at::empty({1}, xc.options());
  AT_DISPATCH_FLOATING_TYPES(xc.scalar_type(), "tiger.masked_logit_backward", [&] {
    backward_cpu<scalar_t>(g.data_ptr<scalar_t>(), xc.data_ptr<scalar_t>(), optional_ptr<bool>(kc),
                           static_cast<scalar_t>(keep_scale),
                           w.data_ptr<scalar_t>(), d, x_grad ? grad_x.data_ptr<scalar_t>() : nullptr,
                           partials.data_ptr<scalar_t>(), grad_w.data_ptr<scalar_t>(), grad_b.data_ptr<scalar_t>());
  });
  return {grad_x, grad_w, grad_b};
}

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CPU, m) {
  m.impl("masked_logit", &masked_logit_cpu);
  m.impl("masked_logit_backward", &masked_logit_backward_cpu);
}

}  // namespace featup
}  // namespace tiger

// CPU kernels of tiger::group_norm: the reference semantics (any layout via an NCHW copy),
// float64 statistics and accumulation, (n, g) pairs in parallel. Speed is not the goal.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <cmath>
#include <tuple>
#include <vector>

#include "group_norm/group_norm_glue.h"

namespace tiger {
namespace group_norm {
namespace {

constexpr const char* kOp = "tiger.group_norm (CPU)";

std::vector<double> param_values(const c10::optional<at::Tensor>& p, int64_t C, double fill) {
  std::vector<double> v(C, fill);
  if (p.has_value()) {
    const auto d = p->to(at::kDouble).contiguous();
    const double* src = d.data_ptr<double>();
    for (int64_t c = 0; c < C; ++c) v[c] = src[c];
  }
  return v;
}

inline double sigmoid(double z) { return 1.0 / (1.0 + std::exp(-z)); }

// [N·C] float64 input biases (zeros when absent).
std::vector<double> input_bias_values(const c10::optional<at::Tensor>& ib, const at::Tensor& x, const char* op) {
  std::vector<double> v(x.size(0) * x.size(1), 0.0);
  const auto t = input_bias_of(ib, x, op);
  if (t.defined()) {
    const auto d = t.to(at::kDouble).contiguous();
    const double* src = d.data_ptr<double>();
    for (size_t k = 0; k < v.size(); ++k) v[k] = src[k];
  }
  return v;
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> group_norm_cpu(const at::Tensor& x_in,
                                                              const c10::optional<at::Tensor>& weight,
                                                              const c10::optional<at::Tensor>& bias,
                                                              int64_t num_groups, double eps, bool silu,
                                                              const c10::optional<at::Tensor>& input_bias) {
  const Dims d = check_inputs(x_in, weight, bias, num_groups, kOp);
  check_eps(eps, kOp);
  TORCH_CHECK(x_in.device().is_cpu(), kOp, ": x must be on the CPU");
  const auto x = x_in.contiguous();
  const int64_t D = d.C / d.G, M = D * d.HW;
  const auto w = param_values(weight, d.C, 1.0), b = param_values(bias, d.C, 0.0);
  const auto ib = input_bias_values(input_bias, x_in, kOp);
  auto y = at::empty_like(x);
  auto mean = at::empty({d.N, d.G}, x.options().dtype(at::kDouble));
  auto rstd = at::empty({d.N, d.G}, x.options().dtype(at::kDouble));
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, x.scalar_type(), "tiger.group_norm", [&] {
    const scalar_t* xp = x.data_ptr<scalar_t>();
    scalar_t* yp = y.data_ptr<scalar_t>();
    double* mp = mean.data_ptr<double>();
    double* rp = rstd.data_ptr<double>();
    at::parallel_for(0, d.N * d.G, 1, [&](int64_t i0, int64_t i1) {
      for (int64_t i = i0; i < i1; ++i) {
        const scalar_t* xs = xp + i * M;  // (n, g) is one contiguous run in NCHW
        const double* ibs = ib.data() + (i / d.G) * d.C + (i % d.G) * D;  // the group's input biases
        double s = 0.0;
        for (int64_t k = 0; k < M; ++k) s += static_cast<double>(xs[k]) + ibs[k / d.HW];
        const double mu = M > 0 ? s / M : 0.0;
        double ss = 0.0;  // two passes: exact for large-mean inputs
        for (int64_t k = 0; k < M; ++k) {
          const double e = static_cast<double>(xs[k]) + ibs[k / d.HW] - mu;
          ss += e * e;
        }
        const double r = 1.0 / std::sqrt((M > 0 ? ss / M : 0.0) + eps);
        mp[i] = mu;
        rp[i] = r;
        const int64_t c0 = (i % d.G) * D;
        for (int64_t j = 0; j < D; ++j) {
          const double a = r * w[c0 + j], bb = b[c0 + j];
          const scalar_t* xc = xs + j * d.HW;
          scalar_t* yc = yp + i * M + j * d.HW;
          for (int64_t p = 0; p < d.HW; ++p) {
            const double z = (static_cast<double>(xc[p]) + ibs[j] - mu) * a + bb;
            yc[p] = static_cast<scalar_t>(silu ? z * sigmoid(z) : z);
          }
        }
      }
    });
  });
  const auto st = stat_dtype(x);
  return {y.contiguous(memory_format(d.nhwc)), mean.to(st), rstd.to(st)};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> group_norm_backward_cpu(
    const at::Tensor& grad_y_in, const at::Tensor& x_in, const c10::optional<at::Tensor>& weight,
    const c10::optional<at::Tensor>& bias, const at::Tensor& mean_in, const at::Tensor& rstd_in, int64_t num_groups,
    bool silu, bool param_grads, const c10::optional<at::Tensor>& input_bias,
    const c10::optional<at::Tensor>& residual_grad) {
  const char* op = "tiger.group_norm_backward (CPU)";
  const Dims d = check_inputs(x_in, weight, bias, num_groups, op);
  check_backward_inputs(grad_y_in, x_in, mean_in, rstd_in, d, op);
  const auto ib = input_bias_values(input_bias, x_in, op);
  const auto residual = residual_grad_of(residual_grad, x_in, /*nhwc=*/false, op);  // NCHW, like x below
  const auto x = x_in.contiguous();
  const auto dy = grad_y_in.contiguous();
  const auto mean = mean_in.to(at::kDouble).contiguous();
  const auto rstd = rstd_in.to(at::kDouble).contiguous();
  const int64_t D = d.C / d.G, M = D * d.HW;
  const auto w = param_values(weight, d.C, 1.0), b = param_values(bias, d.C, 0.0);
  auto dx = at::empty_like(x);
  // Per-(n, c) sums of dz and dz·x̂, kept for the parameter gradients.
  std::vector<double> sum_dz(d.N * d.C, 0.0), sum_dzx(d.N * d.C, 0.0);
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, x.scalar_type(), "tiger.group_norm_backward", [&] {
    const scalar_t* xp = x.data_ptr<scalar_t>();
    const scalar_t* gp = dy.data_ptr<scalar_t>();
    scalar_t* op_ = dx.data_ptr<scalar_t>();
    const scalar_t* rg = residual.defined() ? residual.data_ptr<scalar_t>() : nullptr;
    const double* mp = mean.data_ptr<double>();
    const double* rp = rstd.data_ptr<double>();
    at::parallel_for(0, d.N * d.G, 1, [&](int64_t i0, int64_t i1) {
      std::vector<double> dz(M), xh(M);
      for (int64_t i = i0; i < i1; ++i) {
        const double mu = mp[i], r = rp[i];
        const int64_t n = i / d.G, c0 = (i % d.G) * D;
        double c1 = 0.0, c2 = 0.0;
        for (int64_t j = 0; j < D; ++j) {
          double s1 = 0.0, s2 = 0.0;
          for (int64_t p = 0; p < d.HW; ++p) {
            const int64_t k = j * d.HW + p;
            const double h = (static_cast<double>(xp[i * M + k]) + ib[n * d.C + c0 + j] - mu) * r;
            double g = static_cast<double>(gp[i * M + k]);
            if (silu) {
              const double z = h * w[c0 + j] + b[c0 + j], s = sigmoid(z);
              g *= s * (1.0 + z * (1.0 - s));
            }
            dz[k] = g;
            xh[k] = h;
            s1 += g;
            s2 += g * h;
          }
          sum_dz[n * d.C + c0 + j] = s1;
          sum_dzx[n * d.C + c0 + j] = s2;
          c1 += w[c0 + j] * s1;
          c2 += w[c0 + j] * s2;
        }
        c1 /= M;
        c2 /= M;
        for (int64_t j = 0; j < D; ++j)
          for (int64_t p = 0; p < d.HW; ++p) {
            const int64_t k = j * d.HW + p;
            const double extra = rg != nullptr ? static_cast<double>(rg[i * M + k]) : 0.0;
            op_[i * M + k] = static_cast<scalar_t>(r * (w[c0 + j] * dz[k] - c1 - xh[k] * c2) + extra);
          }
      }
    });
  });
  auto opts = x.options().dtype(at::kDouble);
  at::Tensor dw = at::zeros({param_grads ? d.C : 0}, opts), db = at::zeros({param_grads ? d.C : 0}, opts);
  if (param_grads) {
    double* dwp = dw.data_ptr<double>();
    double* dbp = db.data_ptr<double>();
    for (int64_t c = 0; c < d.C; ++c) {
      double a = 0.0, bb = 0.0;
      for (int64_t n = 0; n < d.N; ++n) {
        a += sum_dzx[n * d.C + c];
        bb += sum_dz[n * d.C + c];
      }
      dwp[c] = a;
      dbp[c] = bb;
    }
  }
  const auto st = stat_dtype(x);
  return {dx.contiguous(memory_format(d.nhwc)), dw.to(st), db.to(st)};
}

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CPU, m) {
  m.impl("group_norm", &group_norm_cpu);
  m.impl("group_norm_backward", &group_norm_backward_cpu);
}

}  // namespace group_norm
}  // namespace tiger

// CPU kernels of tiger::fourier_layer_norm (formula in fourier.h): pixels in parallel for the
// forward; the backward's sums over pixels go through fixed blocks of pixels (one partial row
// each, summed in block order), so the result does not depend on the number of threads.
#include <ATen/Parallel.h>
#include <c10/util/BFloat16.h>
#include <c10/util/Half.h>
#include <torch/library.h>

#include <cmath>
#include <optional>
#include <tuple>
#include <vector>

#include "common/optional_tensor.h"
#include "featup/fourier.h"
#include "featup/fourier_glue.h"
#include "featup/fourier_math.h"

namespace tiger {
namespace featup {
namespace {

constexpr int64_t kPixelBlock = 512;  // pixels per partial row of the backward

// x [C] (the features of one pixel) and, for the Fourier channels, dx/da [10F].
template <typename T>
void pixel_features(const T* v, const T* freqs, const T* phase, const std::vector<FourierChannel>& ch, T* x,
                    T* dxda) {
  for (size_t c = 0; c < ch.size(); ++c) {
    if (ch[c].kind == 2) {
      x[c] = v[ch[c].input];
      continue;
    }
    T s, co;
    sin_cos(fourier_phase(v, freqs, phase, ch[c], static_cast<int>(c)), &s, &co);
    x[c] = ch[c].kind == 0 ? s : co;
    dxda[c] = ch[c].kind == 0 ? co : -s;
  }
}

std::vector<FourierChannel> channel_table(const FourierDims& d) {
  std::vector<FourierChannel> ch(d.C);
  for (int64_t c = 0; c < d.C; ++c) ch[c] = fourier_channel(static_cast<int>(c), static_cast<int>(d.F));
  return ch;
}

template <typename T, typename O>
void forward_cpu(const T* in, const T* freqs, const T* phase, const T* w, const T* b, const T* scale,
                 const FourierDims& d, T eps, O* out, T* mean, T* rstd) {
  const int64_t C = d.C;
  const auto ch = channel_table(d);
  at::parallel_for(0, d.B * d.N, 64, [&](int64_t p0, int64_t p1) {
    std::vector<T> x(C), dxda(C);
    for (int64_t p = p0; p < p1; ++p) {
      pixel_features(in + p * kFourierInputs, freqs, phase, ch, x.data(), dxda.data());
      T sum = 0;
      for (int64_t c = 0; c < C; ++c) sum += x[c];
      const T m = sum / T(C);
      T var = 0;
      for (int64_t c = 0; c < C; ++c) var += (x[c] - m) * (x[c] - m);
      const T r = T(1) / std::sqrt(var / T(C) + eps);
      mean[p] = m;
      rstd[p] = r;
      const T* s = scale ? scale + (p / d.N) * C : nullptr;
      O* o = out + p * C;
      for (int64_t c = 0; c < C; ++c) {
        T y = (x[c] - m) * r * w[c] + b[c];
        if (s) y *= s[c];
        o[c] = static_cast<O>(y);
      }
    }
  });
}

template <typename T, typename O>
void backward_cpu(const O* grad, const T* in, const T* freqs, const T* phase, const T* w, const T* scale,
                  const T* mean, const T* rstd, const FourierDims& d, T* grad_in, T* partials, T* grad_phase,
                  T* grad_weight, T* grad_bias) {
  const int64_t C = d.C, P = d.B * d.N, blocks = (P + kPixelBlock - 1) / kPixelBlock, fourier = C - 3;
  const auto ch = channel_table(d);
  at::parallel_for(0, blocks, 1, [&](int64_t k0, int64_t k1) {
    std::vector<T> x(C), dxda(C), xh(C), g(C);
    for (int64_t k = k0; k < k1; ++k) {
      T* gph = partials + k * 3 * C;
      T* gw = gph + C;
      T* gb = gw + C;
      std::fill(gph, gph + 3 * C, T(0));
      for (int64_t p = k * kPixelBlock; p < std::min(P, (k + 1) * kPixelBlock); ++p) {
        pixel_features(in + p * kFourierInputs, freqs, phase, ch, x.data(), dxda.data());
        const T m = mean[p], r = rstd[p];
        const T* s = scale ? scale + (p / d.N) * C : nullptr;
        const O* go = grad + p * C;
        T sum_g = 0, sum_gxh = 0;
        for (int64_t c = 0; c < C; ++c) {
          xh[c] = (x[c] - m) * r;
          g[c] = static_cast<T>(go[c]) * (s ? s[c] : T(1));
          gw[c] += g[c] * xh[c];
          gb[c] += g[c];
          sum_g += g[c] * w[c];
          sum_gxh += g[c] * w[c] * xh[c];
        }
        const T mg = sum_g / T(C), mgxh = sum_gxh / T(C);
        T gi[kFourierInputs] = {0, 0, 0, 0, 0};
        for (int64_t c = 0; c < C; ++c) {
          const T dx = r * (g[c] * w[c] - mg - xh[c] * mgxh);
          if (c < fourier) {
            const T da = dx * dxda[c];
            gph[c] += da;
            gi[ch[c].input] += freqs[ch[c].freq] * da;
          } else {
            gi[ch[c].input] += dx;
          }
        }
        if (grad_in)
          for (int i = 0; i < kFourierInputs; ++i) grad_in[p * kFourierInputs + i] = gi[i];
      }
    }
  });
  for (int64_t j = 0; j < 3 * C; ++j) {
    if (j >= fourier && j < C) continue;  // the colour channels have no phase
    T total = 0;
    for (int64_t k = 0; k < blocks; ++k) total += partials[k * 3 * C + j];
    (j < C ? grad_phase[j] : j < 2 * C ? grad_weight[j - C] : grad_bias[j - 2 * C]) = total;
  }
}

// Calls f(T{}, O{}) for the inputs' type T and the output type O (T, bfloat16 or float16).
template <typename Fn>
void dispatch_types(at::ScalarType in_dt, at::ScalarType out_dt, Fn&& f) {
  auto with_out = [&](auto t) {
    using T = decltype(t);
    if (out_dt == in_dt) {
      f(T{}, T{});
    } else if (out_dt == at::kBFloat16) {
      f(T{}, c10::BFloat16{});
    } else {
      f(T{}, c10::Half{});
    }
  };
  if (in_dt == at::kDouble) {
    with_out(double{});
  } else {
    with_out(float{});
  }
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> fourier_cpu(const at::Tensor& inputs, const at::Tensor& freqs,
                                                           const at::Tensor& phase, const at::Tensor& weight,
                                                           const at::Tensor& bias,
                                                           const std::optional<at::Tensor>& scale, double eps,
                                                           std::optional<at::ScalarType> out_dtype) {
  const FourierDims d = check_fourier(inputs, freqs, phase, weight, bias, scale);
  const at::ScalarType odt = fourier_out_dtype(inputs, out_dtype);
  TORCH_CHECK(inputs.device().is_cpu(), kFourierOp, "inputs must be on the CPU here, got ", inputs.device());
  const auto in = inputs.contiguous(), fr = freqs.contiguous(), ph = phase.contiguous(), w = weight.contiguous(),
             b = bias.contiguous();
  const auto s = contiguous(scale);
  auto out = at::empty({d.B, d.N, d.C}, in.options().dtype(odt));
  auto mean = at::empty({d.B, d.N}, in.options()), rstd = at::empty({d.B, d.N}, in.options());
  dispatch_types(in.scalar_type(), odt, [&](auto t, auto o) {
    using T = decltype(t);
    using O = decltype(o);
    forward_cpu<T, O>(in.data_ptr<T>(), fr.data_ptr<T>(), ph.data_ptr<T>(), w.data_ptr<T>(), b.data_ptr<T>(),
                      optional_ptr<T>(s), d, static_cast<T>(eps), reinterpret_cast<O*>(out.data_ptr()),
                      mean.data_ptr<T>(), rstd.data_ptr<T>());
  });
  return {out, mean, rstd};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> fourier_backward_cpu(
    const at::Tensor& grad_out, const at::Tensor& inputs, const at::Tensor& freqs, const at::Tensor& phase,
    const at::Tensor& weight, const std::optional<at::Tensor>& scale, const at::Tensor& mean, const at::Tensor& rstd,
    bool input_grad) {
  const FourierDims d = check_fourier(inputs, freqs, phase, weight, weight, scale);
  check_fourier_backward(grad_out, inputs, mean, rstd, d);
  TORCH_CHECK(inputs.device().is_cpu(), "tiger.fourier_layer_norm_backward: inputs must be on the CPU here");
  const auto g = grad_out.contiguous(), in = inputs.contiguous(), fr = freqs.contiguous(), ph = phase.contiguous(),
             w = weight.contiguous(), mu = mean.contiguous(), rs = rstd.contiguous();
  const auto s = contiguous(scale);
  const int64_t blocks = (d.B * d.N + kPixelBlock - 1) / kPixelBlock;
  auto grad_in = input_grad ? at::empty({d.B, d.N, kFourierInputs}, in.options()) : at::empty({0}, in.options());
  auto partials = at::empty({blocks, 3 * d.C}, in.options());
  auto grad_phase = at::empty({2, kFourierInputs, d.F}, in.options());
  auto grad_weight = at::empty({d.C}, in.options()), grad_bias = at::empty({d.C}, in.options());
  dispatch_types(in.scalar_type(), g.scalar_type(), [&](auto t, auto o) {
    using T = decltype(t);
    using O = decltype(o);
    backward_cpu<T, O>(reinterpret_cast<const O*>(g.data_ptr()), in.data_ptr<T>(), fr.data_ptr<T>(),
                       ph.data_ptr<T>(), w.data_ptr<T>(), optional_ptr<T>(s), mu.data_ptr<T>(), rs.data_ptr<T>(), d,
                       input_grad ? grad_in.data_ptr<T>() : nullptr, partials.data_ptr<T>(), grad_phase.data_ptr<T>(),
                       grad_weight.data_ptr<T>(), grad_bias.data_ptr<T>());
  });
  return {grad_in, grad_phase, grad_weight, grad_bias};
}

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CPU, m) {
  m.impl("fourier_layer_norm", &fourier_cpu);
  m.impl("fourier_layer_norm_backward", &fourier_backward_cpu);
}

}  // namespace featup
}  // namespace tiger

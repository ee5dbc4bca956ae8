// CPU kernels of tiger::adaptive_conv: (batch, channel) planes and (batch, row) strips in parallel.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <tuple>

#include "jbu/jbu.h"
#include "jbu/jbu_glue.h"

namespace tiger {
namespace jbu {
namespace {

template <typename scalar_t>
void forward_cpu(const scalar_t* in, const scalar_t* f, Dims d, scalar_t* out) {
  const int64_t Hp = d.H + d.K - 1, Wp = d.W + d.K - 1, KK = d.K * d.K;
  at::parallel_for(0, d.B * d.C, 1, [&](int64_t p0, int64_t p1) {
    for (int64_t bc = p0; bc < p1; ++bc) {
      const int64_t b = bc / d.C;
      const scalar_t* plane = in + bc * Hp * Wp;
      for (int64_t y = 0; y < d.H; ++y)
        for (int64_t x = 0; x < d.W; ++x) {
          const scalar_t* k = f + ((b * d.H + y) * d.W + x) * KK;
          scalar_t s = 0;
          for (int64_t i = 0; i < d.K; ++i)
            for (int64_t j = 0; j < d.K; ++j) s += plane[(y + i) * Wp + x + j] * k[i * d.K + j];
          out[(bc * d.H + y) * d.W + x] = s;
        }
    }
  });
}

// Gather form: each padded input pixel sums over the outputs whose window covers it (no races).
template <typename scalar_t>
void grad_input_cpu(const scalar_t* go, const scalar_t* f, Dims d, scalar_t* gi) {
  const int64_t Hp = d.H + d.K - 1, Wp = d.W + d.K - 1, KK = d.K * d.K;
  at::parallel_for(0, d.B * d.C, 1, [&](int64_t p0, int64_t p1) {
    for (int64_t bc = p0; bc < p1; ++bc) {
      const int64_t b = bc / d.C;
      for (int64_t yy = 0; yy < Hp; ++yy)
        for (int64_t xx = 0; xx < Wp; ++xx) {
          scalar_t s = 0;
          for (int64_t i = 0; i < d.K; ++i) {
            const int64_t y = yy - i;
            if (y < 0 || y >= d.H) continue;
            for (int64_t j = 0; j < d.K; ++j) {
              const int64_t x = xx - j;
              if (x < 0 || x >= d.W) continue;
              s += go[(bc * d.H + y) * d.W + x] * f[((b * d.H + y) * d.W + x) * KK + i * d.K + j];
            }
          }
          gi[(bc * Hp + yy) * Wp + xx] = s;
        }
    }
  });
}

template <typename scalar_t>
void grad_filters_cpu(const scalar_t* go, const scalar_t* in, Dims d, scalar_t* gf) {
  const int64_t Hp = d.H + d.K - 1, Wp = d.W + d.K - 1, KK = d.K * d.K;
  at::parallel_for(0, d.B * d.H, 1, [&](int64_t r0, int64_t r1) {
    for (int64_t by = r0; by < r1; ++by) {
      const int64_t b = by / d.H, y = by % d.H;
      for (int64_t x = 0; x < d.W; ++x) {
        scalar_t* k = gf + (by * d.W + x) * KK;
        for (int64_t t = 0; t < KK; ++t) k[t] = 0;
        for (int64_t c = 0; c < d.C; ++c) {
          const scalar_t g = go[((b * d.C + c) * d.H + y) * d.W + x];
          const scalar_t* plane = in + (b * d.C + c) * Hp * Wp;
          for (int64_t i = 0; i < d.K; ++i)
            for (int64_t j = 0; j < d.K; ++j) k[i * d.K + j] += g * plane[(y + i) * Wp + x + j];
        }
      }
    }
  });
}

at::Tensor adaptive_conv_cpu(const at::Tensor& input_in, const at::Tensor& filters_in) {
  const Dims d = check_adaptive_conv(input_in, filters_in);
  TORCH_CHECK(input_in.device().is_cpu(), "tiger.adaptive_conv (CPU): input must be on the CPU");
  const auto input = input_in.contiguous();
  const auto filters = filters_in.contiguous();
  auto out = at::empty({d.B, d.C, d.H, d.W}, input.options());
  AT_DISPATCH_FLOATING_TYPES(input.scalar_type(), "tiger.adaptive_conv", [&] {
    forward_cpu<scalar_t>(input.data_ptr<scalar_t>(), filters.data_ptr<scalar_t>(), d, out.data_ptr<scalar_t>());
  });
  return out;
}

std::tuple<at::Tensor, at::Tensor> adaptive_conv_backward_cpu(const at::Tensor& grad_out_in,
                                                              const at::Tensor& input_in,
                                                              const at::Tensor& filters_in, bool need_input,
                                                              bool need_filters) {
  const Dims d = check_adaptive_conv(input_in, filters_in);
  TORCH_CHECK(grad_out_in.sizes() == at::IntArrayRef({d.B, d.C, d.H, d.W}),
              "tiger.adaptive_conv_backward: grad_out must be [B, C, H, W] = [", d.B, ", ", d.C, ", ", d.H,
              ", ", d.W, "], got ", grad_out_in.sizes());
  const auto go = grad_out_in.to(input_in.scalar_type()).contiguous();
  const auto input = input_in.contiguous();
  const auto filters = filters_in.contiguous();
  at::Tensor gi, gf;
  AT_DISPATCH_FLOATING_TYPES(input.scalar_type(), "tiger.adaptive_conv_backward", [&] {
    if (need_input) {
      gi = at::empty_like(input);
      grad_input_cpu<scalar_t>(go.data_ptr<scalar_t>(), filters.data_ptr<scalar_t>(), d, gi.data_ptr<scalar_t>());
    }
    if (need_filters) {
      gf = at::empty_like(filters);
      grad_filters_cpu<scalar_t>(go.data_ptr<scalar_t>(), input.data_ptr<scalar_t>(), d, gf.data_ptr<scalar_t>());
    }
  });
  if (!gi.defined()) gi = at::zeros_like(input);
  if (!gf.defined()) gf = at::zeros_like(filters);
  return {gi, gf};
}

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CPU, m) {
  m.impl("adaptive_conv", &adaptive_conv_cpu);
  m.impl("adaptive_conv_backward", &adaptive_conv_backward_cpu);
}

}  // namespace jbu
}  // namespace tiger

// CPU kernels of tiger::jittered_window_attention: cells in parallel for the forward and the
// per-cell backward; the features' gradient in parallel over channel blocks (no races).
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <tuple>
#include <vector>

#include "featup/featup.h"
#include "featup/featup_glue.h"
#include "featup/featup_math.h"

namespace tiger {
namespace featup {
namespace {

// The taps of the K rows and K columns of one cell's window.
template <typename T>
struct CellTaps {
  std::vector<Tap<T>> y, x;
  CellTaps(const T* cy, const T* cx, const WindowDims& d, int64_t cell) : y(d.K), x(d.K) {
    const int64_t j = cell / (d.FH * d.FW), i = (cell / d.FW) % d.FH, l = cell % d.FW;
    for (int64_t t = 0; t < d.K; ++t) {
      y[t] = axis_tap(cy[j * d.Ho + i * d.SH + t], d.H);
      x[t] = axis_tap(cx[j * d.Wo + l * d.SW + t], d.W);
    }
  }
};

// Calls f(source pixel index, bilinear weight) for the (up to) four taps of window pixel (ty, tx).
template <typename T, typename F>
inline void for_taps(const Tap<T>& ty, const Tap<T>& tx, int64_t W, F&& f) {
  const int64_t base = static_cast<int64_t>(ty.index) * W + tx.index;
  const T wy0 = T(1) - ty.frac, wx0 = T(1) - tx.frac;
  f(base, wy0 * wx0);
  if (tx.second) f(base + 1, wy0 * tx.frac);
  if (ty.second) {
    f(base + W, ty.frac * wx0);
    if (tx.second) f(base + W + 1, ty.frac * tx.frac);
  }
}

// attn (softmax of the masked, scaled logits) of one cell; logits[p] receives X_j(logit_map)[p].
template <typename T>
void cell_attention(const CellTaps<T>& taps, const T* logit_map, const T* w, const T* b, T m,
                    const WindowDims& d, T* attn, T* logits) {
  const int64_t K = d.K;
  T zmax = -INFINITY;
  for (int64_t py = 0; py < K; ++py)
    for (int64_t px = 0; px < K; ++px) {
      const int64_t p = py * K + px;
      const T L = bilinear(logit_map, d.W, taps.y[py], taps.x[px]);
      logits[p] = L;
      attn[p] = L * m * w[p] + b[p];
      zmax = std::max(zmax, attn[p]);
    }
  T sum = 0;
  for (int64_t p = 0; p < K * K; ++p) sum += (attn[p] = std::exp(attn[p] - zmax));
  for (int64_t p = 0; p < K * K; ++p) attn[p] /= sum;
}

template <typename T>
void forward_cpu(const T* F, const T* logit_map, const T* cy, const T* cx, const T* w, const T* b, const T* mask,
                 const WindowDims& d, T* out, T* attn) {
  const int64_t cells = d.J * d.FH * d.FW, KK = d.K * d.K, C = d.C;
  at::parallel_for(0, cells, 1, [&](int64_t c0, int64_t c1) {
    std::vector<T> logits(KK);
    for (int64_t cell = c0; cell < c1; ++cell) {
      const CellTaps<T> taps(cy, cx, d, cell);
      T* a = attn + cell * KK;
      cell_attention(taps, logit_map, w, b, mask[cell], d, a, logits.data());
      T* o = out + cell * C;
      std::fill(o, o + C, T(0));
      for (int64_t py = 0; py < d.K; ++py)
        for (int64_t px = 0; px < d.K; ++px) {
          const T ap = a[py * d.K + px];
          for_taps(taps.y[py], taps.x[px], d.W, [&](int64_t src, T wt) {
            const T coef = ap * wt;
            const T* f = F + src * C;
            for (int64_t c = 0; c < C; ++c) o[c] += coef * f[c];
          });
        }
    }
  });
}

template <typename T>
void backward_cpu(const T* g, const T* F, const T* logit_map, const T* cy, const T* cx, const T* w, const T* mask,
                  const T* attn, const WindowDims& d, T* gF, T* gL, T* gw, T* gb) {
  const int64_t cells = d.J * d.FH * d.FW, KK = d.K * d.K, C = d.C;
  std::vector<T> gz(cells * KK), gzl(cells * KK);
  // per cell: the softmax's input gradient (and its product with mask * logit, for w)
  at::parallel_for(0, cells, 1, [&](int64_t c0, int64_t c1) {
    std::vector<T> ga(KK);
    for (int64_t cell = c0; cell < c1; ++cell) {
      const CellTaps<T> taps(cy, cx, d, cell);
      const T* a = attn + cell * KK;
      const T* gc = g + cell * C;
      T dot = 0;
      for (int64_t py = 0; py < d.K; ++py)
        for (int64_t px = 0; px < d.K; ++px) {
          T s = 0;
          for_taps(taps.y[py], taps.x[px], d.W, [&](int64_t src, T wt) {
            const T* f = F + src * C;
            T acc = 0;
            for (int64_t c = 0; c < C; ++c) acc += gc[c] * f[c];
            s += wt * acc;
          });
          ga[py * d.K + px] = s;
          dot += a[py * d.K + px] * s;
        }
      const T m = mask[cell];
      for (int64_t py = 0; py < d.K; ++py)
        for (int64_t px = 0; px < d.K; ++px) {
          const int64_t p = py * d.K + px;
          gz[cell * KK + p] = a[p] * (ga[p] - dot);
          gzl[cell * KK + p] = gz[cell * KK + p] * m * bilinear(logit_map, d.W, taps.y[py], taps.x[px]);
        }
    }
  });
  // w, b and the logit map (serial: K*K*4 scattered adds per cell)
  std::fill(gw, gw + KK, T(0));
  std::fill(gb, gb + KK, T(0));
  std::fill(gL, gL + d.H * d.W, T(0));
  for (int64_t cell = 0; cell < cells; ++cell) {
    const CellTaps<T> taps(cy, cx, d, cell);
    const T m = mask[cell];
    for (int64_t py = 0; py < d.K; ++py)
      for (int64_t px = 0; px < d.K; ++px) {
        const int64_t p = py * d.K + px;
        gb[p] += gz[cell * KK + p];
        gw[p] += gzl[cell * KK + p];
        const T coef = gz[cell * KK + p] * m * w[p];
        for_taps(taps.y[py], taps.x[px], d.W, [&](int64_t src, T wt) { gL[src] += coef * wt; });
      }
  }
  // features: every channel block walks all cells (race-free)
  std::fill(gF, gF + d.H * d.W * C, T(0));
  constexpr int64_t kBlock = 16;
  at::parallel_for(0, (C + kBlock - 1) / kBlock, 1, [&](int64_t b0, int64_t b1) {
    for (int64_t blk = b0; blk < b1; ++blk) {
      const int64_t ca = blk * kBlock, cb = std::min(C, ca + kBlock);
      for (int64_t cell = 0; cell < cells; ++cell) {
        const CellTaps<T> taps(cy, cx, d, cell);
        const T* a = attn + cell * KK;
        const T* gc = g + cell * C;
        for (int64_t py = 0; py < d.K; ++py)
          for (int64_t px = 0; px < d.K; ++px) {
            const T ap = a[py * d.K + px];
            for_taps(taps.y[py], taps.x[px], d.W, [&](int64_t src, T wt) {
              const T coef = ap * wt;
              T* out = gF + src * C;
              for (int64_t c = ca; c < cb; ++c) out[c] += coef * gc[c];
            });
          }
      }
    }
  });
}

std::tuple<at::Tensor, at::Tensor> window_attention_cpu(const at::Tensor& features, const at::Tensor& logit_map,
                                                        const at::Tensor& coord_y, const at::Tensor& coord_x,
                                                        const at::Tensor& w, const at::Tensor& b,
                                                        const at::Tensor& mask, int64_t stride_h, int64_t stride_w,
                                                        c10::string_view variant) {
  const WindowDims d = check_window_attention(features, logit_map, coord_y, coord_x, w, b, mask, stride_h, stride_w);
  parse_window_variant(variant);  // the CPU kernels are every variant's reference: checked, not used
  TORCH_CHECK(features.device().is_cpu(), "tiger.jittered_window_attention (CPU): features must be on the CPU");
  const auto F = features.contiguous(), L = logit_map.contiguous(), cy = coord_y.contiguous(),
             cx = coord_x.contiguous(), wc = w.contiguous(), bc = b.contiguous(), mc = mask.contiguous();
  auto out = at::empty({d.J, d.FH, d.FW, d.C}, F.options());
  auto attn = at::empty({d.J, d.FH, d.FW, d.K * d.K}, F.options());
  AT_DISPATCH_FLOATING_TYPES(F.scalar_type(), "tiger.jittered_window_attention", [&] {
    forward_cpu<scalar_t>(F.data_ptr<scalar_t>(), L.data_ptr<scalar_t>(), cy.data_ptr<scalar_t>(),
                          cx.data_ptr<scalar_t>(), wc.data_ptr<scalar_t>(), bc.data_ptr<scalar_t>(),
                          mc.data_ptr<scalar_t>(), d, out.data_ptr<scalar_t>(), attn.data_ptr<scalar_t>());
  });
  return {out, attn};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> window_attention_backward_cpu(
    const at::Tensor& grad_out, const at::Tensor& features, const at::Tensor& logit_map, const at::Tensor& coord_y,
    const at::Tensor& coord_x, const at::Tensor& w, const at::Tensor& b, const at::Tensor& mask,
    const at::Tensor& attn, int64_t stride_h, int64_t stride_w, c10::string_view variant) {
  const WindowDims d = check_window_attention(features, logit_map, coord_y, coord_x, w, b, mask, stride_h, stride_w);
  parse_window_variant(variant);
  TORCH_CHECK(features.device().is_cpu(), "tiger.jittered_window_attention_backward (CPU): features must be on the CPU");
  TORCH_CHECK(grad_out.sizes() == at::IntArrayRef({d.J, d.FH, d.FW, d.C}),
              "tiger.jittered_window_attention_backward: grad_out must be [J, FH, FW, C] = [", d.J, ", ", d.FH, ", ",
              d.FW, ", ", d.C, "], got ", grad_out.sizes());
  TORCH_CHECK(attn.sizes() == at::IntArrayRef({d.J, d.FH, d.FW, d.K * d.K}) && attn.scalar_type() == features.scalar_type(),
              "tiger.jittered_window_attention_backward: attn must be the forward's [J, FH, FW, K*K], got ",
              attn.sizes(), " ", attn.scalar_type());
  const auto g = grad_out.to(features.scalar_type()).contiguous(), F = features.contiguous(),
             L = logit_map.contiguous(), cy = coord_y.contiguous(), cx = coord_x.contiguous(), wc = w.contiguous(),
             mc = mask.contiguous(), a = attn.contiguous();
  auto gF = at::empty_like(F), gL = at::empty_like(L), gw = at::empty_like(wc), gb = at::empty_like(wc);
  AT_DISPATCH_FLOATING_TYPES(F.scalar_type(), "tiger.jittered_window_attention_backward", [&] {
    backward_cpu<scalar_t>(g.data_ptr<scalar_t>(), F.data_ptr<scalar_t>(), L.data_ptr<scalar_t>(),
                           cy.data_ptr<scalar_t>(), cx.data_ptr<scalar_t>(), wc.data_ptr<scalar_t>(),
                           mc.data_ptr<scalar_t>(), a.data_ptr<scalar_t>(), d, gF.data_ptr<scalar_t>(),
                           gL.data_ptr<scalar_t>(), gw.data_ptr<scalar_t>(), gb.data_ptr<scalar_t>());
  });
  return {gF, gL, gw, gb};
}

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CPU, m) {
  m.impl("jittered_window_attention", &window_attention_cpu);
  m.impl("jittered_window_attention_backward", &window_attention_backward_cpu);
}

}  // namespace featup
}  // namespace tiger

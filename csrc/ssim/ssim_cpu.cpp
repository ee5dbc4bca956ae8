// CPU fused SSIM: per image plane, the window along rows (five moment sums) then along columns,
// in the input's precision, planes and row blocks in parallel.
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <vector>

#include "ssim/ssim.h"

namespace tiger {
namespace ssim {
namespace {

// out_k[r][c] = sum_t taps[t] in_k[r][c + t - radius] (zero outside the row) for K maps.
template <typename T, int K>
void filter_rows(const T* const in[K], T* const out[K], int64_t rows, int64_t W, const Window& w) {
  for (int64_t r = 0; r < rows; ++r)
    for (int64_t c = 0; c < W; ++c) {
      T acc[K] = {};
      for (int t = -w.radius; t <= w.radius; ++t) {
        const int64_t cc = c + t;
        if (cc < 0 || cc >= W) continue;
        const T g = T(w.taps[t + w.radius]);
        for (int k = 0; k < K; ++k) acc[k] += g * in[k][r * W + cc];
      }
      for (int k = 0; k < K; ++k) out[k][r * W + c] = acc[k];
    }
}

// The column pass at (r, c) of K row-filtered maps.
template <typename T, int K>
void filter_column(const T* const in[K], int64_t H, int64_t W, int64_t r, int64_t c, const Window& w,
                   T acc[K]) {
  for (int k = 0; k < K; ++k) acc[k] = T(0);
  for (int t = -w.radius; t <= w.radius; ++t) {
    const int64_t rr = r + t;
    if (rr < 0 || rr >= H) continue;
    const T g = T(w.taps[t + w.radius]);
    for (int k = 0; k < K; ++k) acc[k] += g * in[k][rr * W + c];
  }
}

template <typename T>
void forward_plane(const T* x, const T* y, int64_t H, int64_t W, const Window& w, T c1, T c2, T* out,
                   T* dmu1, T* de11, T* de12) {
  const int64_t n = H * W;
  std::vector<T> prod(3 * n), rows(5 * n);
  for (int64_t i = 0; i < n; ++i) {
    prod[i] = x[i] * x[i];
    prod[n + i] = y[i] * y[i];
    prod[2 * n + i] = x[i] * y[i];
  }
  const T* in[5] = {x, y, prod.data(), prod.data() + n, prod.data() + 2 * n};
  T* rf[5] = {rows.data(), rows.data() + n, rows.data() + 2 * n, rows.data() + 3 * n, rows.data() + 4 * n};
  filter_rows<T, 5>(in, rf, H, W, w);
  const T* rc[5] = {rf[0], rf[1], rf[2], rf[3], rf[4]};
  for (int64_t r = 0; r < H; ++r)
    for (int64_t c = 0; c < W; ++c) {
      T m[5];
      filter_column<T, 5>(rc, H, W, r, c, w, m);
      const SsimPixel<T> p = ssim_pixel<T>(m[0], m[1], m[2], m[3], m[4], c1, c2);
      const int64_t i = r * W + c;
      out[i] = p.value;
      dmu1[i] = p.dmu1;
      de11[i] = p.de11;
      de12[i] = p.de12;
    }
}

template <typename T>
void backward_plane(const T* grad, const T* x, const T* y, const T* dmu1, const T* de11, const T* de12,
                    int64_t H, int64_t W, const Window& w, T* dx) {
  const int64_t n = H * W;
  std::vector<T> g(3 * n), rows(3 * n);
  for (int64_t i = 0; i < n; ++i) {
    g[i] = grad[i] * dmu1[i];
    g[n + i] = grad[i] * de11[i];
    g[2 * n + i] = grad[i] * de12[i];
  }
  const T* in[3] = {g.data(), g.data() + n, g.data() + 2 * n};
  T* rf[3] = {rows.data(), rows.data() + n, rows.data() + 2 * n};
  filter_rows<T, 3>(in, rf, H, W, w);
  const T* rc[3] = {rf[0], rf[1], rf[2]};
  for (int64_t r = 0; r < H; ++r)
    for (int64_t c = 0; c < W; ++c) {
      T b[3];
      filter_column<T, 3>(rc, H, W, r, c, w, b);
      const int64_t i = r * W + c;
      dx[i] = b[0] + T(2) * x[i] * b[1] + y[i] * b[2];
    }
}

std::tuple<at::Tensor, at::Tensor> fused_ssim_cpu(const at::Tensor& img1_in, const at::Tensor& img2_in,
                                                  at::ArrayRef<double> taps, double c1, double c2) {
  check_images(img1_in, img2_in);
  TORCH_CHECK(img1_in.device().is_cpu(), kOp, " (CPU): images must be on the CPU");
  const Window w = check_taps(taps);
  const auto img1 = img1_in.contiguous(), img2 = img2_in.contiguous();
  auto out = at::empty_like(img1);
  auto dm = at::empty({3, img1.size(0), img1.size(1), img1.size(2), img1.size(3)}, img1.options());
  const int64_t planes = img1.size(0) * img1.size(1), H = img1.size(2), W = img1.size(3), n = H * W;
  if (out.numel() == 0) return {out, dm};
  AT_DISPATCH_FLOATING_TYPES(img1.scalar_type(), "fused_ssim_cpu", [&] {
    using T = scalar_t;
    const T *x = img1.data_ptr<T>(), *y = img2.data_ptr<T>();
    T *o = out.data_ptr<T>(), *d = dm.data_ptr<T>();
    const int64_t total = planes * n;
    at::parallel_for(0, planes, 1, [&](int64_t p0, int64_t p1) {
      for (int64_t p = p0; p < p1; ++p)
        forward_plane<T>(x + p * n, y + p * n, H, W, w, T(c1), T(c2), o + p * n, d + p * n,
                         d + total + p * n, d + 2 * total + p * n);
    });
  });
  return {out, dm};
}

at::Tensor fused_ssim_backward_cpu(const at::Tensor& grad_in, const at::Tensor& img1_in, const at::Tensor& img2_in,
                                   const at::Tensor& dm_in, at::ArrayRef<double> taps) {
  check_backward(grad_in, img1_in, img2_in, dm_in);
  const Window w = check_taps(taps);
  const auto grad = grad_in.contiguous(), img1 = img1_in.contiguous(), img2 = img2_in.contiguous(),
             dm = dm_in.contiguous();
  auto dx = at::empty_like(img1);
  const int64_t planes = img1.size(0) * img1.size(1), H = img1.size(2), W = img1.size(3), n = H * W;
  if (dx.numel() == 0) return dx;
  AT_DISPATCH_FLOATING_TYPES(img1.scalar_type(), "fused_ssim_backward_cpu", [&] {
    using T = scalar_t;
    const T *g = grad.data_ptr<T>(), *x = img1.data_ptr<T>(), *y = img2.data_ptr<T>(), *d = dm.data_ptr<T>();
    T* o = dx.data_ptr<T>();
    const int64_t total = planes * n;
    at::parallel_for(0, planes, 1, [&](int64_t p0, int64_t p1) {
      for (int64_t p = p0; p < p1; ++p)
        backward_plane<T>(g + p * n, x + p * n, y + p * n, d + p * n, d + total + p * n, d + 2 * total + p * n,
                          H, W, w, o + p * n);
    });
  });
  return dx;
}

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CPU, m) {
  m.impl("fused_ssim", &fused_ssim_cpu);
  m.impl("fused_ssim_backward", &fused_ssim_backward_cpu);
}

}  // namespace ssim
}  // namespace tiger

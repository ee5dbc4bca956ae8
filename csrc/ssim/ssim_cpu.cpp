// CPU fused SSIM, in the input's precision, as two row-parallel passes over all image planes:
// the window along each row (K sums per pixel into a [K, planes·H, W] buffer), then along each
// column, finishing every pixel (forward: the SSIM formula; backward: the image gradient). Rows,
// not planes, are the unit of work: an RGB image has 3 planes for any number of threads.
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <vector>

#include "ssim/ssim.h"

namespace tiger {
namespace ssim {
namespace {

constexpr int64_t kRowGrain = 8;  // rows per parallel task

// out_k[pr][c] = sum_t taps[t] v_k(pr, c + t - radius) over the row pr of the planes·H rows
// (zero outside the row), for K maps; value(pr, c, v) writes the K values at row pr, column c,
// computed once per pixel into a row buffer.
template <typename T, int K, typename Value>
void row_pass(int64_t rows, int64_t W, const Window& w, T* out, Value&& value) {
  const int64_t stride = rows * W;
  at::parallel_for(0, rows, kRowGrain, [&](int64_t r0, int64_t r1) {
    std::vector<T> buf(K * W);  // [W][K]
    for (int64_t pr = r0; pr < r1; ++pr) {
      for (int64_t c = 0; c < W; ++c) value(pr, c, buf.data() + c * K);
      for (int64_t c = 0; c < W; ++c) {
        T acc[K] = {};
        for (int t = -w.radius; t <= w.radius; ++t) {
          const int64_t cc = c + t;
          if (cc < 0 || cc >= W) continue;
          const T g = T(w.taps[t + w.radius]);
          const T* v = buf.data() + cc * K;
          for (int k = 0; k < K; ++k) acc[k] += g * v[k];
        }
        for (int k = 0; k < K; ++k) out[k * stride + pr * W + c] = acc[k];
      }
    }
  });
}

// finish(i, sums) at every pixel i = plane·H·W + r·W + c, with sums[k] the column pass of map k
// of the row pass at (plane, r, c) (zero outside the plane).
template <typename T, int K, typename Finish>
void column_pass(int64_t planes, int64_t H, int64_t W, const Window& w, const T* rows, Finish&& finish) {
  const int64_t stride = planes * H * W;
  at::parallel_for(0, planes * H, kRowGrain, [&](int64_t r0, int64_t r1) {
    for (int64_t pr = r0; pr < r1; ++pr) {
      const int64_t p = pr / H, r = pr - p * H;
      for (int64_t c = 0; c < W; ++c) {
        T acc[K] = {};
        for (int t = -w.radius; t <= w.radius; ++t) {
          const int64_t rr = r + t;
          if (rr < 0 || rr >= H) continue;
          const T g = T(w.taps[t + w.radius]);
          const int64_t j = (p * H + rr) * W + c;
          for (int k = 0; k < K; ++k) acc[k] += g * rows[k * stride + j];
        }
        finish(pr * W + c, acc);
      }
    }
  });
}

std::tuple<at::Tensor, at::Tensor> fused_ssim_cpu(const at::Tensor& img1_in, const at::Tensor& img2_in,
                                                  at::ArrayRef<double> taps, double c1, double c2) {
  check_images(img1_in, img2_in);
  TORCH_CHECK(img1_in.device().is_cpu(), kOp, " (CPU): images must be on the CPU");
  const Window w = check_taps(taps);
  const auto img1 = img1_in.contiguous(), img2 = img2_in.contiguous();
  auto out = at::empty_like(img1);
  auto dm = at::empty({3, img1.size(0), img1.size(1), img1.size(2), img1.size(3)}, img1.options());
  const int64_t planes = img1.size(0) * img1.size(1), H = img1.size(2), W = img1.size(3);
  if (out.numel() == 0) return {out, dm};
  AT_DISPATCH_FLOATING_TYPES(img1.scalar_type(), "fused_ssim_cpu", [&] {
    using T = scalar_t;
    const T *x = img1.data_ptr<T>(), *y = img2.data_ptr<T>();
    T *o = out.data_ptr<T>(), *d = dm.data_ptr<T>();
    const int64_t total = out.numel();
    std::vector<T> rows(5 * total);
    // the five moments' row sums: x, y, x x, y y, x y
    row_pass<T, 5>(planes * H, W, w, rows.data(), [&](int64_t pr, int64_t c, T* v) {
      const T a = x[pr * W + c], b = y[pr * W + c];
      v[0] = a;
      v[1] = b;
      v[2] = a * a;
      v[3] = b * b;
      v[4] = a * b;
    });
    column_pass<T, 5>(planes, H, W, w, rows.data(), [&](int64_t i, const T* m) {
      const SsimPixel<T> p = ssim_pixel<T>(m[0], m[1], m[2], m[3], m[4], T(c1), T(c2));
      o[i] = p.value;
      d[i] = p.dmu1;
      d[total + i] = p.de11;
      d[2 * total + i] = p.de12;
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
  const int64_t planes = img1.size(0) * img1.size(1), H = img1.size(2), W = img1.size(3);
  if (dx.numel() == 0) return dx;
  AT_DISPATCH_FLOATING_TYPES(img1.scalar_type(), "fused_ssim_backward_cpu", [&] {
    using T = scalar_t;
    const T *g = grad.data_ptr<T>(), *x = img1.data_ptr<T>(), *y = img2.data_ptr<T>(), *d = dm.data_ptr<T>();
    T* o = dx.data_ptr<T>();
    const int64_t total = dx.numel();
    std::vector<T> rows(3 * total);
    // the incoming gradient times each derivative map (d/d mu1, d/d e11, d/d e12)
    row_pass<T, 3>(planes * H, W, w, rows.data(), [&](int64_t pr, int64_t c, T* v) {
      const int64_t i = pr * W + c;
      v[0] = g[i] * d[i];
      v[1] = g[i] * d[total + i];
      v[2] = g[i] * d[2 * total + i];
    });
    column_pass<T, 3>(planes, H, W, w, rows.data(), [&](int64_t i, const T* b) {
      o[i] = b[0] + T(2) * x[i] * b[1] + y[i] * b[2];
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

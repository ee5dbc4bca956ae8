// CPU kernel of tiger::relevancy: one pass over the features, rows in parallel.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <limits>
#include <vector>

#include "relevancy/relevancy.h"
#include "relevancy/relevancy_glue.h"

namespace tiger {
namespace relevancy {
namespace {

template <typename scalar_t, typename acc_t>
void relevancy_cpu_kernel(const scalar_t* feat, const acc_t* texts, int64_t n, int64_t d, int64_t q,
                          int64_t m, acc_t temperature, acc_t eps, acc_t* cos_out, acc_t* rel_out) {
  at::parallel_for(0, n, 256, [&](int64_t begin, int64_t end) {
    std::vector<acc_t> row(d);
    std::vector<acc_t> dots(q + m);
    for (int64_t i = begin; i < end; ++i) {
      const scalar_t* f = feat + i * d;
      acc_t n2 = 0;
      for (int64_t k = 0; k < d; ++k) {
        row[k] = static_cast<acc_t>(f[k]);
        n2 += row[k] * row[k];
      }
      const acc_t inv = acc_t(1) / std::max(std::sqrt(n2), eps);
      for (int64_t t = 0; t < q + m; ++t) {
        const acc_t* tv = texts + t * d;
        acc_t s = 0;
        for (int64_t k = 0; k < d; ++k) s += row[k] * tv[k];
        dots[t] = s * inv;
      }
      acc_t max_neg = -std::numeric_limits<acc_t>::infinity();
      for (int64_t j = 0; j < m; ++j) max_neg = std::max(max_neg, dots[q + j]);
      for (int64_t t = 0; t < q; ++t) {
        cos_out[i * q + t] = dots[t];
        if (m > 0) rel_out[i * q + t] = lerf_relevancy<acc_t>(dots[t], max_neg, temperature);
      }
    }
  });
}

std::tuple<at::Tensor, at::Tensor> relevancy_cpu(const at::Tensor& features, const at::Tensor& positives,
                                                 const at::Tensor& negatives, double temperature,
                                                 double eps) {
  TORCH_CHECK(features.device().is_cpu(), "tiger.relevancy (CPU): features must be on the CPU");
  Prepared p = prepare(features, positives, negatives, temperature, eps);
  if (p.n == 0 || p.q == 0) return {p.cosine, p.relevancy};
  AT_DISPATCH_FLOATING_TYPES_AND(at::kHalf, p.features.scalar_type(), "tiger.relevancy", [&] {
    using acc_t = std::conditional_t<std::is_same_v<scalar_t, double>, double, float>;
    relevancy_cpu_kernel<scalar_t, acc_t>(
        p.features.data_ptr<scalar_t>(), p.texts.data_ptr<acc_t>(), p.n, p.d, p.q, p.m,
        static_cast<acc_t>(temperature), static_cast<acc_t>(eps), p.cosine.data_ptr<acc_t>(),
        p.m > 0 ? p.relevancy.data_ptr<acc_t>() : nullptr);
  });
  return {p.cosine, p.relevancy};
}

}  // namespace
}  // namespace relevancy
}  // namespace tiger

TORCH_LIBRARY_IMPL(tiger, CPU, m) { m.impl("relevancy", &tiger::relevancy::relevancy_cpu); }

// CPU kernel of tiger::relevancy: one pass over the features, rows in parallel.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <vector>
#if defined(__F16C__)
#include <immintrin.h>
#endif

#include "relevancy/relevancy.h"
#include "relevancy/relevancy_glue.h"

namespace tiger {
namespace relevancy {
namespace {

// Rows are processed in blocks of kBlock, stored transposed ([D][kBlock], accumulation type) so
// that every dot product is a loop over independent rows: it vectorises (AVX2 FMA) without
// reassociating any sum, so the results do not depend on the SIMD width.
constexpr int64_t kBlock = 64;

// One row to the accumulation type. float16 uses the F16C conversion when the build has it
// (c10::Half's portable conversion costs ~10 ns per element, more than the rest of the op).
template <typename scalar_t, typename acc_t>
inline void row_to_acc(const scalar_t* f, int64_t d, acc_t* out) {
  for (int64_t k = 0; k < d; ++k) out[k] = static_cast<acc_t>(f[k]);
}
#if defined(__F16C__)
template <>
inline void row_to_acc<at::Half, float>(const at::Half* f, int64_t d, float* out) {
  int64_t k = 0;
  for (; k + 8 <= d; k += 8)
    _mm256_storeu_ps(out + k, _mm256_cvtph_ps(_mm_loadu_si128(reinterpret_cast<const __m128i*>(f + k))));
  for (; k < d; ++k) out[k] = static_cast<float>(f[k]);
}
#endif

template <typename scalar_t, typename acc_t>
void relevancy_cpu_kernel(const scalar_t* feat, const acc_t* texts, int64_t n, int64_t d, int64_t q,
                          int64_t m, acc_t temperature, acc_t eps, acc_t* cos_out, acc_t* rel_out) {
  const int64_t blocks = (n + kBlock - 1) / kBlock;
  // Grain of 64 blocks (4096 rows, ~1 ms): smaller inputs run inline, no thread wake-up.
  at::parallel_for(0, blocks, 64, [&](int64_t b0, int64_t b1) {
    std::vector<acc_t> buf(d * kBlock), row(d);
    acc_t inv[kBlock], dot[kBlock], max_neg[kBlock];
    // dot[r] = <row r of the block, v>, the block stored dimension-major so r vectorises.
    auto block_dot = [&](const acc_t* v) {
      for (int64_t r = 0; r < kBlock; ++r) dot[r] = 0;
      for (int64_t k = 0; k < d; ++k) {
        const acc_t* x = buf.data() + k * kBlock;
        const acc_t c = v[k];
        for (int64_t r = 0; r < kBlock; ++r) dot[r] += x[r] * c;
      }
    };
    for (int64_t b = b0; b < b1; ++b) {
      const int64_t r0 = b * kBlock;
      const int64_t nr = std::min(kBlock, n - r0);
      for (int64_t r = 0; r < kBlock; ++r) {
        if (r < nr) {
          row_to_acc<scalar_t, acc_t>(feat + (r0 + r) * d, d, row.data());
          for (int64_t k = 0; k < d; ++k) buf[k * kBlock + r] = row[k];
        } else {
          for (int64_t k = 0; k < d; ++k) buf[k * kBlock + r] = acc_t(0);
        }
      }
      for (int64_t r = 0; r < kBlock; ++r) dot[r] = 0;
      for (int64_t k = 0; k < d; ++k) {
        const acc_t* x = buf.data() + k * kBlock;
        for (int64_t r = 0; r < kBlock; ++r) dot[r] += x[r] * x[r];
      }
      for (int64_t r = 0; r < kBlock; ++r) {
        inv[r] = acc_t(1) / std::max(std::sqrt(dot[r]), eps);
        max_neg[r] = -std::numeric_limits<acc_t>::infinity();
      }
      // Negatives first (their maximum is needed by every query), then the queries.
      for (int64_t t = q; t < q + m; ++t) {
        block_dot(texts + t * d);
        for (int64_t r = 0; r < kBlock; ++r) max_neg[r] = std::max(max_neg[r], dot[r] * inv[r]);
      }
      for (int64_t t = 0; t < q; ++t) {
        block_dot(texts + t * d);
        for (int64_t r = 0; r < nr; ++r) {
          const acc_t cs = dot[r] * inv[r];
          cos_out[(r0 + r) * q + t] = cs;
          if (m > 0) rel_out[(r0 + r) * q + t] = lerf_relevancy<acc_t>(cs, max_neg[r], temperature);
        }
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

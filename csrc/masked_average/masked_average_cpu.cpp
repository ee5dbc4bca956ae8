// CPU kernels of tiger::masked_average: channel blocks in parallel, float64 accumulation.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <tuple>
#include <vector>

#include "masked_average/masked_average.h"
#include "masked_average/masked_average_glue.h"

namespace tiger {
namespace masked_average {
namespace {

constexpr int64_t kChannelBlock = 16;

// sums[M, C] (float64) of values[P, C] grouped by ids; each thread owns a block of channels, so
// no two threads write the same sum.
template <typename scalar_t>
void segment_sum_cpu(const scalar_t* values, const int64_t* ids, int64_t P, int64_t C, double* sums) {
  const int64_t blocks = (C + kChannelBlock - 1) / kChannelBlock;
  at::parallel_for(0, blocks, 1, [&](int64_t b0, int64_t b1) {
    for (int64_t b = b0; b < b1; ++b) {
      const int64_t c0 = b * kChannelBlock, c1 = std::min(C, c0 + kChannelBlock);
      for (int64_t p = 0; p < P; ++p) {
        const int64_t m = ids[p];
        if (m < 0) continue;
        const scalar_t* v = values + p * C;
        double* s = sums + m * C;
        for (int64_t c = c0; c < c1; ++c) s[c] += static_cast<double>(v[c]);
      }
    }
  });
}

std::vector<int64_t> count_ids(const int64_t* ids, int64_t P, int64_t M) {
  std::vector<int64_t> counts(M, 0);
  for (int64_t p = 0; p < P; ++p)
    if (ids[p] >= 0) ++counts[ids[p]];
  return counts;
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> masked_average_cpu(const at::Tensor& features_in,
                                                                  const at::Tensor& ids_in,
                                                                  int64_t num_masks) {
  check_features_ids(features_in, ids_in, "features");
  TORCH_CHECK(features_in.device().is_cpu(), "tiger.masked_average (CPU): features must be on the CPU");
  check_id_range(ids_in, num_masks);
  const auto features = features_in.contiguous();
  const auto ids = ids_in.contiguous();
  const int64_t P = features.size(0), C = features.size(1), M = num_masks;
  auto out = at::empty_like(features);
  auto means = at::zeros({M, C}, features.options());
  auto counts = at::zeros({M}, ids.options());
  const int64_t* id = ids.data_ptr<int64_t>();
  const auto cnt = count_ids(id, P, M);
  std::copy(cnt.begin(), cnt.end(), counts.data_ptr<int64_t>());
  std::vector<double> sums(M * C, 0.0);
  AT_DISPATCH_FLOATING_TYPES(features.scalar_type(), "tiger.masked_average", [&] {
    const scalar_t* f = features.data_ptr<scalar_t>();
    segment_sum_cpu<scalar_t>(f, id, P, C, sums.data());
    scalar_t* mp = means.data_ptr<scalar_t>();
    for (int64_t m = 0; m < M; ++m)
      for (int64_t c = 0; c < C; ++c)
        mp[m * C + c] = cnt[m] > 0 ? static_cast<scalar_t>(sums[m * C + c] / cnt[m]) : scalar_t(0);
    scalar_t* o = out.data_ptr<scalar_t>();
    at::parallel_for(0, P, 1024, [&](int64_t p0, int64_t p1) {
      for (int64_t p = p0; p < p1; ++p) {
        const scalar_t* src = id[p] >= 0 ? mp + id[p] * C : f + p * C;
        std::copy(src, src + C, o + p * C);
      }
    });
  });
  return {out, means, counts};
}

at::Tensor masked_average_backward_cpu(const at::Tensor& grad_out_in, const at::Tensor& grad_means_in,
                                       const at::Tensor& ids_in, const at::Tensor& counts_in) {
  check_features_ids(grad_out_in, ids_in, "grad_out");
  const int64_t P = grad_out_in.size(0), C = grad_out_in.size(1), M = counts_in.size(0);
  TORCH_CHECK(grad_means_in.dim() == 2 && grad_means_in.size(0) == M && grad_means_in.size(1) == C,
              "tiger.masked_average_backward: grad_means must be [M, C] = [", M, ", ", C, "], got ",
              grad_means_in.sizes());
  TORCH_CHECK(counts_in.scalar_type() == at::kLong && counts_in.dim() == 1,
              "tiger.masked_average_backward: counts must be [M] int64");
  const auto grad_out = grad_out_in.contiguous();
  const auto grad_means = grad_means_in.to(grad_out.scalar_type()).contiguous();
  const auto ids = ids_in.contiguous();
  const auto counts = counts_in.contiguous();
  auto grad = at::empty_like(grad_out);
  const int64_t* id = ids.data_ptr<int64_t>();
  const int64_t* cnt = counts.data_ptr<int64_t>();
  std::vector<double> sums(M * C, 0.0);
  AT_DISPATCH_FLOATING_TYPES(grad_out.scalar_type(), "tiger.masked_average_backward", [&] {
    const scalar_t* g = grad_out.data_ptr<scalar_t>();
    const scalar_t* gm = grad_means.data_ptr<scalar_t>();
    segment_sum_cpu<scalar_t>(g, id, P, C, sums.data());
    for (int64_t m = 0; m < M; ++m)
      for (int64_t c = 0; c < C; ++c)
        sums[m * C + c] = cnt[m] > 0 ? (sums[m * C + c] + gm[m * C + c]) / cnt[m] : 0.0;
    scalar_t* o = grad.data_ptr<scalar_t>();
    at::parallel_for(0, P, 1024, [&](int64_t p0, int64_t p1) {
      for (int64_t p = p0; p < p1; ++p) {
        if (id[p] >= 0) {
          const double* s = sums.data() + id[p] * C;
          for (int64_t c = 0; c < C; ++c) o[p * C + c] = static_cast<scalar_t>(s[c]);
        } else {
          std::copy(g + p * C, g + (p + 1) * C, o + p * C);
        }
      }
    });
  });
  return grad;
}

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CPU, m) {
  m.impl("masked_average", &masked_average_cpu);
  m.impl("masked_average_backward", &masked_average_backward_cpu);
}

}  // namespace masked_average
}  // namespace tiger

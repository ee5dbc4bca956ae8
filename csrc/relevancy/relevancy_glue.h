#pragma once
// ATen-side checks and preparation shared by the CPU and CUDA implementations
// (included from .cpp files only: the .cu kernels see raw pointers).
#include <ATen/ATen.h>

#include <cmath>
#include <tuple>

namespace tiger {
namespace relevancy {

struct Prepared {
  at::Tensor features;  // [N, D] contiguous, original dtype
  at::Tensor texts;     // [Q + M, D] contiguous, accumulation dtype, rows normalised
  at::Tensor cosine;    // [N, Q] output
  at::Tensor relevancy; // [N, Q] output, or [0] when M == 0
  int64_t n, d, q, m;
};

inline at::ScalarType acc_dtype(at::ScalarType feature_dtype) {
  return feature_dtype == at::kDouble ? at::kDouble : at::kFloat;
}

inline Prepared prepare(const at::Tensor& features, const at::Tensor& positives,
                        const at::Tensor& negatives, double temperature, double eps) {
  TORCH_CHECK(features.dim() == 2, "tiger.relevancy: features must be [N, D], got ", features.sizes());
  const auto ft = features.scalar_type();
  TORCH_CHECK(ft == at::kHalf || ft == at::kFloat || ft == at::kDouble,
              "tiger.relevancy: features must be float16, float32 or float64, got ", ft);
  TORCH_CHECK(positives.dim() == 2 && positives.size(1) == features.size(1),
              "tiger.relevancy: positives must be [Q, D] with D = ", features.size(1), ", got ",
              positives.sizes());
  TORCH_CHECK(negatives.dim() == 2 && negatives.size(1) == features.size(1),
              "tiger.relevancy: negatives must be [M, D] with D = ", features.size(1), ", got ",
              negatives.sizes());
  TORCH_CHECK(at::isFloatingType(positives.scalar_type()),
              "tiger.relevancy: positives must be a floating tensor, got ", positives.scalar_type());
  TORCH_CHECK(at::isFloatingType(negatives.scalar_type()),
              "tiger.relevancy: negatives must be a floating tensor, got ", negatives.scalar_type());
  TORCH_CHECK(positives.device() == features.device() && negatives.device() == features.device(),
              "tiger.relevancy: features, positives and negatives must be on one device (got ",
              features.device(), ", ", positives.device(), ", ", negatives.device(), ")");
  TORCH_CHECK(std::isfinite(temperature) && temperature > 0,
              "tiger.relevancy: temperature must be finite and > 0, got ", temperature);
  TORCH_CHECK(std::isfinite(eps) && eps > 0, "tiger.relevancy: eps must be finite and > 0, got ", eps);
  TORCH_CHECK(features.size(1) > 0, "tiger.relevancy: the embedding dimension D must be > 0");

  Prepared p;
  p.n = features.size(0);
  p.d = features.size(1);
  p.q = positives.size(0);
  p.m = negatives.size(0);
  p.features = features.contiguous();
  const auto acc = acc_dtype(ft);
  // Q + M rows: normalising them once here (a few hundred flops) keeps the kernels to one
  // pass over the features.
  auto texts = at::cat({positives.to(acc), negatives.to(acc)}, 0);
  texts = texts / texts.norm(2, {1}, /*keepdim=*/true).clamp_min(eps);
  p.texts = texts.contiguous();
  auto opts = features.options().dtype(acc);
  p.cosine = at::empty({p.n, p.q}, opts);
  p.relevancy = p.m > 0 ? at::empty({p.n, p.q}, opts) : at::empty({0}, opts);
  return p;
}

}  // namespace relevancy
}  // namespace tiger

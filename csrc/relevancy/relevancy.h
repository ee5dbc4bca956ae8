#pragma once
// Relevancy op family: fused normalise + dot product + LERF relevancy.
//
// tiger::relevancy(features [N, D] (float16 / float32 / float64),
//                  positives [Q, D], negatives [M, D] (any float dtype),
//                  float temperature, float eps) -> (cosine [N, Q], relevancy [N, Q] or [0])
//
//   f_hat = f / max(|f|, eps), q_hat = q / max(|q|, eps)  (text rows are normalised once, on the host side)
//   cosine[i, q]    = f_hat_i . q_hat_q
//   relevancy[i, q] = min_j exp(t c_iq) / (exp(t c_iq) + exp(t c_ij))       (LERF, t = temperature)
//                   = sigmoid(t (c_iq - max_j c_ij))                          (the form computed: no overflow)
//   With M == 0 the relevancy output is an empty tensor of shape [0].
// Outputs are float32 for float16 / float32 features and float64 for float64 features.
#include "common/macros.h"
#include <math.h>

namespace tiger {
namespace relevancy {

// The LERF pairwise softmax against the hardest negative, written as a sigmoid so that
// large temperatures never overflow exp().
TIGER_HD float exp_t(float x) { return expf(x); }
TIGER_HD double exp_t(double x) { return ::exp(x); }

template <typename T>
TIGER_HD T lerf_relevancy(T cos_pos, T max_cos_neg, T temperature) {
  const T z = temperature * (cos_pos - max_cos_neg);
  // 1 / (1 + exp(-z)) for z >= 0; exp(z) / (1 + exp(z)) for z < 0 (no exp overflow either way).
  if (z >= T(0)) {
    return T(1) / (T(1) + exp_t(-z));
  }
  const T e = exp_t(z);
  return e / (T(1) + e);
}

}  // namespace relevancy
}  // namespace tiger

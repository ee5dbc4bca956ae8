#pragma once
// One element of tiger::scaled_adam_, shared by the CPU loop and the CUDA kernel so that both
// round alike. Adam as torch.optim.Adam computes it (no weight decay, no amsgrad, step t >= 1):
//   m <- b1 m + (1 - b1) g,   v <- b2 v + (1 - b2) g^2,
//   p_adam = p - (lr / (1 - b1^t)) m / (sqrt(v) / sqrt(1 - b2^t) + eps),
// and the row's weight w scales the update: p <- p + w (p_adam - p) = p - w (p - p_adam).
#include <math.h>

#include "common/macros.h"

namespace tiger {
namespace scaled_adam {

constexpr int kMaxTensors = 8;  // tensors of one step: the scene's per-Gaussian parameters are at most 7

// lr / (1 - b1^t) and sqrt(1 - b2^t): the step's two bias corrections, in T.
template <typename T>
struct StepScalars {
  T step_size, bc2_sqrt;
};

template <typename T>
TIGER_HD StepScalars<T> step_scalars(T lr, T beta1, T beta2, T t) {
  return {lr / (T(1) - pow(beta1, t)), sqrt(T(1) - pow(beta2, t))};
}

template <typename T>
TIGER_HD void update_element(T& p, T g, T& m, T& v, T w, T beta1, T beta2, T eps, const StepScalars<T>& s) {
  m = beta1 * m + (T(1) - beta1) * g;
  v = beta2 * v + (T(1) - beta2) * g * g;
  const T denom = sqrt(v) / s.bc2_sqrt + eps;
  p = p - w * (s.step_size * m / denom);
}

}  // namespace scaled_adam
}  // namespace tiger

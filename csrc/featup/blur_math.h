#pragma once
// The reflect-padded Gaussian taps of one row or column and their transpose, shared by the CPU
// and CUDA kernels of tiger::magnitude_blur (formula in magnitude_blur.h).
#include <cmath>
#include <cstdint>

#include "common/macros.h"
#include "featup/magnitude_blur.h"

namespace tiger {
namespace featup {

// F.pad's "reflect" of index i about 0 and n - 1 (|overhang| < n).
TIGER_HD int64_t reflect_index(int64_t i, int64_t n) {
  if (i < 0) return -i;
  if (i >= n) return 2 * (n - 1) - i;
  return i;
}

// The transposed taps of output index j along an axis of size n: the source indices i and the
// weights with which blurred[i] read index j (direct taps, plus the reflected taps of the
// rows near the borders). At most 4 radius + 1 distinct i, each listed once, in increasing i.
template <typename T>
struct AdjointTaps {
  int64_t index[4 * kMaxBlurRadius + 1];
  T weight[4 * kMaxBlurRadius + 1];
  int count;
};

template <typename T>
TIGER_HD void adjoint_taps(int64_t j, int64_t n, const T* g, int radius, AdjointTaps<T>& out) {
  if (j > radius && j < n - 1 - radius) {  // no reflected tap reaches j: the direct taps, i = j - t
    out.count = 2 * radius + 1;
    for (int s = 0; s < out.count; ++s) {
      out.index[s] = j - radius + s;
      out.weight[s] = g[2 * radius - s];
    }
    return;
  }
  const int slots = 4 * radius + 1;
  T w[4 * kMaxBlurRadius + 1];
  for (int s = 0; s < slots; ++s) w[s] = T(0);
  const int64_t first = j - 2 * radius;  // slot s holds i = first + s
  for (int t = -radius; t <= radius; ++t) {
    const T gt = g[t + radius];
    const int64_t direct = j - t;  // blurred[direct] reads j + ... at tap t without reflection
    if (direct >= 0 && direct < n) w[direct - first] += gt;
    if (j >= 1) {  // i + t = -j < 0 reflects onto j
      const int64_t i = -j - t;
      if (i >= 0 && i < n) w[i - first] += gt;
    }
    if (j < n - 1) {  // i + t = 2 (n - 1) - j > n - 1 reflects onto j
      const int64_t i = 2 * (n - 1) - j - t;
      if (i >= 0 && i < n) w[i - first] += gt;
    }
  }
  out.count = 0;
  for (int s = 0; s < slots; ++s) {
    if (w[s] != T(0)) {
      out.index[out.count] = first + s;
      out.weight[out.count] = w[s];
      ++out.count;
    }
  }
}

}  // namespace featup
}  // namespace tiger

#pragma once
// The bilinear taps of one row or column of a jittered copy, shared by the CPU and CUDA kernels.
#include <cmath>
#include <cstdint>

#include "common/macros.h"

namespace tiger {
namespace featup {

// Source index of the first tap, and the second tap's weight (the first's is 1 - frac); the
// second tap exists when index + 1 < size (grid_sample, align_corners=True). The coordinate is
// clamped to [0, size - 1] first (a NaN reads index 0).
template <typename T>
struct Tap {
  int32_t index;
  T frac;
  bool second;
};

template <typename T>
TIGER_HD Tap<T> axis_tap(T coord, int64_t size) {
  const T hi = static_cast<T>(size - 1);
  T s = coord > T(0) ? coord : T(0);  // NaN -> 0
  s = s < hi ? s : hi;
  const T f = std::floor(s);
  Tap<T> t;
  t.index = static_cast<int32_t>(f);
  t.frac = s - f;
  t.second = t.index + 1 < size;
  return t;
}

// Bilinear value of a single-channel map [H, W] at the taps (ty, tx).
template <typename T>
TIGER_HD T bilinear(const T* map, int64_t W, const Tap<T>& ty, const Tap<T>& tx) {
  const T* row = map + static_cast<int64_t>(ty.index) * W + tx.index;
  T top = (T(1) - tx.frac) * row[0];
  if (tx.second) top += tx.frac * row[1];
  T v = (T(1) - ty.frac) * top;
  if (ty.second) {
    const T* next = row + W;
    T bottom = (T(1) - tx.frac) * next[0];
    if (tx.second) bottom += tx.frac * next[1];
    v += ty.frac * bottom;
  }
  return v;
}

}  // namespace featup
}  // namespace tiger

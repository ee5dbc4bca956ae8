#pragma once
// Launcher of the CUDA scaled-Adam kernel (scaled_adam_cuda.cu).
#include <cstdint>

#include "scaled_adam/scaled_adam_math.h"

namespace tiger {
namespace scaled_adam {

// The tensors of one step: tensor k holds elements [start[k], start[k + 1]) of the flattened
// list, `row[k]` per row; its step count is read from step[k] (float32, or float64 where
// step_double[k]) after the glue has incremented it.
template <typename T>
struct Lists {
  T* p[kMaxTensors];
  const T* g[kMaxTensors];
  T* m[kMaxTensors];
  T* v[kMaxTensors];
  T* target[kMaxTensors];
  const void* step[kMaxTensors];
  bool step_double[kMaxTensors];
  int64_t row[kMaxTensors];
  int64_t start[kMaxTensors + 1];
  T lr[kMaxTensors];
  int n;
};

template <typename T>
void launch_scaled_adam(const Lists<T>& lists, const T* weight, const int64_t* index, T beta1, T beta2, T eps,
                        void* stream);

}  // namespace scaled_adam
}  // namespace tiger

#pragma once
// dispatch_stored_types (stored_types.h) with the CUDA element types the kernels are
// instantiated for (__nv_bfloat16, __half); included by the CUDA glue only.
#include <cuda_bf16.h>
#include <cuda_fp16.h>

#include <utility>

#include "featup/stored_types.h"

namespace tiger {
namespace featup {

template <typename Fn>
void dispatch_cuda_stored_types(at::ScalarType dt, const char* op, Fn&& f) {
  dispatch_stored_types<__nv_bfloat16, __half>(dt, op, std::forward<Fn>(f));
}

}  // namespace featup
}  // namespace tiger

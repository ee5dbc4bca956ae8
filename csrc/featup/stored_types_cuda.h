#pragma once
// dispatch_stored_types (stored_types.h) with the CUDA element types the kernels are
// instantiated for (__nv_bfloat16, __half); included by the CUDA glue only.
#include <ATen/ATen.h>
#include <cuda_bf16.h>
#include <cuda_fp16.h>

namespace tiger {
namespace featup {

template <typename Fn>
void dispatch_cuda_stored_types(at::ScalarType dt, const char* op, Fn&& f) {
  switch (dt) {
    case at::kDouble: f(double{}, double{}); break;
    case at::kFloat: f(float{}, float{}); break;
    case at::kBFloat16: f(__nv_bfloat16{}, float{}); break;
    case at::kHalf: f(__half{}, float{}); break;
    default: TORCH_CHECK(false, op, "unsupported dtype ", dt);
  }
}

}  // namespace featup
}  // namespace tiger

#pragma once
// Dtype dispatch of the FeatUp ops that read activations as stored (float64, float32, bf16, fp16)
// and accumulate in float32 (float64 for float64): f(X{}, T{}) with X the stored element type
// and T the accumulation type. One home for the glue of relu_norm and magnitude_blur; the
// CUDA glue passes the CUDA types as BF16 and Half (dispatch_cuda_stored_types, stored_types_cuda.h).
#include <ATen/ATen.h>
#include <c10/util/BFloat16.h>
#include <c10/util/Half.h>

namespace tiger {
namespace featup {

template <typename BF16 = c10::BFloat16, typename Half = c10::Half, typename Fn>
void dispatch_stored_types(at::ScalarType dt, const char* op, Fn&& f) {
  switch (dt) {
    case at::kDouble: f(double{}, double{}); break;
    case at::kFloat: f(float{}, float{}); break;
    case at::kBFloat16: f(BF16{}, float{}); break;
    case at::kHalf: f(Half{}, float{}); break;
    default: TORCH_CHECK(false, op, "unsupported dtype ", dt);
  }
}

}  // namespace featup
}  // namespace tiger

#pragma once
// Checks shared by the CPU and CUDA implementations of the fp8_rows family.
#include <ATen/ATen.h>

#include "common/torch_checks.h"

namespace tiger {
namespace fp8_rows {

inline void check_quantize_input(const at::Tensor& x, bool geglu) {
  const char* op = "tiger.quantize_rows_fp8";
  TORCH_CHECK(x.dim() == 2, op, ": x must be [M, K] (a matmul's activations as rows), got ", shape_str(x.sizes()));
  TORCH_CHECK(x.is_floating_point() && x.element_size() >= 2, op,
              ": x must be float32, bfloat16 or float16 (float64 on the CPU), got ", x.scalar_type());
  TORCH_CHECK(!geglu || x.size(1) % 2 == 0, op, ": geglu=True needs an even number of columns (value and gate "
              "halves), got K = ", x.size(1));
}

inline void check_geglu_input(const at::Tensor& x) {
  const char* op = "tiger.geglu";
  TORCH_CHECK(x.dim() >= 1 && x.size(-1) % 2 == 0, op, ": x must be [..., 2F] (value and gate halves), got ",
              shape_str(x.sizes()));
  TORCH_CHECK(x.is_floating_point() && x.element_size() >= 2, op,
              ": x must be float32, bfloat16 or float16 (float64 on the CPU), got ", x.scalar_type());
}

}  // namespace fp8_rows
}  // namespace tiger

// CPU implementation of the fp8_rows family: the reference semantics (ops.cpp), computed with ATen
// in float32 (float64 for float64 input) and rounded once, as the CUDA kernels do.
#include <torch/library.h>

#include <tuple>

#include "fp8_rows/fp8_rows.h"
#include "fp8_rows/fp8_rows_glue.h"

namespace tiger {
namespace fp8_rows {
namespace {

at::Tensor geglu_float(const at::Tensor& x) {
  const auto acc = x.scalar_type() == at::kDouble ? at::kDouble : at::kFloat;
  const int64_t F = x.size(-1) / 2;
  const auto xf = x.to(acc);
  return xf.narrow(-1, 0, F) * at::gelu(xf.narrow(-1, F, F));
}

std::tuple<at::Tensor, at::Tensor> quantize_rows_fp8_cpu(const at::Tensor& x, bool geglu) {
  check_quantize_input(x, geglu);
  const auto acc = x.scalar_type() == at::kDouble ? at::kDouble : at::kFloat;
  const auto h = geglu ? geglu_float(x) : x.to(acc);
  const auto amax = h.abs().amax({1}, /*keepdim=*/true);
  const auto positive = amax > 0;
  // Element-wise divisions by a same-shape tensor (a scalar divisor may become a reciprocal
  // multiply), so both roundings equal the CUDA kernel's IEEE divisions.
  const auto fp8_max = at::full_like(amax, kE4M3Max);
  const auto inv = at::where(positive, at::div(fp8_max, amax), at::ones_like(amax));
  const auto scale = at::where(positive, at::div(amax, fp8_max), at::ones_like(amax)).to(at::kFloat);
  const auto q = (h * inv).clamp(-kE4M3Max, kE4M3Max).to(at::kFloat8_e4m3fn);
  return {q, scale};
}

at::Tensor geglu_cpu(const at::Tensor& x) {
  check_geglu_input(x);
  return geglu_float(x).to(x.scalar_type()).contiguous();
}

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CPU, m) {
  m.impl("quantize_rows_fp8", &quantize_rows_fp8_cpu);
  m.impl("geglu", &geglu_cpu);
}

}  // namespace fp8_rows
}  // namespace tiger

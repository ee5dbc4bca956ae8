// Schema of the fp8_rows family: row-wise float8 (e4m3) quantisation of a matmul's activations,
// optionally of a GEGLU's output computed on the fly, and the GEGLU itself.
//   quantize_rows_fp8(x [M, K], geglu) -> (q [M, K'] float8_e4m3fn, scale [M, 1] float32)
//     h = geglu ? x[:, :F]·gelu(x[:, F:]) (K = 2F, K' = F) : x (K' = K), in float;
//     amax = max_k |h|, scale = amax / 448 (1 when amax = 0), q = e4m3(h · (448 / amax)) (saturating).
//   geglu(x [..., 2F]) -> [..., F] = x[..., :F]·gelu(x[..., F:]) (exact erf GELU, float, rounded once).
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(tiger, m) {
  m.def("quantize_rows_fp8(Tensor x, bool geglu=False) -> (Tensor, Tensor)");
  m.def("geglu(Tensor x) -> Tensor");
}

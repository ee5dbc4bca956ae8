// Schema of the layer_norm family: LayerNorm over the last dimension of row-major rows, the
// transformer blocks' norms of the guidances' UNets (tiger/edit/guidance/model_kernels.py).
//   layer_norm_rows(x [..., C], weight [C], bias [C] or None, eps, input_bias [C] or None) -> [..., C]
//     with u = x + input_bias (in float; the row itself when None):
//     y = (u - mean) / sqrt(var + eps) * weight + bias per row, mean and (biased) var of u
//     computed in float (double for float64) in two passes, the result rounded once to x's dtype.
//     input_bias lets a residual stream carry a per-channel bias not yet added to it.
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(tiger, m) { m.def("layer_norm_rows(Tensor x, Tensor weight, Tensor? bias, float eps, Tensor? input_bias=None) -> Tensor"); }

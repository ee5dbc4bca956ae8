// Schema of the attention family: softmax(q kᵀ · scale) v over token rows [batch·L, heads·D]
// (the layout diffusers' attention layers hold q, k and v in), for the guidances' UNets.
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(tiger, m) {
  m.def("attention_rows(Tensor q, Tensor k, Tensor v, int batch, int heads, float? scale=None, "
        "str schedule=\"producer\", int warpgroups=3) -> Tensor");
}

// Schema of the channel_bias family: y = x + bias[c], the bias a convolution leaves out.
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(tiger, m) { m.def("channel_bias_add(Tensor x, Tensor bias) -> Tensor"); }

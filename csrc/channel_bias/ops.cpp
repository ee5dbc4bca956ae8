// Schema of the channel_bias family: y = x + bias[(n,) c] (+ residual), the bias a convolution
// leaves out (plus, per sample, a ResNet block's time embedding) and the block's shortcut.
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(tiger, m) { m.def("channel_bias_add(Tensor x, Tensor bias, Tensor? residual=None) -> Tensor"); }

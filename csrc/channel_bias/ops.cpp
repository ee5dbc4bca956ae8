// Schema of the channel_bias family: y = x + bias[(n,) c] (+ residual), the bias a convolution
// leaves out (plus, per sample, a ResNet block's time embedding) and the block's shortcut.
#include <torch/library.h>

// channel_bias_add_into writes the same values into a given output (e.g. a channel slice of a wider
// channels-last map); without a bias it is a copy (+ residual).
TORCH_LIBRARY_FRAGMENT(tiger, m) {
  m.def("channel_bias_add(Tensor x, Tensor bias, Tensor? residual=None) -> Tensor");
  m.def("channel_bias_add_into(Tensor x, Tensor? bias, Tensor? residual, Tensor(a!) out) -> ()");
}

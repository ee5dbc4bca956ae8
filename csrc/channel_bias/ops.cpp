// Schema of the channel_bias family: y = x + bias[(n,) c] (+ residual), the bias a convolution
// leaves out (plus, per sample, a ResNet block's time embedding) and the block's shortcut.
#include <torch/library.h>

// channel_bias_add_into writes the same values into a given output (e.g. a channel slice of a wider
// channels-last map); without a bias it is a copy (+ residual).
// subpixel_interleave_into(z [N, 4C, H+1, W+1], bias [C] or None, out [N, C, 2H, 2W]):
//   out[n, c, 2i+a, 2j+b] = z[n, (2a+b)·C + c, i+a, j+b] (+ bias[c]), summed in float and rounded
//   once: the four phase outputs of a sub-pixel 2x upsampling convolution interleaved, with its bias.
TORCH_LIBRARY_FRAGMENT(tiger, m) {
  m.def("channel_bias_add(Tensor x, Tensor bias, Tensor? residual=None) -> Tensor");
  m.def("channel_bias_add_into(Tensor x, Tensor? bias, Tensor? residual, Tensor(a!) out) -> ()");
  m.def("subpixel_interleave_into(Tensor z, Tensor? bias, Tensor(a!) out) -> ()");
}

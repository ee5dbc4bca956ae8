#pragma once
// tiger::fourier_layer_norm — the first layers of FeatUp's implicit network in one pass: the
// Fourier features of each pixel's five inputs, their LayerNorm and an optional per-image,
// per-channel multiplier (the channel dropout's mask), written once in the output dtype.
//
//   inputs [B, N, 5]   per pixel (y, x, r, g, b), min-max scaled
//   freqs  [F]         the frequencies
//   phase  [2, 5, F]   learned phase biases, read flat: channel c < 10F adds phase_flat[c]
//                      (FeatUp reshapes its (2, 5, F) biases as (2, F, 5))
//   weight, bias [C]   the LayerNorm's affine, C = 10F + 3
//   scale  [B, C]      optional multiplier per image and channel (not differentiable)
//
// Channels of pixel (n, i), with m = c mod 5F, d = m mod 5, f = m / 5:
//   a_c = inputs[d] * freqs[f] + phase_flat[c]   (c < 10F; the product rounded before the sum)
//   x_c = sin(a_c) for c < 5F, cos(a_c) for 5F <= c < 10F, inputs[2 + c - 10F] for the colour
//   mean = sum_c x_c / C;  rstd = 1 / sqrt(sum_c (x_c - mean)^2 / C + eps)
//   out_c = ((x_c - mean) * rstd * weight_c + bias_c) * scale[n, c]
// Outputs: out [B, N, C] (the output dtype), mean and rstd [B, N] (the inputs' dtype).
//
// Backward (fourier_layer_norm_backward), g = grad_out * scale, xh = (x - mean) * rstd:
//   grad_weight_c = sum_pixels g_c xh_c;  grad_bias_c = sum_pixels g_c
//   dx_c = rstd (g_c w_c - mean_c'(g w) - xh_c mean_c'(g w xh))
//   grad_phase_flat[c] = sum_pixels dx_c * (cos a_c for sin channels, -sin a_c for cos channels)
//   grad_inputs[d] = sum over the channels of input d of freqs[f] * dx_c * (cos a_c | -sin a_c),
//                    plus dx of the colour channel for d >= 2.
// The features are recomputed from the inputs; nothing of C channels is stored. The sums over
// pixels go through fixed blocks of pixels (one partial row per block, then summed in block
// order): deterministic, and the same on every run.
#include <cstdint>

namespace tiger {
namespace featup {

constexpr int kFourierInputs = 5;
constexpr int kMaxFourierChannels = 512;  // C <= 512 (F <= 50) on CUDA: 16 channels per lane

struct FourierDims {
  int64_t B, N, F, C;  // images, pixels per image, frequencies, channels (10F + 3)
};

// Number of partial rows (pixel blocks) of the CUDA backward for P pixels.
int fourier_backward_blocks(int64_t pixels);

// T: float or double (inputs, parameters, statistics); O: the output / gradient storage type
// (T, __nv_bfloat16 or __half). scale may be null.
template <typename T, typename O>
void launch_fourier_forward(const T* inputs, const T* freqs, const T* phase, const T* weight, const T* bias,
                            const T* scale, FourierDims d, double eps, O* out, T* mean, T* rstd, void* stream);

// grad_inputs [B, N, 5] may be null (not computed); partials [blocks, 3C] scratch (per block:
// the phase gradient by channel, the last 3 unused, then the weight's and the bias's);
// grad_phase [10F], grad_weight [C], grad_bias [C] the block sums.
template <typename T, typename O>
void launch_fourier_backward(const O* grad_out, const T* inputs, const T* freqs, const T* phase, const T* weight,
                             const T* scale, const T* mean, const T* rstd, FourierDims d, T* grad_inputs,
                             T* partials, int blocks, T* grad_phase, T* grad_weight, T* grad_bias, void* stream);

}  // namespace featup
}  // namespace tiger

#pragma once
// tiger::relu_scale_layer_norm — the implicit network's hidden layers between its first and
// second linear maps in one pass: ReLU, a per-image, per-channel multiplier (the channel
// dropout's mask) and LayerNorm, read and written once in the activations' dtype.
//
//   x      [B, N, D]   the first linear map's output (float32/float64, bfloat16/float16 on CUDA)
//   scale  [B, D]      optional multiplier per image and channel (not differentiable)
//   weight, bias [D]   the LayerNorm's affine (float32, float64 for float64 x)
//
//   z_c = max(x_c, 0) * scale[n, c];  mean = sum_c z_c / D;  rstd = 1 / sqrt(var_c(z) + eps)
//   out_c = (z_c - mean) * rstd * weight_c + bias_c      (x's dtype; statistics in the affine's)
// Outputs: out [B, N, D], mean and rstd [B, N].
//
// Backward (relu_scale_layer_norm_backward), g = grad_out, zh = (z - mean) * rstd:
//   grad_weight = sum_pixels g zh;  grad_bias = sum_pixels g
//   dz_c = rstd (g_c w_c - mean_c'(g w) - zh_c mean_c'(g w zh))
//   grad_x_c = dz_c * scale_c if x_c > 0, else 0
// The sums over pixels go through fixed blocks of pixels, summed in block order (deterministic).
#include <cstdint>

namespace tiger {
namespace featup {

constexpr int kMaxNormChannels = 512;  // D <= 512 on CUDA

struct NormDims {
  int64_t B, N, D;
};

int relu_norm_backward_blocks(int64_t pixels);

// X: the activations' storage type; T: float (double for double X) for the affine, the scale
// and the statistics. scale may be null.
template <typename X, typename T>
void launch_relu_norm_forward(const X* x, const T* scale, const T* weight, const T* bias, NormDims d, double eps,
                              X* out, T* mean, T* rstd, void* stream);

// partials [blocks, 2D] scratch; grad_weight, grad_bias [D] their block sums.
template <typename X, typename T>
void launch_relu_norm_backward(const X* grad_out, const X* x, const T* scale, const T* weight, const T* mean,
                               const T* rstd, NormDims d, X* grad_x, T* partials, int blocks, T* grad_weight,
                               T* grad_bias, void* stream);

}  // namespace featup
}  // namespace tiger

#pragma once
// tiger::group_norm — GroupNorm with an optional fused SiLU (the diffusion models' norm + act).
//
//   x [N, C, H, W], G groups of D = C / G channels, optionally shifted per (n, c) first by an
//   input bias (a preceding convolution's bias, plus a ResNet block's time embedding, folded in:
//   x ← x + ib[n, c], float32 [N, C]; the sum is never written); per (n, g) over the D·H·W elements:
//     mean[n, g], rstd[n, g] = 1 / sqrt(var[n, g] + eps)     (biased variance; float32 [N, G])
//     z = (x − mean)·rstd·w[c] + b[c]                          (w = 1, b = 0 when absent)
//     y = silu ? z·σ(z) : z                                    (x's dtype and memory format)
//
// Backward (group_norm_backward), with x̂ = (x − mean)·rstd and dz = dy·σ(z)(1 + z(1 − σ(z)))
// (z recomputed from x, mean and rstd; dz = dy without SiLU), M = D·H·W:
//   c1[n, g] = Σ_{c∈g, p} w[c]·dz / M,   c2[n, g] = Σ_{c∈g, p} w[c]·dz·x̂ / M
//   dx = rstd·(w[c]·dz − c1 − x̂·c2) (+ residual_grad),   dw[c] = Σ_{n, p} dz·x̂,   db[c] = Σ_{n, p} dz.
// residual_grad (optional, like x): the gradient x receives through another path (a ResNet
// block's shortcut), added before dx is rounded: the sum costs no pass of its own.
//
// The CUDA launchers take raw pointers (no torch headers in the .cu). Layouts: NCHW
// (contiguous) or NHWC (channels-last); per-(n, c, chunk) partials live in caller-allocated
// float32 workspaces sized by plan_chunks, so nothing synchronises with the host.
#include <cstdint>
#include <initializer_list>

namespace tiger {
namespace group_norm {

struct Dims {
  int64_t N, C, HW, G;
  bool nhwc;
};

// Blocks of the walking kernels the grid is planned for, per SM of the current device: the
// forward's apply and statistics run four blocks per SM (one wave); the backward's reduction and
// input gradient kBackwardBlocksPerSm (their launch bounds) in kBackwardWaves waves. A grid that is
// not a whole number of waves leaves its last wave at a fraction of the bandwidth these long
// walks are bound by. Measured on the H100 (group_norm_backward_occupancy_variants_h100.txt): 3
// blocks per SM (the folded constants fit 80 registers) in 1, 2 or 3 waves, and 4 in one, were
// slower than 2 in 2 on the VAE's 128²-512² maps (4x128x512² 484 us against 500-559).
constexpr int kForwardBlocksPerSm = 4;
constexpr int kBackwardBlocksPerSm = 2;
constexpr int kBackwardWaves = 2;

// Row chunks per slice for a grid of about blocks_per_sm blocks per SM (resident blocks x waves):
// the partial buffers hold N·C·chunks (NHWC) or N·C·chunks·vector_width (NCHW) floats each.
int64_t plan_chunks(const Dims& d, int vector_width, int blocks_per_sm);

// Affine parameters: dtype of x, or float32 (params_float); null = absent (w = 1, b = 0).
// input_bias: float32 [N, C] added to x before everything else; null = absent.
struct Params {
  const void* weight;
  const void* bias;
  bool params_float;
  const float* input_bias;
  int64_t input_bias_stride;  // elements between the rows of input_bias (0: one [C] row for every n)
};

// mean/rstd [N, G]; partial_mean/partial_m2 [N·C·chunks] workspaces; y like x. The three-kernel walk;
// the caller tries launch_forward_small first.
template <typename T>
void launch_forward(const T* x, Params p, const Dims& d, float eps, bool silu, int64_t chunks,
                    float* partial_mean, float* partial_m2, float* mean, float* rstd, T* y, int vector_width,
                    void* stream);

// The forward in one launch for channels-last maps whose (sample, channel block) fits one block's
// registers (compute capability 9.0 and up; group_norm_small_cuda.cu): same outputs, no partial
// workspaces. Returns false, launching nothing, where it does not apply.
template <typename T>
bool launch_forward_small(const T* x, Params p, const Dims& d, float eps, bool silu, float* mean, float* rstd, T* y,
                          int vector_width, void* stream);

// The input gradient in one launch (no parameter gradients: nothing but dx is written) for
// channels-last maps that give most SMs a (sample, channel block) and whose x and dy fit L2
// (group_norm_small_cuda.cu): the same formula as launch_backward. Returns false, launching
// nothing, where it does not apply.
template <typename T>
bool launch_backward_small(const T* dy, const T* x, Params p, const Dims& d, const float* mean, const float* rstd,
                           bool silu, const T* residual, T* dx, int vector_width, void* stream);

// sum_dz/sum_dzx [N, C] (for dw, db) and c1/c2 [N, G] are outputs; partial_* [N·C·chunks] workspaces;
// residual (like x, may be null) is added to dx.
template <typename T>
void launch_backward(const T* dy, const T* x, Params p, const Dims& d, const float* mean, const float* rstd,
                     bool silu, int64_t chunks, float* partial_dz, float* partial_dzx, float* sum_dz,
                     float* sum_dzx, float* c1, float* c2, const T* residual, T* dx, int vector_width, void* stream);

}  // namespace group_norm
}  // namespace tiger

namespace tiger {
namespace group_norm {

constexpr int kThreads = 256;   // threads of the walking kernels
constexpr int kMaxCols = 64;    // vector columns one block row covers per pass

// 16-byte vectors when every pointer is aligned and the contiguous run (C for NHWC, H·W for
// NCHW) is a multiple of the vector; otherwise scalar.
inline int choose_vector_width(const Dims& d, int elem_size, std::initializer_list<const void*> ptrs) {
  const int v = 16 / elem_size;
  if ((d.nhwc ? d.C : d.HW) % v != 0) return 1;
  for (const void* p : ptrs)
    if (p != nullptr && reinterpret_cast<uintptr_t>(p) % 16 != 0) return 1;
  return v;
}

}  // namespace group_norm
}  // namespace tiger

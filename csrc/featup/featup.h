#pragma once
// tiger::jittered_window_attention — FeatUp's attention downsampler applied to jittered copies
// of one feature map, without materialising the copies.
//
//   features  [H, W, C]     the blurred high-resolution map (channels last)
//   logit_map [H, W]        the attention logit of every source pixel (the Linear on the features)
//   coord_y   [J, Ho]       source row (pixel units) read by row y of jitter j's copy
//   coord_x   [J, Wo]       source column read by column x of jitter j's copy
//   w, b      [K, K]        the downsampler's logit scale and bias
//   mask      [J, FH, FW]   per-(jitter, cell) logit multiplier (FeatUp's logit dropout; 1 = kept)
//   stride_h, stride_w      window strides; cell (i, l) covers rows i*stride_h + [0, K) and
//                           columns l*stride_w + [0, K) of the jittered copy
//
// The jittered copy is bilinear and separable: X_j[y, x] = sum over the two rows and two columns
// around (coord_y[j, y], coord_x[j, x]) (clamped to [0, H-1] x [0, W-1]; FeatUp's reflection is
// applied by the caller to the coordinates) of their bilinear weights times the source
// (grid_sample with align_corners=True: a tap past the last row/column has weight 0 and is skipped).
//   z[j, i, l, p]   = X_j(logit_map)[window pixel p] * mask[j, i, l] * w[p] + b[p]
//   attn[j, i, l,:] = softmax_p z[j, i, l, :]
//   out[j, i, l, c] = sum_p attn[j, i, l, p] * X_j(features)[window pixel p, c]
// Outputs: out [J, FH, FW, C] and attn [J, FH, FW, K*K] (saved for the backward).
//
// Backward (jittered_window_attention_backward), g = grad_out [J, FH, FW, C]:
//   ga[p]  = sum_c g[c] X_j(features)[p, c];  gz[p] = attn[p] (ga[p] - sum_q attn[q] ga[q])
//   grad_b[p] = sum_cells gz[p];  grad_w[p] = sum_cells gz[p] * mask * X_j(logit_map)[p]
//   grad_logit_map = bilinear transpose of gz[p] * mask * w[p];
//   grad_features  = bilinear transpose of g[c] * attn[p].
//
// CUDA path: every cell's window reads a source tile of at most (K + 3)^2 pixels, which holds when
// consecutive rows/columns of a copy read source coordinates at most one pixel apart (FeatUp's
// zoom >= 1); a cell whose footprint is larger gets NaN outputs. The CPU path has no such limit.
//
// CUDA kernel variants (argument `variant`; the CPU kernels are the reference of all of them and
// only check the name). Each adds to the one before it and computes the same function up to float
// rounding:
//   baseline           one block per cell; each cell dots g with the features of its whole tile
//                      (~(K+3)^2 * C reads per cell) and adds the logit map's gradient with K*K*4
//                      global atomics per cell.
//   shared_scatter     the cell's logit-map gradient summed in a shared tile first: at most (K+3)^2
//                      global atomics per cell, one per touched source pixel.
//   pixel_dots         the backward's dots of g with the features computed pixel-major: a block
//                      stages one row segment of the features in shared memory and dots it with g
//                      of every cell whose tile covers it (each feature read once per backward
//                      instead of once per covering cell).
//   staged_tiles       the features' gradient reads the covering tiles' values at its pixels from
//                      shared memory (staged per round of listed cells) instead of testing and
//                      loading them per channel; the forward computes 4 neighbouring cells of a
//                      window row per block (2 in float64) and reads the union of their tiles once.
//   staged_tiles_bf16  the attention's reads of the features as bfloat16, accumulated in float32
//                      (float32 features only): the forward reads a bfloat16 copy, the backward's
//                      dots round each feature as they stage it (the same values, no copy); the
//                      features' own gradient does not read them.
#include <cstdint>

namespace tiger {
namespace featup {

constexpr int kMaxKernel = 32;  // K <= 32 on CUDA (FeatUp's downsampler uses 29)

// The CUDA kernel variants (above); the names in the order of the values.
enum WindowVariant : int { kBaseline = 0, kSharedScatter = 1, kPixelDots = 2, kStagedTiles = 3, kStagedTilesBf16 = 4 };
constexpr const char* kWindowVariantNames[] = {"baseline", "shared_scatter", "pixel_dots", "staged_tiles",
                                               "staged_tiles_bf16"};
constexpr int kWindowVariants = 5;
inline bool uses_pixel_dots(int variant) { return variant >= kPixelDots; }
inline bool uses_bf16_features(int variant) { return variant == kStagedTilesBf16; }
inline bool uses_grouped_forward(int variant) { return variant >= kStagedTiles; }

// pixel_dots (and after) stages one row segment of at least one pixel's C channels in shared memory: C * sizeof(T)
// (plus one element of padding) must fit this many bytes.
constexpr int64_t kDotStageBytes = 40960;

struct WindowDims {
  int64_t H, W, C, J, Ho, Wo, FH, FW, K, SH, SW;
};

// features_bf16: the features as a contiguous bfloat16 [H, W, C] copy, read instead of `features`
// by variant kStagedTilesBf16 (float only); null otherwise.
template <typename scalar_t>
void launch_window_forward(const scalar_t* features, const scalar_t* logit_map, const scalar_t* coord_y,
                           const scalar_t* coord_x, const scalar_t* w, const scalar_t* b, const scalar_t* mask,
                           WindowDims d, int variant, const void* features_bf16, scalar_t* out, scalar_t* attn,
                           void* stream);

// Per-cell part of the backward: gz and gz * mask * logit per cell and window pixel ([J*FH*FW, K*K]
// each, summed over cells by the caller), grad_logit_map (accumulated: zeroed by the caller), and
// the cells' source tiles (attention pushed through the bilinear weights, [J*FH*FW, T*T] with
// T = K + 3) and tile origins ([J*FH*FW, 2] row, column) for launch_window_grad_features.
// Variants from kPixelDots on need scratch: extents [J*FH*FW, 4] int32 and dots [J*FH*FW, T*T]
// (null for the others); kStagedTilesBf16 rounds the features to bfloat16 as its dots read them.
template <typename scalar_t>
void launch_window_backward_cells(const scalar_t* grad_out, const scalar_t* features, const scalar_t* logit_map,
                                  const scalar_t* coord_y, const scalar_t* coord_x, const scalar_t* w,
                                  const scalar_t* mask, const scalar_t* attn, WindowDims d, int variant,
                                  int32_t* extents, scalar_t* dots, scalar_t* gz,
                                  scalar_t* gz_logit, scalar_t* grad_logit_map, scalar_t* tiles,
                                  int32_t* origins, void* stream);

// grad_features [H, W, C] gathered from the cells' tiles (no atomics).
template <typename scalar_t>
void launch_window_grad_features(const scalar_t* grad_out, const scalar_t* tiles, const int32_t* origins,
                                 WindowDims d, int variant, scalar_t* grad_features, void* stream);

}  // namespace featup
}  // namespace tiger

#pragma once
// Raw-pointer launchers of the CUDA rasterization kernels (no torch headers).
// Shapes and semantics as in raster.h (views images stacked along the rows). One thread block per tile, one thread per pixel (two
// in the float32 backward of up to 16 channels); channels are processed in register blocks
// whose size is a template parameter (up to 64 channels per block in float32), so any C runs
// in one launch.
#include <cuda_runtime_api.h>
#include <stdint.h>

namespace tiger {

// Storage type of the per-Gaussian channels (colors): the accumulation type T itself,
// or 16-bit floats (only with T = float), converted at load.
enum class ColorStorage : int { kSame = 0, kHalf = 1, kBFloat16 = 2 };

template <typename T>
struct RasterLaunch {
  const T* means2d;
  const T* conics;
  const T* opacities;
  const T* depths;  // may be null for the features-only backward
  const int64_t* tile_offsets;
  const int32_t* ids;
  // [N] or null (all): the backward kernels add gradients only for these Gaussians (raster.h)
  const bool* trainable;
  // [tiles] or null (identity): block b draws tile tile_order[b] (raster.h: heaviest first)
  const int32_t* tile_order;
  // Each warp skips the list entries whose cutoff ellipse reaches none of its pixel centres
  // (raster_kernels.cuh, WarpSpan): the values are those of the walk without it (raster.h).
  bool warp_cull;
  int width, height, tile_size, tiles_x, tiles_y;  // of one image
  // Images drawn (raster.h): one block per tile of views * tiles_y * tiles_x; tile t belongs
  // to image t / (tiles_x * tiles_y), whose pixels are rows image * height ... of the outputs.
  int views;
  int channels;
  T alpha_max, alpha_threshold, t_min;
};

// channel_block (float32: 64 or 32, the largest register block of channels; float64 always
// runs 8) and pixels_per_thread (float32 backward: 2 where it applies, else 1) are the ops'
// kernel choices (raster.h), checked by the glue.

// Outputs: color [H,W,C], alpha, depth (accumulated), n_contrib, transmittance [H,W] (=).
template <typename T>
cudaError_t rasterize_forward_cuda_launch(const RasterLaunch<T>& a, const void* colors,
                                          ColorStorage storage, const T* background, T* out_color,
                                          T* out_alpha, T* out_depth, int32_t* out_count,
                                          T* out_trans, int channel_block, cudaStream_t stream);

// Gradient outputs must be zero-filled (accumulated with atomics). v_geom [N, 8] holds per
// Gaussian d/d(u, v, conic a, b, c, opacity, depth) and a pad, so one warp's atomics for a
// Gaussian hit one 32-byte sector; v_colors is in T whatever the colour storage;
// v_bg_tiles [tiles, C] holds one partial row per tile.
template <typename T>
cudaError_t rasterize_backward_cuda_launch(const RasterLaunch<T>& a, const void* colors,
                                           ColorStorage storage, const T* background,
                                           const T* trans, const int32_t* n_contrib,
                                           const T* v_color, const T* v_alpha, const T* v_depth,
                                           T* v_geom, T* v_colors, T* v_bg_tiles,
                                           int channel_block, int pixels_per_thread,
                                           cudaStream_t stream);

// Features-only backward (front to back, no division): v_colors [N,C] (zero-filled) and
// v_bg_tiles [tiles, C].
template <typename T>
cudaError_t rasterize_backward_colors_cuda_launch(const RasterLaunch<T>& a,
                                                  const int32_t* n_contrib, const T* v_color,
                                                  T* v_colors, T* v_bg_tiles, int channel_block,
                                                  cudaStream_t stream);

// order [tiles]: a permutation of the tiles, longest list first within a factor of sqrt(2) (lists
// of one half-octave of lengths in no fixed order); tile_offsets [tiles + 1].
cudaError_t heavy_first_order_cuda_launch(const int64_t* tile_offsets, int tiles, int32_t* order,
                                          cudaStream_t stream);

}  // namespace tiger

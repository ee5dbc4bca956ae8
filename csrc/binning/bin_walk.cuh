#pragma once
// Pieces both CUDA binning paths share (binning_tiles_cuda.cu, binning_global_cuda.cu): the
// block size, a Gaussian's bounding box of candidate tiles and its exact ellipse-tile test
// (tile_touches from common/raster_math.h: a tile is listed only where the ellipse reaches
// alpha >= threshold at one of its pixel centres), and a grid that fills the GPU once.
#include <cuda_runtime_api.h>
#include <stdint.h>

#include "binning_cuda.h"
#include "common/cuda_helpers.cuh"
#include "common/raster_math.h"

namespace tiger {
// Named (not anonymous) so that every binning kernel's name holds "bin_cuda": the sanitizer's
// racecheck selects them by that (benchmarks/gpu/binning.sh).
namespace bin_cuda {

constexpr int kThreads = 256;
constexpr int kWarps = kThreads / 32;
// A Gaussian with at most kSmallTiles candidate (bounding-box) tiles is walked by one thread:
// no thread of a warp does more than kSmallTiles tests, and there is nothing to coordinate.
// The larger ones are listed and walked by warps (or blocks).
constexpr int kSmallTiles = 32;

template <typename T>
__device__ __forceinline__ TileRect rect_of(int64_t i, const T* means2d, const int32_t* radii,
                                            const BinGeometry& g) {
  const int32_t rx = radii[2 * i], ry = radii[2 * i + 1];
  if (rx <= 0 || ry <= 0) return {0, 0, 0, 0};
  return tile_rect(means2d[2 * i], means2d[2 * i + 1], rx, ry, g.tile_size, g.tiles_x, g.tiles_y);
}

// The first tile of Gaussian i's image: the images' tile grids follow one another
// (bin_gaussians(views=V)); below 2^31 as the glue checks the total. One image (per_view = n):
// 0 without the 64-bit division.
template <typename T>
__device__ __forceinline__ int view_first_tile(int64_t i, const BinInputs<T>& in,
                                               const BinGeometry& g) {
  if (in.per_view >= in.n) return 0;
  return int(i / in.per_view * (int64_t(g.tiles_x) * g.tiles_y));
}

// The exact test of one Gaussian, loaded once.
template <typename T>
struct TileTester {
  T u, v, ca, cb, cc, qcut;
  TileRect r;
  int first_tile;  // the first tile of the Gaussian's image: tile ids are first_tile + local id

  __device__ void load(int64_t i, const BinInputs<T>& in, const BinGeometry& g) {
    u = in.means2d[2 * i];
    v = in.means2d[2 * i + 1];
    ca = in.conics[3 * i];
    cb = in.conics[3 * i + 1];
    cc = in.conics[3 * i + 2];
    qcut = cutoff_quadratic<T>(in.opacities[i], in.alpha_threshold);
    r = rect_of(i, in.means2d, in.radii, g);
    first_tile = view_first_tile(i, in, g);
  }
  __device__ bool touches(int tx, int ty, const BinGeometry& g) const {
    const int px0 = tx * g.tile_size, py0 = ty * g.tile_size;
    return tile_touches<T>(u, v, ca, cb, cc, qcut, px0, min(px0 + g.tile_size, g.width), py0,
                           min(py0 + g.tile_size, g.height));
  }
  // The tile id of the Gaussian's image's tile (tx, ty).
  __device__ __forceinline__ int tile_id(int tx, int ty, const BinGeometry& g) const {
    return first_tile + ty * g.tiles_x + tx;
  }
  // Candidate k (row-major in the box; k < count() < 2^31): its tile if touched, else -1.
  __device__ int test(int k, const BinGeometry& g) const {
    const int w = r.width();
    const int row = k / w, col = k - row * w;
    const int tx = r.x0 + col, ty = r.y0 + row;
    return touches(tx, ty, g) ? tile_id(tx, ty, g) : -1;
  }
};

}  // namespace bin_cuda

// A grid that fills the GPU once (kernels that loop over a work list).
inline cudaError_t bin_full_grid(int& blocks) {
  int dev = 0, sms = 0;
  cudaError_t err = cudaGetDevice(&dev);
  if (err == cudaSuccess) err = cudaDeviceGetAttribute(&sms, cudaDevAttrMultiProcessorCount, dev);
  blocks = (sms > 0 ? sms : 1) * (2048 / bin_cuda::kThreads);
  return err;
}

}  // namespace tiger

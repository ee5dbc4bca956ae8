// CUDA kernels of the components family (raw pointers, no torch headers).
//
// Block-based union-find: (1) each 32x32 tile is labelled in shared memory (union-find with
// atomicMin, so a tree's root is its smallest pixel) and its local component sizes are counted
// with shared atomics; (2) only the pixels on tile borders join their neighbours in other tiles,
// by the same union-find on the global labels; (3) every pixel finds its root (path compression)
// and each tile-local root adds its local size to its global root: one global atomic per tile
// and component instead of one per pixel; then every pixel reads its global root through its
// tile-local root. Uniform tiles (all inside or all outside the mask: most tiles of SAM's masks)
// skip the shared-memory union-find. Each pass reads or writes every pixel once, so the cost is
// a few passes over M x H x W int32 plus finds only from tile-local roots.
#include <cuda_runtime.h>

#include "components/components.h"

namespace tiger {
namespace components {
namespace {

constexpr int kTile = 32;  // tile side; one thread per pixel, 1024 threads per block

__device__ __forceinline__ int find_root(volatile int* parent, int a) {
  int p = parent[a];
  while (p != a) {
    a = p;
    p = parent[a];
  }
  return a;
}

// Union of the sets of a and b; the larger root is linked below the smaller with atomicMin, and
// when another thread relinked a root first the walk continues from where it now points.
__device__ void unite(int* parent, int a, int b) {
  volatile int* vp = parent;
  while (true) {
    a = find_root(vp, a);
    b = find_root(vp, b);
    if (a == b) return;
    if (a < b) {
      const int old = atomicMin(parent + b, a);
      if (old == b) return;
      b = old;
    } else {
      const int old = atomicMin(parent + a, b);
      if (old == a) return;
      a = old;
    }
  }
}

__global__ void tile_label_kernel(const bool* __restrict__ masks, bool invert, int h, int w, int tiles_x,
                                  int* __restrict__ labels, int* __restrict__ local_size) {
  __shared__ int parent[kTile * kTile];
  __shared__ int count[kTile * kTile];
  const int tx = threadIdx.x, ty = threadIdx.y, t = ty * kTile + tx;
  const int x0 = (blockIdx.x % tiles_x) * kTile, y0 = (blockIdx.x / tiles_x) * kTile;
  const int x = x0 + tx, y = y0 + ty;
  const long long base = static_cast<long long>(blockIdx.y) * h * w;
  const bool inside = x < w && y < h;
  const bool fg = inside && (masks[base + static_cast<long long>(y) * w + x] != invert);
  const int n_fg = __syncthreads_count(fg), n_inside = __syncthreads_count(inside);
  const long long p = base + static_cast<long long>(y) * w + x;
  if (n_fg == 0 || n_fg == n_inside) {  // a uniform tile (most of them): one component or none
    if (inside) {
      labels[p] = n_fg ? y0 * w + x0 : -1;
      local_size[p] = (n_fg && t == 0) ? n_fg : 0;
    }
    return;
  }
  parent[t] = fg ? t : -1;
  count[t] = 0;
  __syncthreads();
  if (fg) {  // backward neighbours inside the tile: left, up-left, up, up-right
    if (tx > 0 && parent[t - 1] >= 0) unite(parent, t, t - 1);
    if (ty > 0) {
      const int up = t - kTile;
      if (tx > 0 && parent[up - 1] >= 0) unite(parent, t, up - 1);
      if (parent[up] >= 0) unite(parent, t, up);
      if (tx + 1 < kTile && parent[up + 1] >= 0) unite(parent, t, up + 1);
    }
  }
  __syncthreads();
  const int root = fg ? find_root(parent, t) : -1;
  if (fg) atomicAdd(&count[root], 1);
  __syncthreads();
  if (!inside) return;
  labels[p] = fg ? (y0 + root / kTile) * w + x0 + root % kTile : -1;
  local_size[p] = (fg && root == t) ? count[t] : 0;
}

// Pixels whose backward neighbours lie in another tile join them in the global forest.
__global__ void border_merge_kernel(int h, int w, int tiles_x, int* __restrict__ labels) {
  const int tx = threadIdx.x, ty = threadIdx.y;
  const bool left = tx == 0, right = tx == kTile - 1, top = ty == 0;
  if (!(left || right || top)) return;
  const int x = (blockIdx.x % tiles_x) * kTile + tx, y = (blockIdx.x / tiles_x) * kTile + ty;
  if (x >= w || y >= h) return;
  int* lab = labels + static_cast<long long>(blockIdx.y) * h * w;
  const int p = y * w + x;
  if (lab[p] < 0) return;
  if (left && x > 0 && lab[p - 1] >= 0) unite(lab, p, p - 1);
  if (y > 0) {
    const int up = p - w;
    if ((left || top) && x > 0 && lab[up - 1] >= 0) unite(lab, p, up - 1);
    if (top && lab[up] >= 0) unite(lab, p, up);
    if ((right || top) && x + 1 < w && lab[up + 1] >= 0) unite(lab, p, up + 1);
  }
}

// Tile-local roots find their global root, add their sizes to it and point straight at it.
// (Border merging only relinks roots, so every other pixel still points at its tile-local root.)
__global__ void local_roots_kernel(long long total, int hw, int* __restrict__ labels,
                                   const int* __restrict__ local_size, int* __restrict__ sizes) {
  const long long i = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= total) return;
  const int own = local_size[i];
  if (own == 0) return;
  const long long base = (i / hw) * hw;
  int* lab = labels + base;
  const int root = find_root(lab, static_cast<int>(i - base));
  atomicAdd(sizes + base + root, own);
  lab[i - base] = root;  // a valid shortcut for concurrent finds: root is an ancestor
}

// Every pixel takes its tile-local root's global root: two reads.
__global__ void final_labels_kernel(long long total, int hw, int* __restrict__ labels) {
  const long long i = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= total) return;
  const int local = labels[i];
  if (local < 0) return;
  const long long base = (i / hw) * hw;
  labels[i] = labels[base + local];
}

__device__ __forceinline__ unsigned long long size_key(int size, int root) {
  // larger size first, then smaller root: the largest component, ties to the first in raster order
  return (static_cast<unsigned long long>(size) << 32) | static_cast<unsigned int>(0x7fffffff - root);
}

__global__ void root_stats_kernel(long long total, int hw, const int* __restrict__ labels,
                                  const int* __restrict__ sizes, long long area, bool* __restrict__ changed,
                                  int* __restrict__ has_big, unsigned long long* __restrict__ best) {
  const long long i = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= total) return;
  const long long m = i / hw;
  const int p = static_cast<int>(i - m * hw);
  if (labels[i] != p) return;  // roots only
  const int s = sizes[i];
  if (s < area) changed[m] = true;
  else has_big[m] = 1;
  atomicMax(best + m, size_key(s, p));
}

__global__ void apply_kernel(long long total, int hw, const bool* __restrict__ masks, bool holes,
                             const int* __restrict__ labels, const int* __restrict__ sizes, long long area,
                             const int* __restrict__ has_big, const unsigned long long* __restrict__ best,
                             bool* __restrict__ out) {
  const long long i = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= total) return;
  const long long m = i / hw, base = m * hw;
  const int root = labels[i];
  if (holes) {
    out[i] = masks[i] || (root >= 0 && sizes[base + root] < area);
  } else {
    const bool keep_largest = !has_big[m] && root >= 0 && best[m] == size_key(sizes[base + root], root);
    out[i] = root >= 0 && (sizes[base + root] >= area || keep_largest);
  }
}

constexpr int kThreads = 256;

inline unsigned int blocks_for(long long n) { return static_cast<unsigned int>((n + kThreads - 1) / kThreads); }

}  // namespace

void launch_label(const bool* masks, bool invert, int64_t m, int64_t h, int64_t w, int32_t* labels,
                  int32_t* local_size, int32_t* sizes, void* stream) {
  if (m == 0 || h == 0 || w == 0) return;
  cudaStream_t s = static_cast<cudaStream_t>(stream);
  const int tiles_x = static_cast<int>((w + kTile - 1) / kTile), tiles_y = static_cast<int>((h + kTile - 1) / kTile);
  const dim3 block(kTile, kTile);
  for (int64_t m0 = 0; m0 < m; m0 += 65535) {  // gridDim.y limit
    const int64_t mc = m - m0 < 65535 ? m - m0 : 65535;
    const int64_t off = m0 * h * w;
    const dim3 grid(tiles_x * tiles_y, static_cast<unsigned int>(mc));
    tile_label_kernel<<<grid, block, 0, s>>>(masks + off, invert, int(h), int(w), tiles_x, labels + off,
                                             local_size + off);
    border_merge_kernel<<<grid, block, 0, s>>>(int(h), int(w), tiles_x, labels + off);
  }
  const long long total = static_cast<long long>(m) * h * w;
  local_roots_kernel<<<blocks_for(total), kThreads, 0, s>>>(total, int(h * w), labels, local_size, sizes);
  final_labels_kernel<<<blocks_for(total), kThreads, 0, s>>>(total, int(h * w), labels);
}

void launch_small_region_step(const bool* masks, bool holes, int64_t m, int64_t h, int64_t w,
                              const int32_t* labels, const int32_t* sizes, int64_t area_threshold,
                              bool* changed, int32_t* has_big, unsigned long long* best, bool* out,
                              void* stream) {
  if (m == 0 || h == 0 || w == 0) return;
  cudaStream_t s = static_cast<cudaStream_t>(stream);
  const long long total = static_cast<long long>(m) * h * w;
  root_stats_kernel<<<blocks_for(total), kThreads, 0, s>>>(total, int(h * w), labels, sizes, area_threshold,
                                                           changed, has_big, best);
  apply_kernel<<<blocks_for(total), kThreads, 0, s>>>(total, int(h * w), masks, holes, labels, sizes,
                                                      area_threshold, has_big, best, out);
}

}  // namespace components
}  // namespace tiger

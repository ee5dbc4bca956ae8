#pragma once
// Raw-pointer launchers of the CUDA projection kernels (no torch headers).
// Shapes as in projection.h; viewmat [4,4] and K [3,3] are device pointers, so no
// host synchronisation is needed to read the camera.
#include <cuda_runtime_api.h>
#include <stdint.h>

namespace tiger {

template <typename T>
struct ProjectLaunch {
  const T *means, *quats, *scales, *opacities, *viewmat, *K;
  int64_t n;
  int width, height;
  T eps2d, near_plane, far_plane, alpha_threshold;
  bool antialiased;
};

// Every output row is written (zeros for culled Gaussians): no zero fill needed.
template <typename T>
cudaError_t project_gaussians_cuda_launch(const ProjectLaunch<T>& a, T* means2d, T* conics,
                                          T* depths, T* opac_out, int32_t* radii,
                                          cudaStream_t stream);

// Row strides (in elements) of the incoming gradients, whose last dimension is contiguous: the
// rasterizer's backward hands them over as views of one [N, 8] buffer (stride 8), uncopied.
struct VRowStrides {
  int64_t means2d, conics, depths, opacities;
};

// v_cam [N,16] (optional, may be null): per-Gaussian rows (R 3x3 | t) x 3 rows as a 3x4
// block, then fx, fy, cx, cy; summed by the caller. Per-Gaussian outputs are written (=).
template <typename T>
cudaError_t project_gaussians_backward_cuda_launch(const ProjectLaunch<T>& a, const int32_t* radii,
                                                   const T* v_means2d, const T* v_conics,
                                                   const T* v_depths, const T* v_opac,
                                                   VRowStrides strides, T* g_means, T* g_quats,
                                                   T* g_scales, T* g_opac, T* v_cam,
                                                   cudaStream_t stream);

}  // namespace tiger

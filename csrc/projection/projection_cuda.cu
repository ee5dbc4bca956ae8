// CUDA kernels of the projection ops: one thread per Gaussian, the same
// project_gaussian / project_gaussian_vjp as the CPU kernels.
#include "common/cuda_helpers.cuh"
#include "common/projection_math.h"
#include "projection_cuda.h"

namespace tiger {
namespace {

template <typename T>
__device__ Camera<T> load_camera(const T* v, const T* k, int width, int height) {
  Camera<T> cam;
#pragma unroll
  for (int i = 0; i < 3; ++i)
#pragma unroll
    for (int j = 0; j < 3; ++j) cam.R.m[i][j] = v[i * 4 + j];
  cam.t = {v[3], v[7], v[11]};
  cam.fx = k[0];
  cam.fy = k[4];
  cam.cx = k[2];
  cam.cy = k[5];
  cam.width = width;
  cam.height = height;
  return cam;
}

// Extents are stored as int32 pixels; huge Gaussians saturate instead of overflowing.
template <typename T>
__global__ void project_kernel(ProjectLaunch<T> a, T* means2d, T* conics, T* depths, T* opac_out,
                               int32_t* radii) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= a.n) return;
  const Camera<T> cam = load_camera(a.viewmat, a.K, a.width, a.height);
  const ProjectOptions<T> opt{a.eps2d, a.near_plane, a.far_plane, a.alpha_threshold, a.antialiased};
  Projected<T> pr;
  if (project_gaussian<T>(a.means + 3 * i, a.quats + 4 * i, a.scales + 3 * i, a.opacities[i], cam,
                          opt, pr)) {
    store_projected(pr, i, means2d, conics, depths, opac_out, radii);
    return;
  }
  // Culled: zeros, written here so that the outputs need no zero fill before the launch.
  means2d[2 * i] = means2d[2 * i + 1] = T(0);
  conics[3 * i] = conics[3 * i + 1] = conics[3 * i + 2] = T(0);
  depths[i] = opac_out[i] = T(0);
  radii[2 * i] = radii[2 * i + 1] = 0;
}

template <typename T>
__global__ void project_backward_kernel(ProjectLaunch<T> a, const int32_t* radii,
                                        const T* v_means2d, const T* v_conics, const T* v_depths,
                                        const T* v_opac, VRowStrides st, T* g_means, T* g_quats,
                                        T* g_scales, T* g_opac, T* v_cam) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= a.n) return;
  if (radii[2 * i] == 0) {  // culled: zero gradients (the outputs are not zero-filled)
#pragma unroll
    for (int k = 0; k < 3; ++k) g_means[3 * i + k] = g_scales[3 * i + k] = T(0);
#pragma unroll
    for (int k = 0; k < 4; ++k) g_quats[4 * i + k] = T(0);
    g_opac[i] = T(0);
    if (v_cam)
#pragma unroll
      for (int k = 0; k < 16; ++k) v_cam[16 * i + k] = T(0);
    return;
  }
  const Camera<T> cam = load_camera(a.viewmat, a.K, a.width, a.height);
  const ProjectOptions<T> opt{a.eps2d, T(0), T(0), T(0), a.antialiased};
  ProjectionGrads<T> g{};
  g.R = mat3_zero<T>();
  project_gaussian_vjp<T>(a.means + 3 * i, a.quats + 4 * i, a.scales + 3 * i, a.opacities[i], cam,
                          opt, v_means2d[st.means2d * i], v_means2d[st.means2d * i + 1],
                          v_conics[st.conics * i], v_conics[st.conics * i + 1],
                          v_conics[st.conics * i + 2], v_depths[st.depths * i],
                          v_opac[st.opacities * i], g);
#pragma unroll
  for (int k = 0; k < 3; ++k) {
    g_means[3 * i + k] = g.mean[k];
    g_scales[3 * i + k] = g.scale[k];
  }
#pragma unroll
  for (int k = 0; k < 4; ++k) g_quats[4 * i + k] = g.quat[k];
  g_opac[i] = g.opacity;
  if (v_cam) {
    T* c = v_cam + 16 * i;
#pragma unroll
    for (int r = 0; r < 3; ++r) {
#pragma unroll
      for (int k = 0; k < 3; ++k) c[r * 4 + k] = g.R.m[r][k];
      c[r * 4 + 3] = g.t[r];
    }
#pragma unroll
    for (int k = 0; k < 4; ++k) c[12 + k] = g.K[k];
  }
}

constexpr int kThreads = 256;

}  // namespace

template <typename T>
cudaError_t project_gaussians_cuda_launch(const ProjectLaunch<T>& a, T* means2d, T* conics,
                                          T* depths, T* opac_out, int32_t* radii,
                                          cudaStream_t stream) {
  if (a.n == 0) return cudaSuccess;
  project_kernel<T><<<cuda::ceil_div(a.n, kThreads), kThreads, 0, stream>>>(a, means2d, conics,
                                                                            depths, opac_out, radii);
  return cudaGetLastError();
}

template <typename T>
cudaError_t project_gaussians_backward_cuda_launch(const ProjectLaunch<T>& a, const int32_t* radii,
                                                   const T* v_means2d, const T* v_conics,
                                                   const T* v_depths, const T* v_opac,
                                                   VRowStrides strides, T* g_means, T* g_quats,
                                                   T* g_scales, T* g_opac, T* v_cam,
                                                   cudaStream_t stream) {
  if (a.n == 0) return cudaSuccess;
  project_backward_kernel<T><<<cuda::ceil_div(a.n, kThreads), kThreads, 0, stream>>>(
      a, radii, v_means2d, v_conics, v_depths, v_opac, strides, g_means, g_quats, g_scales, g_opac,
      v_cam);
  return cudaGetLastError();
}

#define TIGER_INSTANTIATE(T)                                                                   \
  template cudaError_t project_gaussians_cuda_launch<T>(const ProjectLaunch<T>&, T*, T*, T*, T*, \
                                                        int32_t*, cudaStream_t);               \
  template cudaError_t project_gaussians_backward_cuda_launch<T>(                              \
      const ProjectLaunch<T>&, const int32_t*, const T*, const T*, const T*, const T*,            \
      VRowStrides, T*, T*, T*, T*, T*, cudaStream_t);
TIGER_INSTANTIATE(float)
TIGER_INSTANTIATE(double)
#undef TIGER_INSTANTIATE

}  // namespace tiger

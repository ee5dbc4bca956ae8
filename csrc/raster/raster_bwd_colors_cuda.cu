// CUDA features-only backward (front to back, colours and background only).
#include "raster_kernels.cuh"

namespace tiger {
namespace {
using namespace raster_cuda;

// A thread holds v_color per channel (gradient terms are reduced in pieces of 32): blocks
// of 64 in float32 (the op's channel_block = 32 selects 32 for tuning), 8 in float64 (tests
// only).
template <int CB_MAX, typename T>
cudaError_t launch_colors_cb(const RasterLaunch<T>& a, const int32_t* n_contrib,
                             const T* v_color, T* v_colors, T* v_bg_tiles, cudaStream_t stream) {
  const ChannelPlan plan = plan_channels(a.channels, CB_MAX);
  const int threads = block_threads(a.tile_size);
  const int blocks = a.views * a.tiles_x * a.tiles_y;  // every image's tiles
  return dispatch_plan<CB_MAX>(plan, [&](auto m, auto t) -> cudaError_t {
    constexpr int CBM = decltype(m)::value, CBT = decltype(t)::value;
    constexpr int CBX = CBM > CBT ? CBM : CBT;
    auto kernel = backward_colors_kernel<T, CBM, CBT>;
    const size_t smem =
        size_t(threads) * (sizeof(SplatGeom<T>) + sizeof(int32_t)) + CBX * sizeof(T) + 16;
    cudaError_t err = set_smem_limit(kernel, smem);
    if (err != cudaSuccess) return err;
    kernel<<<blocks, threads, smem, stream>>>(a, n_contrib, v_color, v_colors, v_bg_tiles,
                                              plan.n_main);
    return cudaGetLastError();
  });
}
}  // namespace

template <typename T>
cudaError_t rasterize_backward_colors_cuda_launch(const RasterLaunch<T>& a,
                                                  const int32_t* n_contrib, const T* v_color,
                                                  T* v_colors, T* v_bg_tiles, int channel_block,
                                                  cudaStream_t stream) {
  if (a.tiles_x * a.tiles_y == 0) return cudaSuccess;
  if constexpr (std::is_same<T, float>::value) {
    if (channel_block == 32)
      return launch_colors_cb<32>(a, n_contrib, v_color, v_colors, v_bg_tiles, stream);
    return launch_colors_cb<64>(a, n_contrib, v_color, v_colors, v_bg_tiles, stream);
  } else {
    return launch_colors_cb<8>(a, n_contrib, v_color, v_colors, v_bg_tiles, stream);
  }
}

template cudaError_t rasterize_backward_colors_cuda_launch<float>(const RasterLaunch<float>&,
                                                                  const int32_t*, const float*,
                                                                  float*, float*, int,
                                                                  cudaStream_t);
template cudaError_t rasterize_backward_colors_cuda_launch<double>(const RasterLaunch<double>&,
                                                                   const int32_t*, const double*,
                                                                   double*, double*, int,
                                                                   cudaStream_t);

}  // namespace tiger

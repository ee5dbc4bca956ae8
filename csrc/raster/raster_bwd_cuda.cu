// CUDA rasterization backward (back to front): launcher and instantiations.
#include "raster_kernels.cuh"

namespace tiger {
namespace {
using namespace raster_cuda;

// Per channel a thread holds only v_color (the colour behind is one scalar): blocks of 64
// channels in float32, so C <= 64 walks the list once (the op's channel_block = 32 selects 32
// for tuning); 8 in float64 (tests only). Two pixels per thread where they apply
// (pixels_per_thread; the op's pixels_per_thread = 1 selects one).
template <int CB_MAX, typename T, typename TC>
cudaError_t launch_backward_cb(const RasterLaunch<T>& a, const TC* colors,
                               const BackwardIO<T>& io, int pixels_wanted, cudaStream_t stream) {
  const ChannelPlan plan = plan_channels(a.channels, CB_MAX);
  const int blocks = a.views * a.tiles_x * a.tiles_y;  // every image's tiles
  return dispatch_plan<CB_MAX>(plan, [&](auto m, auto t) -> cudaError_t {
    constexpr int CBM = decltype(m)::value, CBT = decltype(t)::value;
    constexpr int CBX = CBM > CBT ? CBM : CBT;
    auto launch = [&](auto ppt) -> cudaError_t {
      constexpr int PPT = decltype(ppt)::value;
      auto kernel = backward_kernel<T, TC, CBM, CBT, PPT>;
      const int threads = PPT == 1 ? block_threads(a.tile_size) : kTwoPixelThreads;
      const size_t batch = size_t(threads) * PPT;
      const size_t smem = batch * (sizeof(SplatGeom<T>) + CBX * sizeof(T) + sizeof(int32_t)) +
                          CBX * sizeof(T) + 16;
      cudaError_t err = set_smem_limit(kernel, smem);
      if (err != cudaSuccess) return err;
      kernel<<<blocks, threads, smem, stream>>>(a, colors, io, plan.n_main);
      return cudaGetLastError();
    };
    if constexpr (std::is_same<T, float>::value && CBX <= kTwoPixelMaxChannels) {
      if (pixels_per_thread(a, CBX, pixels_wanted) == 2) return launch(IC<2>());
    }
    return launch(IC<1>());
  });
}

template <typename T, typename TC>
cudaError_t launch_backward(const RasterLaunch<T>& a, const TC* colors, const BackwardIO<T>& io,
                            int channel_block, int pixels_wanted, cudaStream_t stream) {
  if constexpr (std::is_same<T, float>::value) {
    if (channel_block == 32) return launch_backward_cb<32>(a, colors, io, pixels_wanted, stream);
    return launch_backward_cb<64>(a, colors, io, pixels_wanted, stream);
  } else {
    return launch_backward_cb<8>(a, colors, io, pixels_wanted, stream);
  }
}
}  // namespace

template <typename T>
cudaError_t rasterize_backward_cuda_launch(const RasterLaunch<T>& a, const void* colors,
                                           ColorStorage storage, const T* background,
                                           const T* trans, const int32_t* n_contrib,
                                           const T* v_color, const T* v_alpha, const T* v_depth,
                                           T* v_geom, T* v_colors, T* v_bg_tiles,
                                           int channel_block, int pixels_per_thread,
                                           cudaStream_t stream) {
  if (a.tiles_x * a.tiles_y == 0) return cudaSuccess;
  const BackwardIO<T> io{background, trans,  n_contrib, v_color,   v_alpha,
                         v_depth,    v_geom, v_colors,  v_bg_tiles};
  if constexpr (std::is_same<T, float>::value) {
    if (storage == ColorStorage::kHalf)
      return launch_backward<T>(a, static_cast<const __half*>(colors), io, channel_block, pixels_per_thread, stream);
    if (storage == ColorStorage::kBFloat16)
      return launch_backward<T>(a, static_cast<const __nv_bfloat16*>(colors), io, channel_block, pixels_per_thread, stream);
  }
  if (storage != ColorStorage::kSame) return cudaErrorInvalidValue;
  return launch_backward<T>(a, static_cast<const T*>(colors), io, channel_block, pixels_per_thread, stream);
}

#define TIGER_INSTANTIATE(T)                                                                   \
  template cudaError_t rasterize_backward_cuda_launch<T>(                                      \
      const RasterLaunch<T>&, const void*, ColorStorage, const T*, const T*, const int32_t*,   \
      const T*, const T*, const T*, T*, T*, T*, int, int, cudaStream_t);
TIGER_INSTANTIATE(float)
TIGER_INSTANTIATE(double)
#undef TIGER_INSTANTIATE

}  // namespace tiger

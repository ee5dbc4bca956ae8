// CUDA rasterization forward: launcher and instantiations (kernels in raster_kernels.cuh).
#include "raster_kernels.cuh"

namespace tiger {
namespace {
using namespace raster_cuda;

// Largest channel block held in registers: 64 accumulators per thread in float32 (the op's
// channel_block = 32 selects 32, for tuning), 8 in float64 (tests only).
template <int CB_MAX, typename T, typename TC>
cudaError_t launch_forward_cb(const RasterLaunch<T>& a, const TC* colors, const ForwardOut<T>& out,
                              cudaStream_t stream) {
  const ChannelPlan plan = plan_channels(a.channels, CB_MAX);
  const int threads = block_threads(a.tile_size);
  const int blocks = a.views * a.tiles_x * a.tiles_y;  // every image's tiles
  return dispatch_plan<CB_MAX>(plan, [&](auto m, auto t) -> cudaError_t {
    constexpr int CBM = decltype(m)::value, CBT = decltype(t)::value;
    constexpr int CBX = CBM > CBT ? CBM : CBT;
    auto kernel = forward_kernel<T, TC, CBM, CBT>;
    const size_t smem = size_t(threads) * (sizeof(SplatGeom<T>) + CBX * sizeof(T));
    cudaError_t err = set_smem_limit(kernel, smem);
    if (err != cudaSuccess) return err;
    kernel<<<blocks, threads, smem, stream>>>(a, colors, out, plan.n_main);
    return cudaGetLastError();
  });
}

template <typename T, typename TC>
cudaError_t launch_forward(const RasterLaunch<T>& a, const TC* colors, const ForwardOut<T>& out,
                           int channel_block, cudaStream_t stream) {
  if constexpr (std::is_same<T, float>::value) {
    if (channel_block == 32)
      return launch_forward_cb<32>(a, colors, out, stream);
    return launch_forward_cb<64>(a, colors, out, stream);
  } else {
    return launch_forward_cb<8>(a, colors, out, stream);
  }
}
}  // namespace

template <typename T>
cudaError_t rasterize_forward_cuda_launch(const RasterLaunch<T>& a, const void* colors,
                                          ColorStorage storage, const T* background, T* out_color,
                                          T* out_alpha, T* out_depth, int32_t* out_count,
                                          T* out_trans, int channel_block, cudaStream_t stream) {
  if (a.tiles_x * a.tiles_y == 0) return cudaSuccess;
  const ForwardOut<T> out{background, out_color, out_alpha, out_depth, out_trans, out_count};
  if constexpr (std::is_same<T, float>::value) {
    if (storage == ColorStorage::kHalf)
      return launch_forward<T>(a, static_cast<const __half*>(colors), out, channel_block, stream);
    if (storage == ColorStorage::kBFloat16)
      return launch_forward<T>(a, static_cast<const __nv_bfloat16*>(colors), out, channel_block, stream);
  }
  if (storage != ColorStorage::kSame) return cudaErrorInvalidValue;
  return launch_forward<T>(a, static_cast<const T*>(colors), out, channel_block, stream);
}

template cudaError_t rasterize_forward_cuda_launch<float>(const RasterLaunch<float>&, const void*,
                                                          ColorStorage, const float*, float*,
                                                          float*, float*, int32_t*, float*, int,
                                                          cudaStream_t);
template cudaError_t rasterize_forward_cuda_launch<double>(const RasterLaunch<double>&,
                                                           const void*, ColorStorage,
                                                           const double*, double*, double*,
                                                           double*, int32_t*, double*, int,
                                                           cudaStream_t);

}  // namespace tiger

// Torch glue of the CUDA rasterization kernels (built only with CUDA on). Colors may be
// stored in float16/bfloat16 when the geometry is float32 (converted at load,
// accumulated in float32); gradients are returned in the accumulation dtype.
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <torch/library.h>

#include "common/cuda_zeros.h"
#include "common/torch_checks.h"
#include "raster.h"
#include "raster_cuda.h"

namespace tiger {

namespace {

ColorStorage color_storage(const at::Tensor& colors, const at::Tensor& means2d, const char* op) {
  if (colors.scalar_type() == means2d.scalar_type()) return ColorStorage::kSame;
  TORCH_CHECK(means2d.scalar_type() == at::kFloat &&
                  (colors.scalar_type() == at::kHalf || colors.scalar_type() == at::kBFloat16),
              op, ": colors must have the dtype of means2d (", means2d.scalar_type(),
              "), or float16/bfloat16 with float32 geometry; got ", colors.scalar_type());
  return colors.scalar_type() == at::kHalf ? ColorStorage::kHalf : ColorStorage::kBFloat16;
}

void check_device(const at::Tensor& t, const at::Tensor& ref, const char* op, const char* name) {
  TORCH_CHECK(t.device() == ref.device(), op, ": ", name, " is on ", t.device(), " but expected ",
              ref.device());
}

template <typename T>
RasterLaunch<T> make_launch(const at::Tensor& means2d, const at::Tensor& conics,
                            const at::Tensor& opac, const at::Tensor* depths,
                            const at::Tensor& tile_offsets, const at::Tensor& ids,
                            const RasterArgs& a, int64_t channels,
                            const at::Tensor& trainable = at::Tensor(),
                            const at::Tensor& tile_order = at::Tensor(), bool warp_cull = true) {
  RasterLaunch<T> l;
  l.means2d = means2d.data_ptr<T>();
  l.conics = conics.data_ptr<T>();
  l.opacities = opac.data_ptr<T>();
  l.depths = depths ? depths->data_ptr<T>() : nullptr;
  l.tile_offsets = tile_offsets.data_ptr<int64_t>();
  l.ids = ids.data_ptr<int32_t>();
  l.trainable = trainable.defined() ? trainable.data_ptr<bool>() : nullptr;
  l.tile_order = tile_order.defined() ? tile_order.data_ptr<int32_t>() : nullptr;
  l.warp_cull = warp_cull;
  l.width = int(a.width);
  l.height = int(a.height);
  l.tile_size = int(a.tile_size);
  l.tiles_x = int((a.width + a.tile_size - 1) / a.tile_size);
  l.tiles_y = int((a.height + a.tile_size - 1) / a.tile_size);
  l.views = int(a.views);
  l.channels = int(channels);
  l.alpha_max = T(a.alpha_max);
  l.alpha_threshold = T(a.alpha_threshold);
  l.t_min = T(a.t_min);
  return l;
}

// Tiles of every image (views images, raster.h).
int64_t num_tiles(const RasterArgs& a) {
  return a.views * ((a.width + a.tile_size - 1) / a.tile_size) *
         ((a.height + a.tile_size - 1) / a.tile_size);
}

// Checked before any dispatch: one block per tile holds at most 256 pixel threads, and the
// kernels index tiles and pixel rows of an image with int.
void check_cuda_limits(const char* op, const RasterArgs& a, int64_t channels) {
  TORCH_CHECK(a.tile_size <= 16, op, ": the CUDA kernels take tile_size <= 16, got ", a.tile_size);
  TORCH_CHECK(channels < (int64_t(1) << 24), op, ": too many channels (", channels, ")");
  TORCH_CHECK(num_tiles(a) < (int64_t(1) << 31) && a.width < (int64_t(1) << 30) &&
                  a.height < (int64_t(1) << 30),
              op, ": ", a.views, " images of ", a.width, "x", a.height, " are too many tiles");
}

void check_ok(cudaError_t err, const char* op) {
  TORCH_CHECK(err == cudaSuccess, op, ": CUDA kernel failed: ", cudaGetErrorString(err));
}

// The order of the kernels' blocks (raster.h, tile_order): null for index order, else a
// permutation of the tiles, longest list first (tile_order_cuda.cu), on the current stream.
at::Tensor launch_order(const at::Tensor& tile_offsets, int64_t tile_order, const char* op) {
  if (tile_order != kTileOrderHeavyFirst) return at::Tensor();
  const int64_t tiles = tile_offsets.size(0) - 1;
  auto order = at::empty({tiles}, tile_offsets.options().dtype(at::kInt));
  check_ok(heavy_first_order_cuda_launch(tile_offsets.data_ptr<int64_t>(), int(tiles),
                                         order.data_ptr<int32_t>(), c10::cuda::getCurrentCUDAStream()),
           op);
  return order;
}

}  // namespace

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> rasterize_cuda(
    const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
    const at::Tensor& colors, const at::Tensor& depths, const std::optional<at::Tensor>& background,
    const at::Tensor& tile_offsets, const at::Tensor& gaussian_ids, int64_t width, int64_t height,
    int64_t tile_size, double alpha_max, double alpha_threshold, double t_min,
    int64_t channel_block, int64_t backward_channel_block, int64_t colors_channel_block,
    int64_t backward_pixels_per_thread, int64_t views, const std::optional<at::Tensor>& trainable,
    int64_t tile_order, bool warp_cull) {
  const char* op = "tiger.rasterize";
  const RasterArgs a{width, height, tile_size, alpha_max, alpha_threshold, t_min, views};
  check_channel_block(op, "channel_block", channel_block);
  // the backward's choices, carried for the autograd formula: checked here as on the CPU
  check_channel_block(op, "backward_channel_block", backward_channel_block);
  check_channel_block(op, "colors_channel_block", colors_channel_block);
  check_pixels_per_thread(op, "backward_pixels_per_thread", backward_pixels_per_thread);
  check_tile_order(op, tile_order);
  check_shape(colors, op, "colors", {means2d.size(0), -1});
  check_raster_inputs(op, means2d, conics, opacities, depths, background, colors.size(1),
                      tile_offsets, gaussian_ids, a);
  const ColorStorage storage = color_storage(colors, means2d, op);
  check_cuda_limits(op, a, colors.size(1));
  check_device(colors, means2d, op, "colors");
  check_device(tile_offsets, means2d, op, "tile_offsets");
  check_device(gaussian_ids, means2d, op, "gaussian_ids");
  check_row_mask(trainable, means2d.size(0), means2d, op, "trainable", "means2d");  // carried for the autograd formula
  const c10::cuda::CUDAGuard guard(means2d.device());
  const int64_t C = colors.size(1);
  const int64_t rows = views * height;  // the views' images, stacked
  auto out_color = at::empty({rows, width, C}, means2d.options());
  auto out_alpha = at::empty({rows, width}, means2d.options());
  auto out_depth = at::empty({rows, width}, means2d.options());
  auto out_count = at::empty({rows, width}, means2d.options().dtype(at::kInt));
  auto out_trans = at::empty({rows, width}, means2d.options());
  const auto m = means2d.contiguous(), c = conics.contiguous(), o = opacities.contiguous(),
             d = depths.contiguous(), col = colors.contiguous(), to = tile_offsets.contiguous(),
             ids = gaussian_ids.contiguous();
  const auto bg = background.has_value() ? background->contiguous() : at::Tensor();
  const at::Tensor order = launch_order(to, tile_order, op);
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "rasterize_cuda", [&] {
    using T = scalar_t;
    const auto l = make_launch<T>(m, c, o, &d, to, ids, a, C, at::Tensor(), order, warp_cull);
    check_ok(rasterize_forward_cuda_launch<T>(
                 l, col.data_ptr(), storage, bg.defined() ? bg.data_ptr<T>() : nullptr,
                 out_color.data_ptr<T>(), out_alpha.data_ptr<T>(), out_depth.data_ptr<T>(),
                 out_count.data_ptr<int32_t>(), out_trans.data_ptr<T>(), int(channel_block),
                 c10::cuda::getCurrentCUDAStream().stream()),
             op);
  });
  return {out_color, out_alpha, out_depth, out_count, out_trans};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor>
rasterize_backward_cuda(const at::Tensor& means2d, const at::Tensor& conics,
                        const at::Tensor& opacities, const at::Tensor& colors,
                        const at::Tensor& depths, const std::optional<at::Tensor>& background,
                        const at::Tensor& tile_offsets, const at::Tensor& gaussian_ids,
                        int64_t width, int64_t height, int64_t tile_size, double alpha_max,
                        double alpha_threshold, double t_min, const at::Tensor& transmittance,
                        const at::Tensor& n_contrib, const at::Tensor& v_color,
                        const std::optional<at::Tensor>& v_alpha,
                        const std::optional<at::Tensor>& v_depth, int64_t channel_block,
                        int64_t pixels_per_thread, int64_t views,
                        const std::optional<at::Tensor>& trainable, int64_t tile_order, bool warp_cull) {
  const char* op = "tiger.rasterize_backward";
  const RasterArgs a{width, height, tile_size, alpha_max, alpha_threshold, t_min, views};
  check_channel_block(op, "channel_block", channel_block);
  check_pixels_per_thread(op, "pixels_per_thread", pixels_per_thread);
  check_tile_order(op, tile_order);
  const int64_t n = means2d.size(0);
  check_shape(colors, op, "colors", {n, -1});
  const int64_t C = colors.size(1);
  check_raster_inputs(op, means2d, conics, opacities, depths, background, C, tile_offsets,
                      gaussian_ids, a);
  const ColorStorage storage = color_storage(colors, means2d, op);
  const int64_t H = views * height;  // the views' images, stacked
  check_shape(transmittance, op, "transmittance", {H, width});
  check_shape(n_contrib, op, "n_contrib", {H, width});
  check_dtype(n_contrib, at::kInt, op, "n_contrib");
  check_shape(v_color, op, "v_color", {H, width, C});
  if (v_alpha.has_value()) check_shape(*v_alpha, op, "v_alpha", {H, width});
  if (v_depth.has_value()) check_shape(*v_depth, op, "v_depth", {H, width});
  check_cuda_limits(op, a, C);
  check_device(colors, means2d, op, "colors");
  check_device(tile_offsets, means2d, op, "tile_offsets");
  check_device(gaussian_ids, means2d, op, "gaussian_ids");
  check_device(transmittance, means2d, op, "transmittance");
  check_device(n_contrib, means2d, op, "n_contrib");
  check_device(v_color, means2d, op, "v_color");
  if (v_alpha.has_value()) check_device(*v_alpha, means2d, op, "v_alpha");
  if (v_depth.has_value()) check_device(*v_depth, means2d, op, "v_depth");
  check_row_mask(trainable, means2d.size(0), means2d, op, "trainable", "means2d");
  const c10::cuda::CUDAGuard guard(means2d.device());
  const auto opts = means2d.options();
  // The kernel adds into these atomically. The geometry rows and the per-tile background
  // terms share one zero fill (the geometry gradients are returned as views of it);
  // v_colors is returned as is, so it keeps its own buffer.
  const int64_t tiles = num_tiles(a);
  auto acc = cuda_zeros({n * 8 + tiles * C}, opts);
  auto v_geom = acc.narrow(0, 0, n * 8).view({n, 8});  // u, v, conic a, b, c, opacity, depth, pad
  auto v_bg_tiles = acc.narrow(0, n * 8, tiles * C).view({tiles, C});
  auto v_colors = cuda_zeros({n, C}, opts);
  const auto dt = means2d.scalar_type();
  const auto m = means2d.contiguous(), c = conics.contiguous(), o = opacities.contiguous(),
             d = depths.contiguous(), col = colors.contiguous(), to = tile_offsets.contiguous(),
             ids = gaussian_ids.contiguous(), tr = transmittance.to(dt).contiguous(),
             cnt = n_contrib.contiguous(), vc = v_color.to(dt).contiguous();
  const auto va = v_alpha.has_value() ? v_alpha->to(dt).contiguous() : at::Tensor(),
             vd = v_depth.has_value() ? v_depth->to(dt).contiguous() : at::Tensor();
  const auto bg = background.has_value() ? background->contiguous() : at::Tensor();
  const auto train = trainable.has_value() ? trainable->contiguous() : at::Tensor();
  const at::Tensor order = launch_order(to, tile_order, op);
  AT_DISPATCH_FLOATING_TYPES(dt, "rasterize_backward_cuda", [&] {
    using T = scalar_t;
    const auto l = make_launch<T>(m, c, o, &d, to, ids, a, C, train, order, warp_cull);
    check_ok(rasterize_backward_cuda_launch<T>(
                 l, col.data_ptr(), storage, bg.defined() ? bg.data_ptr<T>() : nullptr,
                 tr.data_ptr<T>(), cnt.data_ptr<int32_t>(), vc.data_ptr<T>(),
                 va.defined() ? va.data_ptr<T>() : nullptr,
                 vd.defined() ? vd.data_ptr<T>() : nullptr, v_geom.data_ptr<T>(), v_colors.data_ptr<T>(),
                 v_bg_tiles.data_ptr<T>(), int(channel_block), int(pixels_per_thread),
                 c10::cuda::getCurrentCUDAStream().stream()),
             op);
  });
  // The [N, 8] rows themselves: the caller hands column views on (the projection's backward
  // reads them strided), no copies.
  return {v_geom, v_colors, v_bg_tiles.sum(0)};
}

std::tuple<at::Tensor, at::Tensor> rasterize_backward_colors_cuda(
    const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
    const at::Tensor& tile_offsets, const at::Tensor& gaussian_ids, int64_t width, int64_t height,
    int64_t tile_size, double alpha_max, double alpha_threshold, double t_min,
    const at::Tensor& n_contrib, const at::Tensor& v_color, int64_t channel_block, int64_t views,
    const std::optional<at::Tensor>& trainable, int64_t tile_order, bool warp_cull) {
  const char* op = "tiger.rasterize_backward_colors";
  const RasterArgs a{width, height, tile_size, alpha_max, alpha_threshold, t_min, views};
  check_channel_block(op, "channel_block", channel_block);
  check_tile_order(op, tile_order);
  const int64_t n = means2d.size(0);
  const int64_t H = views * height;  // the views' images, stacked
  check_shape(v_color, op, "v_color", {H, width, -1});
  const int64_t C = v_color.size(2);
  check_raster_inputs(op, means2d, conics, opacities, opacities.new_empty({n}), std::nullopt, C,
                      tile_offsets, gaussian_ids, a);
  check_shape(n_contrib, op, "n_contrib", {H, width});
  check_dtype(n_contrib, at::kInt, op, "n_contrib");
  check_cuda_limits(op, a, C);
  check_device(tile_offsets, means2d, op, "tile_offsets");
  check_device(gaussian_ids, means2d, op, "gaussian_ids");
  check_device(n_contrib, means2d, op, "n_contrib");
  check_device(v_color, means2d, op, "v_color");
  check_row_mask(trainable, means2d.size(0), means2d, op, "trainable", "means2d");
  const c10::cuda::CUDAGuard guard(means2d.device());
  const auto dt = means2d.scalar_type();
  auto v_colors = cuda_zeros({n, C}, means2d.options());
  auto v_bg_tiles = cuda_zeros({num_tiles(a), C}, means2d.options());
  const auto m = means2d.contiguous(), c = conics.contiguous(), o = opacities.contiguous(),
             to = tile_offsets.contiguous(), ids = gaussian_ids.contiguous(),
             cnt = n_contrib.contiguous(), vc = v_color.to(dt).contiguous();
  const auto train = trainable.has_value() ? trainable->contiguous() : at::Tensor();
  const at::Tensor order = launch_order(to, tile_order, op);
  AT_DISPATCH_FLOATING_TYPES(dt, "rasterize_backward_colors_cuda", [&] {
    using T = scalar_t;
    const auto l = make_launch<T>(m, c, o, nullptr, to, ids, a, C, train, order, warp_cull);
    check_ok(rasterize_backward_colors_cuda_launch<T>(
                 l, cnt.data_ptr<int32_t>(), vc.data_ptr<T>(), v_colors.data_ptr<T>(),
                 v_bg_tiles.data_ptr<T>(), int(channel_block),
                 c10::cuda::getCurrentCUDAStream().stream()),
             op);
  });
  return {v_colors, v_bg_tiles.sum(0)};
}

TORCH_LIBRARY_IMPL(tiger, CUDA, m) {
  m.impl("rasterize", &rasterize_cuda);
  m.impl("rasterize_backward", &rasterize_backward_cuda);
  m.impl("rasterize_backward_colors", &rasterize_backward_colors_cuda);
}

}  // namespace tiger

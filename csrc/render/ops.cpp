// tiger::render_forward: one view's projection, SH colour, tile binning and compositing in one
// call, for renders that need no gradient (tiger.rasterize_gaussians takes it then). The ops it
// chains are called through the dispatcher below autograd, so no Python runs between them: on
// a host where each Python-level op costs tens of microseconds, the GPU otherwise waits for the
// host between the stages (docs/BENCHMARKS.md, "Real scenes"). Same kernels, same values as the
// op-by-op render (tests/render/test_render_forward.py).
#include <ATen/ATen.h>
#include <ATen/core/dispatch/Dispatcher.h>
#include <torch/library.h>

#include <optional>
#include <string>
#include <tuple>

#include "binning/binning_choices.h"
#include "raster/raster.h"

namespace tiger {
namespace {

using T = at::Tensor;
using OptT = std::optional<at::Tensor>;

using ProjectFn = std::tuple<T, T, T, T, T>(const T&, const T&, const T&, const T&, const T&, const T&,
                                            int64_t, int64_t, double, double, double, double, bool,
                                            const OptT&);
using ShFn = T(const T&, const T&, int64_t, const OptT&, const OptT&, bool, const OptT&);
using BinFn = std::tuple<T, T>(const T&, const T&, const T&, const T&, const T&, int64_t, int64_t,
                               int64_t, double, c10::string_view, int64_t, int64_t, int64_t, bool,
                               int64_t);
using RasterFn = std::tuple<T, T, T, T, T>(const T&, const T&, const T&, const T&, const T&,
                                           const OptT&, const T&, const T&, int64_t, int64_t,
                                           int64_t, double, double, double, int64_t, int64_t,
                                           int64_t, int64_t, int64_t, const OptT&, int64_t, bool);

template <typename Fn>
c10::TypedOperatorHandle<Fn> handle(const char* name) {
  return c10::Dispatcher::singleton().findSchemaOrThrow(name, "").typed<Fn>();
}

// The renderer's SH colour step (tiger.render.rasterize.sh_colors): max(SH(means − centre) + 0.5,
// 0) for the Gaussians the projection kept, the camera centre −Rᵀt of the world→camera viewmat.
T sh_colors(const T& means, const T& coeffs, const OptT& rest, const T& viewmat, int64_t degree,
            const T& radii) {
  static const auto sh = handle<ShFn>("tiger::sh_to_color");
  const T rot = viewmat.slice(0, 0, 3).slice(1, 0, 3), trans = viewmat.slice(0, 0, 3).select(1, 3);
  const T centre = at::neg(at::matmul(rot.transpose(0, 1), trans));
  const T visible = radii.select(1, 0) > 0;
  return at::clamp_min(sh.call(means - centre, coeffs, degree, visible, rest, true, std::nullopt) + 0.5, 0.0);
}

std::tuple<T, T, T, T, T, T, T, T, T> render_forward(
    const T& means, const T& quats, const T& scales, const T& opacities, const T& colors,
    const OptT& sh_rest, int64_t sh_degree, const OptT& background, const T& viewmat, const T& K,
    int64_t width, int64_t height, double eps2d, double near_plane, double far_plane,
    double alpha_threshold, bool antialiased, int64_t tile_size, double alpha_max, double t_min,
    c10::string_view path, int64_t block_sort_keys, int64_t warp_sort_keys, int64_t giant_tiles,
    bool serial, int64_t channel_block, int64_t tile_order, bool warp_cull) {
  static const auto project = handle<ProjectFn>("tiger::project_gaussians");
  static const auto bin = handle<BinFn>("tiger::bin_gaussians");
  static const auto raster = handle<RasterFn>("tiger::rasterize");
  TORCH_CHECK(sh_degree >= -1 && sh_degree <= 3, "tiger.render_forward: sh_degree must be -1 (colours "
              "given) or in [0, 3], got ", sh_degree);
  const at::AutoDispatchBelowADInplaceOrView below_autograd;  // no gradient is recorded here
  const T vm = viewmat.to(means.scalar_type()).contiguous();
  const auto [means2d, conics, depths, opac, radii] =
      project.call(means.contiguous(), quats.contiguous(), scales.contiguous(), opacities.contiguous(),
                   vm, K.to(means.scalar_type()).contiguous(), width, height, eps2d, near_plane,
                   far_plane, alpha_threshold, antialiased, std::nullopt);
  T feats;
  if (sh_degree >= 0)
    feats = sh_colors(means, colors, sh_rest, vm, sh_degree, radii);
  else if (!colors.is_cuda() && colors.scalar_type() != means.scalar_type())
    feats = colors.to(means.scalar_type()).contiguous();  // the CPU kernels accumulate in the storage dtype
  else
    feats = colors.contiguous();  // CUDA reads float16/bfloat16 channels directly
  OptT bg;
  if (background.has_value()) bg = background->to(means.scalar_type()).contiguous();
  const auto [tile_offsets, gaussian_ids] =
      bin.call(means2d, conics, opac, depths, radii, width, height, tile_size, alpha_threshold, path,
               block_sort_keys, warp_sort_keys, giant_tiles, serial, 1);
  const auto [color, alpha, depth_accum, n_contrib, transmittance] =
      raster.call(means2d, conics, opac, feats, depths, bg, tile_offsets, gaussian_ids, width, height,
                  tile_size, alpha_max, alpha_threshold, t_min, channel_block, kRasterChannelBlock,
                  kRasterChannelBlock, kRasterPixelsPerThread, 1, std::nullopt, tile_order, warp_cull);
  // tiger.render.rasterize.expected_depth: 0 where nothing contributed (alpha == 0)
  T depth = depth_accum / (alpha + (alpha == 0));
  return {color, alpha, depth, depth_accum, radii.amax(1), means2d, conics, depths, gaussian_ids};
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(tiger, m) {
  const std::string schema =
      "render_forward(Tensor means, Tensor quats, Tensor scales, Tensor opacities, Tensor colors, "
      "Tensor? sh_rest, int sh_degree, Tensor? background, Tensor viewmat, Tensor K, int width, "
      "int height, float eps2d, float near_plane, float far_plane, float alpha_threshold, "
      "bool antialiased, int tile_size, float alpha_max, float t_min, str path=\"auto\", "
      "int block_sort_keys=" + std::to_string(kBinSortKeysMax) +
      ", int warp_sort_keys=" + std::to_string(kWarpSortKeys) +
      ", int giant_tiles=" + std::to_string(kBinGiantTiles) +
      ", bool _serial=False, int channel_block=" + std::to_string(kRasterChannelBlock) +
      ", int tile_order=" + std::to_string(kRasterTileOrder) +
      ", bool warp_cull=" + (kRasterWarpCull ? "True" : "False") + ") -> (Tensor color, Tensor alpha, Tensor depth, Tensor depth_accum, Tensor radii, "
      "Tensor means2d, Tensor conics, Tensor depths, Tensor gaussian_ids)";
  m.def(schema.c_str());
}

TORCH_LIBRARY_IMPL(tiger, CompositeExplicitAutograd, m) { m.impl("render_forward", &render_forward); }

}  // namespace tiger

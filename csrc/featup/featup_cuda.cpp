// Torch glue of the CUDA jittered_window_attention kernels (built only with CUDA).
#include <ATen/Dispatch.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <torch/library.h>

#include <tuple>

#include "featup/featup.h"
#include "featup/featup_glue.h"

namespace tiger {
namespace featup {
namespace {

void check_cuda(const at::Tensor& features, const WindowDims& d, const char* op) {
  TORCH_CHECK(features.is_cuda(), op, " (CUDA): features must be on a CUDA device");
  TORCH_CHECK(d.K <= kMaxKernel, op, " (CUDA): the window (w, b) must be at most ", kMaxKernel, " x ", kMaxKernel,
              ", got ", d.K, " x ", d.K);
  TORCH_CHECK(d.H * d.W * d.C < (int64_t(1) << 31) && d.J * d.FH * d.FW < (int64_t(1) << 31), op,
              " (CUDA): features or cells too many for 32-bit indices");
  TORCH_CHECK(d.H < 65536, op, " (CUDA): features must have fewer than 65536 rows, got ", d.H);
}

// The variant's extra requirements; with `copy`, for staged_tiles_bf16 the features' bfloat16 copy that
// the forward reads (else undefined).
at::Tensor check_variant(const at::Tensor& F, const WindowDims& d, int variant, const char* op, bool copy) {
  if (uses_pixel_dots(variant)) {
    const int64_t elem = uses_bf16_features(variant) ? 4 : static_cast<int64_t>(F.element_size());
    TORCH_CHECK((d.C + 1) * elem <= kDotStageBytes, op, " (CUDA): variant '", kWindowVariantNames[variant],
                "' stages a pixel's channels in shared memory and takes at most ", kDotStageBytes / elem - 1,
                " channels, got features with ", d.C, "; use variant 'shared_scatter'");
  }
  if (!uses_bf16_features(variant)) return at::Tensor();
  TORCH_CHECK(F.scalar_type() == at::kFloat, op, " (CUDA): variant '", kWindowVariantNames[variant],
              "' takes float32 features, got ", F.scalar_type());
  return copy ? F.to(at::kBFloat16).contiguous() : at::Tensor();
}

std::tuple<at::Tensor, at::Tensor> window_attention_cuda(const at::Tensor& features, const at::Tensor& logit_map,
                                                         const at::Tensor& coord_y, const at::Tensor& coord_x,
                                                         const at::Tensor& w, const at::Tensor& b,
                                                         const at::Tensor& mask, int64_t stride_h, int64_t stride_w,
                                                         c10::string_view variant_name) {
  const WindowDims d = check_window_attention(features, logit_map, coord_y, coord_x, w, b, mask, stride_h, stride_w);
  const int variant = parse_window_variant(variant_name);
  check_cuda(features, d, "tiger.jittered_window_attention");
  const c10::cuda::CUDAGuard guard(features.device());
  const auto F = features.contiguous(), L = logit_map.contiguous(), cy = coord_y.contiguous(),
             cx = coord_x.contiguous(), wc = w.contiguous(), bc = b.contiguous(), mc = mask.contiguous();
  const at::Tensor Fb = check_variant(F, d, variant, "tiger.jittered_window_attention", true);
  const void* fb = Fb.defined() ? Fb.data_ptr() : nullptr;
  auto out = at::empty({d.J, d.FH, d.FW, d.C}, F.options());
  auto attn = at::empty({d.J, d.FH, d.FW, d.K * d.K}, F.options());
  void* stream = c10::cuda::getCurrentCUDAStream().stream();
  AT_DISPATCH_FLOATING_TYPES(F.scalar_type(), "tiger.jittered_window_attention", [&] {
    launch_window_forward<scalar_t>(F.data_ptr<scalar_t>(), L.data_ptr<scalar_t>(), cy.data_ptr<scalar_t>(),
                                    cx.data_ptr<scalar_t>(), wc.data_ptr<scalar_t>(), bc.data_ptr<scalar_t>(),
                                    mc.data_ptr<scalar_t>(), d, variant, fb, out.data_ptr<scalar_t>(),
                                    attn.data_ptr<scalar_t>(), stream);
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return {out, attn};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> window_attention_backward_cuda(
    const at::Tensor& grad_out, const at::Tensor& features, const at::Tensor& logit_map, const at::Tensor& coord_y,
    const at::Tensor& coord_x, const at::Tensor& w, const at::Tensor& b, const at::Tensor& mask,
    const at::Tensor& attn, int64_t stride_h, int64_t stride_w, c10::string_view variant_name) {
  const WindowDims d = check_window_attention(features, logit_map, coord_y, coord_x, w, b, mask, stride_h, stride_w);
  const int variant = parse_window_variant(variant_name);
  check_cuda(features, d, "tiger.jittered_window_attention_backward");
  TORCH_CHECK(grad_out.sizes() == at::IntArrayRef({d.J, d.FH, d.FW, d.C}) && grad_out.device() == features.device(),
              "tiger.jittered_window_attention_backward: grad_out must be [J, FH, FW, C] = [", d.J, ", ", d.FH, ", ",
              d.FW, ", ", d.C, "] on the features' device, got ", grad_out.sizes());
  TORCH_CHECK(attn.sizes() == at::IntArrayRef({d.J, d.FH, d.FW, d.K * d.K}) &&
                  attn.scalar_type() == features.scalar_type() && attn.device() == features.device(),
              "tiger.jittered_window_attention_backward: attn must be the forward's [J, FH, FW, K*K], got ",
              attn.sizes(), " ", attn.scalar_type());
  const c10::cuda::CUDAGuard guard(features.device());
  const auto g = grad_out.to(features.scalar_type()).contiguous(), F = features.contiguous(),
             L = logit_map.contiguous(), cy = coord_y.contiguous(), cx = coord_x.contiguous(), wc = w.contiguous(),
             mc = mask.contiguous(), a = attn.contiguous();
  const int64_t cells = d.J * d.FH * d.FW, KK = d.K * d.K, side = d.K + 3;
  auto gz = at::empty({cells, KK}, F.options()), gzl = at::empty({cells, KK}, F.options());
  auto gL = at::zeros_like(L), gF = at::empty_like(F);
  auto tiles = at::empty({cells, side * side}, F.options());
  auto origins = at::empty({cells, 2}, F.options().dtype(at::kInt));
  check_variant(F, d, variant, "tiger.jittered_window_attention_backward", false);
  const bool pixel_dots = uses_pixel_dots(variant);
  // pixel_dots' scratch: the cells' tile extents and the dots of g with the tile pixels' features
  auto extents = pixel_dots ? at::empty({cells, 4}, F.options().dtype(at::kInt)) : at::Tensor();
  auto dots = pixel_dots ? at::empty({cells, side * side}, F.options()) : at::Tensor();
  void* stream = c10::cuda::getCurrentCUDAStream().stream();
  AT_DISPATCH_FLOATING_TYPES(F.scalar_type(), "tiger.jittered_window_attention_backward", [&] {
    launch_window_backward_cells<scalar_t>(g.data_ptr<scalar_t>(), F.data_ptr<scalar_t>(), L.data_ptr<scalar_t>(),
                                           cy.data_ptr<scalar_t>(), cx.data_ptr<scalar_t>(), wc.data_ptr<scalar_t>(),
                                           mc.data_ptr<scalar_t>(), a.data_ptr<scalar_t>(), d, variant,
                                           pixel_dots ? extents.data_ptr<int32_t>() : nullptr,
                                           pixel_dots ? dots.data_ptr<scalar_t>() : nullptr, gz.data_ptr<scalar_t>(),
                                           gzl.data_ptr<scalar_t>(), gL.data_ptr<scalar_t>(), tiles.data_ptr<scalar_t>(),
                                           origins.data_ptr<int32_t>(), stream);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
    launch_window_grad_features<scalar_t>(g.data_ptr<scalar_t>(), tiles.data_ptr<scalar_t>(),
                                          origins.data_ptr<int32_t>(), d, variant, gF.data_ptr<scalar_t>(),
                                          stream);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return {gF, gL, gzl.sum(0).view({d.K, d.K}), gz.sum(0).view({d.K, d.K})};
}

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CUDA, m) {
  m.impl("jittered_window_attention", &window_attention_cuda);
  m.impl("jittered_window_attention_backward", &window_attention_backward_cuda);
}

}  // namespace featup
}  // namespace tiger

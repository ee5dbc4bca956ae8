#pragma once
// ATen-side checks shared by the CPU and CUDA implementations of tiger::jittered_window_attention.
#include <ATen/ATen.h>

#include <string>

#include "featup/featup.h"

namespace tiger {
namespace featup {

inline void check_same(const at::Tensor& t, const at::Tensor& ref, const char* name) {
  TORCH_CHECK(t.scalar_type() == ref.scalar_type(), "tiger.jittered_window_attention: ", name, " (",
              t.scalar_type(), ") must have the dtype of features (", ref.scalar_type(), ")");
  TORCH_CHECK(t.device() == ref.device(), "tiger.jittered_window_attention: ", name,
              " must be on the device of features (", ref.device(), "), got ", t.device());
}

// The WindowVariant named `name` (featup.h); one clear line naming the choices otherwise.
inline int parse_window_variant(c10::string_view name) {
  std::string choices;
  for (int v = 0; v < kWindowVariants; ++v) {
    if (name == kWindowVariantNames[v]) return v;
    choices += std::string(v ? ", " : "") + "'" + kWindowVariantNames[v] + "'";
  }
  TORCH_CHECK(false, "tiger.jittered_window_attention: variant must be one of ", choices, ", got '",
              std::string(name), "'");
  return kBaseline;
}

inline WindowDims check_window_attention(const at::Tensor& features, const at::Tensor& logit_map,
                                         const at::Tensor& coord_y, const at::Tensor& coord_x,
                                         const at::Tensor& w, const at::Tensor& b, const at::Tensor& mask,
                                         int64_t stride_h, int64_t stride_w) {
  const char* op = "tiger.jittered_window_attention: ";
  TORCH_CHECK(features.dim() == 3, op, "features must be [H, W, C], got ", features.sizes());
  TORCH_CHECK(features.scalar_type() == at::kFloat || features.scalar_type() == at::kDouble, op,
              "features must be float32 or float64, got ", features.scalar_type());
  const int64_t H = features.size(0), W = features.size(1), C = features.size(2);
  TORCH_CHECK(H >= 1 && W >= 1 && C >= 1, op, "features must be non-empty, got ", features.sizes());
  TORCH_CHECK(logit_map.dim() == 2 && logit_map.size(0) == H && logit_map.size(1) == W, op,
              "logit_map must be [H, W] = [", H, ", ", W, "], got ", logit_map.sizes());
  TORCH_CHECK(coord_y.dim() == 2, op, "coord_y must be [J, Ho], got ", coord_y.sizes());
  TORCH_CHECK(coord_x.dim() == 2 && coord_x.size(0) == coord_y.size(0), op, "coord_x must be [J, Wo] with J = ",
              coord_y.size(0), " (coord_y's), got ", coord_x.sizes());
  TORCH_CHECK(w.dim() == 2 && w.size(0) == w.size(1) && w.size(0) >= 1, op, "w must be [K, K], got ", w.sizes());
  TORCH_CHECK(b.sizes() == w.sizes(), op, "b must be [K, K] like w ", w.sizes(), ", got ", b.sizes());
  TORCH_CHECK(mask.dim() == 3 && mask.size(0) == coord_y.size(0), op, "mask must be [J, FH, FW] with J = ",
              coord_y.size(0), ", got ", mask.sizes());
  TORCH_CHECK(stride_h >= 1 && stride_w >= 1, op, "strides must be >= 1, got ", stride_h, ", ", stride_w);
  for (auto [t, name] : {std::pair<const at::Tensor*, const char*>{&logit_map, "logit_map"},
                         {&coord_y, "coord_y"}, {&coord_x, "coord_x"}, {&w, "w"}, {&b, "b"}, {&mask, "mask"}})
    check_same(*t, features, name);
  WindowDims d{H, W, C, coord_y.size(0), coord_y.size(1), coord_x.size(1), mask.size(1), mask.size(2),
               w.size(0), stride_h, stride_w};
  TORCH_CHECK(d.FH >= 1 && d.FW >= 1, op, "mask must have at least one cell, got ", mask.sizes());
  TORCH_CHECK((d.FH - 1) * d.SH + d.K <= d.Ho && (d.FW - 1) * d.SW + d.K <= d.Wo, op, "the windows of ", d.FH,
              " x ", d.FW, " cells (kernel ", d.K, ", strides ", d.SH, ", ", d.SW,
              ") must fit the jittered copy of ", d.Ho, " x ", d.Wo, " (coord_y, coord_x)");
  return d;
}

}  // namespace featup
}  // namespace tiger

#pragma once
// Argument checks for the torch-facing glue (host only). Messages name the op,
// the tensor and what was expected, so Python users see an actionable error.
#include <torch/library.h>
#include <ATen/ATen.h>

#include <initializer_list>
#include <optional>
#include <sstream>
#include <string>

namespace tiger {

inline std::string shape_str(at::IntArrayRef s) {
  std::ostringstream o;
  o << "[";
  for (size_t i = 0; i < s.size(); ++i) o << (i ? ", " : "") << s[i];
  o << "]";
  return o.str();
}

// Checks rank and the sizes that are not -1.
inline void check_shape(const at::Tensor& t, const char* op, const char* name,
                        std::initializer_list<int64_t> sizes) {
  bool ok = t.dim() == static_cast<int64_t>(sizes.size());
  int64_t i = 0;
  for (int64_t s : sizes) {
    if (ok && s >= 0 && t.size(i) != s) ok = false;
    ++i;
  }
  if (!ok) {
    std::ostringstream want;
    want << "[";
    i = 0;
    for (int64_t s : sizes) want << (i++ ? ", " : "") << (s >= 0 ? std::to_string(s) : std::string("*"));
    want << "]";
    TORCH_CHECK(false, op, ": ", name, " must have shape ", want.str(), ", got ", shape_str(t.sizes()));
  }
}

inline void check_same(const at::Tensor& t, const at::Tensor& ref, const char* op, const char* name) {
  TORCH_CHECK(t.device() == ref.device(), op, ": ", name, " is on ", t.device(), " but expected ",
              ref.device());
  TORCH_CHECK(t.scalar_type() == ref.scalar_type(), op, ": ", name, " has dtype ", t.scalar_type(),
              " but expected ", ref.scalar_type());
}

inline void check_dtype(const at::Tensor& t, at::ScalarType dt, const char* op, const char* name) {
  TORCH_CHECK(t.scalar_type() == dt, op, ": ", name, " must have dtype ", dt, ", got ", t.scalar_type());
}

// An optional per-row mask (e.g. an op's `trainable`): absent, or bool [rows] on the device of
// `ref` (the tensor named `ref_name`).
inline void check_row_mask(const std::optional<at::Tensor>& mask, int64_t rows, const at::Tensor& ref,
                           const char* op, const char* name, const char* ref_name) {
  if (!mask.has_value()) return;
  check_dtype(*mask, at::kBool, op, name);
  check_shape(*mask, op, name, {rows});
  TORCH_CHECK(mask->device() == ref.device(), op, ": ", name, " is on ", mask->device(), " but ", ref_name,
              " is on ", ref.device());
}

}  // namespace tiger

#pragma once
// Optional tensor arguments of the torch-facing glue (host only): one home for the two helpers
// every op with an optional input needs.
#include <ATen/ATen.h>

#include <optional>

namespace tiger {

// t made contiguous, or no tensor.
inline std::optional<at::Tensor> contiguous(const std::optional<at::Tensor>& t) {
  return t.has_value() ? std::optional<at::Tensor>(t->contiguous()) : std::nullopt;
}

// t's data, or nullptr when there is no tensor.
template <typename T>
const T* optional_ptr(const std::optional<at::Tensor>& t) {
  return t.has_value() ? t->data_ptr<T>() : nullptr;
}

}  // namespace tiger

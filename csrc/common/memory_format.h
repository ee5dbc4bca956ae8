#pragma once
// The layout rule of the ops that keep channels-last maps channels-last (group_norm,
// channel_bias_add): channels-last when x is in that format and not also plain contiguous
// (then NCHW wins); every other stride pattern is copied to NCHW. Outputs take the same format.
#include <ATen/ATen.h>

namespace tiger {

inline bool is_nhwc(const at::Tensor& x) {
  return !x.is_contiguous() && x.is_contiguous(at::MemoryFormat::ChannelsLast);
}

inline at::MemoryFormat memory_format(bool nhwc) {
  return nhwc ? at::MemoryFormat::ChannelsLast : at::MemoryFormat::Contiguous;
}

}  // namespace tiger

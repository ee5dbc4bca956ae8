#pragma once
// tiger connected-component ops for SAM's small-region clean-up (SPEC §4).
//
// connected_components(masks [M, H, W] bool) -> labels [M, H, W] int32
//   8-connected components of every mask. A foreground pixel's label is the row-major index
//   y * W + x (within its own mask) of its component's first pixel in raster order; background
//   pixels are -1. Labels are thus canonical: equal partitions give equal tensors.
// remove_small_regions(masks [M, H, W] bool, area_threshold) -> (cleaned [M, H, W] bool, changed [M] bool)
//   SAM's remove_small_regions applied as its automatic mask generator does, per mask: first
//   'holes' (8-connected components of ~mask with fewer than area_threshold pixels are filled),
//   then 'islands' on the filled mask (components of the mask with fewer than area_threshold
//   pixels are dropped; when every component is small, the largest stays, ties going to the one
//   whose first pixel comes first in raster order). changed[m] is true when either step found a
//   small component (even if the result equals the input, as SAM reports it).
#include <cstdint>

namespace tiger {
namespace components {

// labels[m * H * W + p] = root of p as above (-1: not foreground), where foreground is
// masks[...] != invert; sizes[m * H * W + root] = pixel count of the component (other entries
// are left as they were: zeroed by the caller). local_size is scratch of the same shape.
void launch_label(const bool* masks, bool invert, int64_t m, int64_t h, int64_t w, int32_t* labels,
                  int32_t* local_size, int32_t* sizes, void* stream);

// One SAM clean-up step on labelled components (holes: foreground = ~mask). out[m] = mask with
// small holes filled (holes) or small islands dropped (islands); changed[m] |= a small component
// exists. has_big and best are per-mask scratch, zeroed by the caller.
void launch_small_region_step(const bool* masks, bool holes, int64_t m, int64_t h, int64_t w,
                              const int32_t* labels, const int32_t* sizes, int64_t area_threshold,
                              bool* changed, int32_t* has_big, unsigned long long* best, bool* out,
                              void* stream);

}  // namespace components
}  // namespace tiger

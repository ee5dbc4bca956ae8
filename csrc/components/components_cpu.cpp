// CPU kernels of the components family: one mask per task, union-find over a raster scan.
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <tuple>
#include <vector>

#include "components/components.h"
#include "components/components_glue.h"

namespace tiger {
namespace components {
namespace {

int32_t find_root(std::vector<int32_t>& parent, int32_t a) {
  while (parent[a] != a) {
    parent[a] = parent[parent[a]];  // path halving
    a = parent[a];
  }
  return a;
}

// labels[p] = first pixel (raster order) of p's 8-connected component of {mask != invert}, or -1.
// The smaller root always becomes the parent, so every tree's root is its component's first pixel.
void label_one(const bool* mask, bool invert, int64_t h, int64_t w, int32_t* labels,
               std::vector<int32_t>& parent) {
  const int64_t n = h * w;
  parent.resize(n);
  auto unite = [&](int32_t a, int32_t b) {
    a = find_root(parent, a);
    b = find_root(parent, b);
    if (a < b) parent[b] = a;
    else if (b < a) parent[a] = b;
  };
  for (int64_t y = 0; y < h; ++y)
    for (int64_t x = 0; x < w; ++x) {
      const int32_t p = static_cast<int32_t>(y * w + x);
      if (mask[p] == invert) {
        parent[p] = -1;
        continue;
      }
      parent[p] = p;
      // the four neighbours already scanned: left, up-left, up, up-right
      if (x > 0 && parent[p - 1] >= 0) unite(p, p - 1);
      if (y > 0) {
        const int32_t up = static_cast<int32_t>(p - w);
        if (x > 0 && parent[up - 1] >= 0) unite(p, up - 1);
        if (parent[up] >= 0) unite(p, up);
        if (x + 1 < w && parent[up + 1] >= 0) unite(p, up + 1);
      }
    }
  for (int64_t p = 0; p < n; ++p) labels[p] = parent[p] < 0 ? -1 : find_root(parent, static_cast<int32_t>(p));
}

// One SAM clean-up step on one mask (see components.h); returns whether a small component exists.
bool small_region_step(const bool* mask, bool holes, int64_t h, int64_t w, int64_t area, bool* out,
                       std::vector<int32_t>& labels, std::vector<int32_t>& sizes, std::vector<int32_t>& parent) {
  const int64_t n = h * w;
  labels.resize(n);
  label_one(mask, holes, h, w, labels.data(), parent);
  sizes.assign(n, 0);
  for (int64_t p = 0; p < n; ++p)
    if (labels[p] >= 0) ++sizes[labels[p]];
  bool small = false, big = false;
  int32_t best = -1;
  for (int64_t p = 0; p < n; ++p) {
    if (labels[p] != p) continue;  // roots only
    if (sizes[p] < area) small = true;
    else big = true;
    if (best < 0 || sizes[p] > sizes[best]) best = static_cast<int32_t>(p);
  }
  for (int64_t p = 0; p < n; ++p) {
    const int32_t r = labels[p];
    if (holes) out[p] = mask[p] || (r >= 0 && sizes[r] < area);
    else out[p] = r >= 0 && (sizes[r] >= area || (!big && r == best));
  }
  return small;
}

at::Tensor connected_components_cpu(const at::Tensor& masks_in) {
  check_masks(masks_in, "tiger.connected_components");
  TORCH_CHECK(masks_in.device().is_cpu(), "tiger.connected_components (CPU): masks must be on the CPU");
  const auto masks = masks_in.contiguous();
  const int64_t M = masks.size(0), H = masks.size(1), W = masks.size(2), n = H * W;
  auto labels = at::empty({M, H, W}, masks.options().dtype(at::kInt));
  const bool* src = masks.data_ptr<bool>();
  int32_t* dst = labels.data_ptr<int32_t>();
  at::parallel_for(0, M, 1, [&](int64_t b, int64_t e) {
    std::vector<int32_t> parent;
    for (int64_t m = b; m < e; ++m) label_one(src + m * n, false, H, W, dst + m * n, parent);
  });
  return labels;
}

std::tuple<at::Tensor, at::Tensor> remove_small_regions_cpu(const at::Tensor& masks_in, int64_t area_threshold) {
  check_masks(masks_in, "tiger.remove_small_regions");
  check_area(area_threshold);
  TORCH_CHECK(masks_in.device().is_cpu(), "tiger.remove_small_regions (CPU): masks must be on the CPU");
  const auto masks = masks_in.contiguous();
  const int64_t M = masks.size(0), H = masks.size(1), W = masks.size(2), n = H * W;
  auto out = at::empty_like(masks);
  auto changed = at::zeros({M}, masks.options());
  const bool* src = masks.data_ptr<bool>();
  bool* dst = out.data_ptr<bool>();
  bool* chg = changed.data_ptr<bool>();
  at::parallel_for(0, M, 1, [&](int64_t b, int64_t e) {
    std::vector<int32_t> labels, sizes, parent;
    std::vector<char> filled_storage(n);
    bool* filled = reinterpret_cast<bool*>(filled_storage.data());
    for (int64_t m = b; m < e; ++m) {
      const bool c1 = small_region_step(src + m * n, true, H, W, area_threshold, filled, labels, sizes, parent);
      const bool c2 = small_region_step(filled, false, H, W, area_threshold, dst + m * n, labels, sizes, parent);
      chg[m] = c1 || c2;
    }
  });
  return {out, changed};
}

}  // namespace

TORCH_LIBRARY_IMPL(tiger, CPU, m) {
  m.impl("connected_components", &connected_components_cpu);
  m.impl("remove_small_regions", &remove_small_regions_cpu);
}

}  // namespace components
}  // namespace tiger

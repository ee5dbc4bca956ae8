#pragma once
// The CUDA binning's kernel choices: their defaults (the measured best, docs/BENCHMARKS.md) and
// bounds. Plain constants, shared by the op schema (ops.cpp), its checks and the CUDA sources.
#include <stdint.h>

namespace tiger {

// path "auto": scenes of at most this many Gaussians take the per-tile path, larger ones the
// global sort. On the H100 the per-tile path halved the binning of a 26k-Gaussian real scene;
// the global one was as fast at 400k Gaussians on the standard scene and faster from ~1M
// (docs/BENCHMARKS.md).
constexpr int64_t kBinTilePathMaxGaussians = 1 << 18;

// block_sort_keys: the longest tile list one block sorts in shared memory (CUB block merge
// sort); longer lists are merged from sorted runs of this length. The default and maximum; a
// power of two >= 2 (tests lower it to run the merge passes on small scenes).
constexpr int kBinSortKeysMax = 4096;

// warp_sort_keys: the longest tile list one warp sorts (a bitonic network in registers); the
// longer ones by a block. The default and maximum; >= 1.
constexpr int kWarpSortKeys = 256;

// giant_tiles: candidate (bounding-box) tiles beyond which a large Gaussian of the global-sort
// path is walked by a whole block instead of a warp. >= 1.
constexpr int64_t kBinGiantTiles = 512;

}  // namespace tiger

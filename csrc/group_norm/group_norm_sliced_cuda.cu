// The L2-sliced GroupNorm forward of large channels-last maps (the VAE encoders' 128²-512²).
//
// The three-kernel forward (group_norm_cuda.cu) reads a 512² map from DRAM twice: once for the
// statistics, once more for the apply, 268 MB each at 4 x 128 x 512² in bfloat16. A group's
// apply cannot start before every pixel of it is counted, so the second read can only come from
// L2 if the map is walked in pieces whose statistics and apply run close together: slices of S
// channels of one sample (whole groups and whole 16-byte vectors, about kSliceBytes each). One
// persistent launch claims work items in a fixed order: phase p holds the statistics of slice p
// (K row chunks), then the apply of slice p − 1, so an apply never waits for statistics still
// being computed and about three slices are live in L2 at a time. The last statistics block of
// a slice combines its partials (the arithmetic and fixed order of finalize_stats_kernel: the
// result does not depend on which block is last) and releases the slice's apply items through
// a flag. Blocks claim items only while running, and every statistics item of a slice is claimed
// before its apply items, so a waiting block only ever waits for blocks that are running.
#include <cuda_runtime.h>
#include <cuda_bf16.h>
#include <cuda_fp16.h>

#include <algorithm>

#include "common/cuda_helpers.cuh"
#include "group_norm/group_norm.h"
#include "group_norm/group_norm_walk.cuh"

namespace tiger {
namespace group_norm {
namespace {

using tiger::cuda::load_as;
using tiger::cuda::store_as;
using tiger::cuda::Vec;
using namespace walk;

// Maps of at least this many pixels take the sliced forward; smaller ones fit L2 whole or are
// latency-bound (benchmarks/gpu/NOTES.md, "The CSD guidance step").
constexpr int64_t kSlicedMinPixels = 128 * 128;
// About this many bytes of x per slice: ~3 slices (x) plus the apply's output stay within the
// H100's 50 MB L2.
constexpr int64_t kSliceBytes = int64_t(8) << 20;
// About this many bytes of x per work item (a row chunk of a slice).
constexpr int64_t kItemBytes = int64_t(128) << 10;

struct Sliced {
  int64_t C, HW, G, S, per_n, slices, K, chunk;
  int cols, cvt, R;  // vectors per slice row; threads along them; thread rows per pass
};

// Work item i -> (apply?, slice, chunk k): K statistics items of slice 0, then per phase p >= 1
// the statistics of slice p (none after the last slice) and the apply of slice p − 1.
__device__ __forceinline__ void item_of(const Sliced& s, int64_t i, bool& apply, int64_t& slice, int64_t& k) {
  if (i < s.K) {
    apply = false, slice = 0, k = i;
    return;
  }
  const int64_t j = i - s.K, p = 1 + j / (2 * s.K), r = j % (2 * s.K);
  if (p < s.slices && r < s.K) {
    apply = false, slice = p, k = r;
  } else {
    apply = true, slice = p - 1, k = p < s.slices ? r - s.K : r;
  }
}

template <typename T, int V, bool SILU>
__global__ void __launch_bounds__(kThreads) sliced_forward_kernel(const T* __restrict__ x, Sliced s, Params p,
                                                                  float eps, float* __restrict__ pmean,
                                                                  float* __restrict__ pm2, float* __restrict__ mean_g,
                                                                  float* __restrict__ rstd_g, T* __restrict__ y,
                                                                  unsigned* __restrict__ counters) {
  __shared__ float s_mean[kThreads * V], s_m2[kThreads * V], s_n[kThreads];
  __shared__ long long s_item;
  __shared__ int s_last;
  unsigned* done = counters + 1;        // statistics items finished, per slice
  unsigned* ready = done + s.slices;    // statistics combined, per slice
  const int64_t items = 2 * s.slices * s.K;
  const int tx = threadIdx.x % s.cvt, ty = threadIdx.x / s.cvt, slot = threadIdx.x;
  const bool active = ty < s.R;
  const int64_t D = s.C / s.G;
  for (;;) {
    if (threadIdx.x == 0) s_item = static_cast<long long>(atomicAdd(counters, 1u));
    __syncthreads();
    const int64_t i = s_item;
    __syncthreads();  // every thread has read s_item before thread 0 claims the next item
    if (i >= items) return;
    bool apply;
    int64_t slice, k;
    item_of(s, i, apply, slice, k);
    const int64_t n = slice / s.per_n, c0 = (slice % s.per_n) * s.S + int64_t(tx) * V;  // c0: this column's first channel
    const int64_t r0 = k * s.chunk, r1 = min(s.HW, r0 + s.chunk);
    const auto at = [&](int64_t r) { return (n * s.HW + r) * s.C + c0; };
    if (!apply) {
      // Welford moments of this column's V channels over the chunk's rows, relative to each
      // channel's first element (stats_kernel's shift), combined over the block's rows.
      float cnt = 0.f, mean[V], m2[V], shift[V];
#pragma unroll
      for (int j = 0; j < V; ++j) mean[j] = m2[j] = shift[j] = 0.f;
      if (active) {
#pragma unroll
        for (int j = 0; j < V; ++j) shift[j] = load_as<float>(x[at(0) + j]);
        walk_rows<4>(
            r0 + ty, r1, s.R, [&](int64_t r) { return *reinterpret_cast<const Vec<T, V>*>(x + at(r)); },
            [&](int64_t, const Vec<T, V>& val) {
              cnt += 1.f;
              const float inv = 1.f / cnt;
#pragma unroll
              for (int j = 0; j < V; ++j) {
                const float xv = load_as<float>(val.v[j]) - shift[j];
                const float d = xv - mean[j];
                mean[j] += d * inv;
                m2[j] += d * (xv - mean[j]);
              }
            });
      }
#pragma unroll
      for (int j = 0; j < V; ++j) {
        s_mean[slot * V + j] = mean[j];
        s_m2[slot * V + j] = m2[j];
      }
      s_n[slot] = cnt;
      __syncthreads();
      const int P = pow2_at_least(s.R);
      for (int h = P / 2; h >= 1; h >>= 1) {
        if (active && ty < h && ty + h < s.R) {
          const int other = slot + h * s.cvt;
          const float nb = s_n[other];
#pragma unroll
          for (int j = 0; j < V; ++j) {
            float n_j = cnt;
            merge(n_j, mean[j], m2[j], nb, s_mean[other * V + j], s_m2[other * V + j]);
            s_mean[slot * V + j] = mean[j];
            s_m2[slot * V + j] = m2[j];
          }
          cnt += nb;
          s_n[slot] = cnt;
        }
        __syncthreads();
      }
      if (active && ty == 0) {  // partials [slice, k, S]
        const int64_t base = (slice * s.K + k) * s.S + int64_t(tx) * V;
#pragma unroll
        for (int j = 0; j < V; ++j) {
          pmean[base + j] = mean[j];
          pm2[base + j] = m2[j];
        }
      }
      __threadfence();  // this thread's partials before the block's count
      __syncthreads();
      if (threadIdx.x == 0) s_last = atomicAdd(done + slice, 1u) == static_cast<unsigned>(s.K - 1);
      __syncthreads();
      if (!s_last) continue;
      __threadfence();  // the other blocks' partials, published before their counts
      // The slice's groups, one after another: entry e of a group is (chunk e / D, channel
      // e % D), merged per thread in a fixed stride and then in a fixed tree.
      const int64_t cs = (slice % s.per_n) * s.S;  // the slice's first channel
      for (int64_t gl = 0; gl < s.S / D; ++gl) {
        const int64_t c_first = cs + gl * D, g = c_first / D;
        const float s0 = load_as<float>(x[n * s.HW * s.C + c_first]) + input_bias_at(p.input_bias, s.C, n, c_first);
        float tc = 0.f, tm = 0.f, t2 = 0.f;
        for (int64_t e = threadIdx.x; e < D * s.K; e += kThreads) {
          const int64_t kk = e / D, c = c_first + e % D;
          const int64_t idx = (slice * s.K + kk) * s.S + (c - cs);
          const float count = static_cast<float>(max(int64_t(0), min(s.chunk, s.HW - kk * s.chunk)));
          const float to_group = load_as<float>(x[n * s.HW * s.C + c]) + input_bias_at(p.input_bias, s.C, n, c) - s0;
          merge(tc, tm, t2, count, to_group + __ldcg(pmean + idx), __ldcg(pm2 + idx));
        }
        __syncthreads();  // s_* free (the previous group's tree, or the walk's)
        s_n[threadIdx.x] = tc;
        s_mean[threadIdx.x] = tm;
        s_m2[threadIdx.x] = t2;
        __syncthreads();
        for (int h = kThreads / 2; h >= 1; h >>= 1) {
          if (threadIdx.x < h) {
            const int o = threadIdx.x + h;
            merge(tc, tm, t2, s_n[o], s_mean[o], s_m2[o]);
            s_n[threadIdx.x] = tc;
            s_mean[threadIdx.x] = tm;
            s_m2[threadIdx.x] = t2;
          }
          __syncthreads();
        }
        if (threadIdx.x == 0) {
          mean_g[n * s.G + g] = s0 + tm;
          rstd_g[n * s.G + g] = rsqrtf(fmaxf(tc > 0.f ? t2 / tc : 0.f, 0.f) + eps);
        }
      }
      if (threadIdx.x == 0) {
        __threadfence();  // mean and rstd before the flag
        atomicExch(ready + slice, 1u);
      }
      continue;
    }
    // Apply: wait for the slice's statistics (combined a phase ago in the usual case).
    if (threadIdx.x == 0) {
      while (atomicAdd(ready + slice, 0u) == 0u) __nanosleep(64);
      __threadfence();
    }
    __syncthreads();
    if (!active) continue;
    float m[V], a[V], b[V];
#pragma unroll
    for (int j = 0; j < V; ++j) {
      const int64_t c = c0 + j, ng = n * s.G + c / D;
      m[j] = __ldcg(mean_g + ng) - input_bias_at(p.input_bias, s.C, n, c);
      a[j] = __ldcg(rstd_g + ng) * param_at<T>(p, p.weight, c, 1.f);
      b[j] = param_at<T>(p, p.bias, c, 0.f);
    }
    walk_rows<4>(
        r0 + ty, r1, s.R, [&](int64_t r) { return *reinterpret_cast<const Vec<T, V>*>(x + at(r)); },
        [&](int64_t r, const Vec<T, V>& in) {
          Vec<T, V> out;
#pragma unroll
          for (int j = 0; j < V; ++j) {
            float z = (load_as<float>(in.v[j]) - m[j]) * a[j] + b[j];
            if (SILU) z *= sigmoid(z);
            out.v[j] = store_as<T>(z);
          }
          *reinterpret_cast<Vec<T, V>*>(y + at(r)) = out;
        });
  }
}

int64_t gcd64(int64_t a, int64_t b) { return b == 0 ? a : gcd64(b, a % b); }

template <typename T, int V, bool SILU>
int resident_blocks() {
  int dev = 0, sms = 0, per_sm = 0;
  if (cudaGetDevice(&dev) != cudaSuccess || cudaDeviceGetAttribute(&sms, cudaDevAttrMultiProcessorCount, dev) != cudaSuccess)
    sms = 132;
  if (cudaOccupancyMaxActiveBlocksPerMultiprocessor(&per_sm, sliced_forward_kernel<T, V, SILU>, kThreads, 0) != cudaSuccess)
    per_sm = 1;
  return std::max(1, sms * std::max(per_sm, 1));
}

}  // namespace

SlicedPlan plan_sliced(const Dims& d, int vector_width, int elem_size, int64_t chunks) {
  SlicedPlan plan;
  if (!d.nhwc || vector_width <= 1 || d.HW < kSlicedMinPixels) return plan;
  const int64_t D = d.C / d.G, V = vector_width;
  const int64_t step = D / gcd64(D, V) * V;  // whole groups and whole vectors
  if (d.C % step != 0) return plan;
  // the smallest S (a multiple of step dividing C) of at least kSliceBytes, else all of C
  int64_t S = d.C;
  for (int64_t s = step; s < d.C; s += step)
    if (d.C % s == 0 && d.HW * s * elem_size >= kSliceBytes) {
      S = s;
      break;
    }
  if (S / V > kThreads) return plan;  // a thread row must hold a slice row
  // row chunks of ~kItemBytes; no more than the partial buffers (sized by `chunks`) hold
  int64_t chunk = std::max<int64_t>(1, kItemBytes / (S * elem_size));
  int64_t K = (d.HW + chunk - 1) / chunk;
  if (K > chunks) {
    chunk = (d.HW + chunks - 1) / chunks;
    K = (d.HW + chunk - 1) / chunk;
  }
  plan.S = S;
  plan.slices = d.N * (d.C / S);
  plan.K = K;
  plan.chunk = chunk;
  return plan;
}

template <typename T, int V>
void launch_sliced_forward(const T* x, Params p, const Dims& d, float eps, bool silu, const SlicedPlan& plan,
                           float* pmean, float* pm2, float* mean, float* rstd, T* y, unsigned* counters,
                           cudaStream_t st) {
  Sliced s;
  s.C = d.C, s.HW = d.HW, s.G = d.G, s.S = plan.S, s.per_n = d.C / plan.S, s.slices = plan.slices;
  s.K = plan.K, s.chunk = plan.chunk;
  s.cols = static_cast<int>(plan.S / V);
  s.cvt = s.cols;
  s.R = kThreads / s.cvt;
  if (silu)
    sliced_forward_kernel<T, V, true><<<resident_blocks<T, V, true>(), kThreads, 0, st>>>(
        x, s, p, eps, pmean, pm2, mean, rstd, y, counters);
  else
    sliced_forward_kernel<T, V, false><<<resident_blocks<T, V, false>(), kThreads, 0, st>>>(
        x, s, p, eps, pmean, pm2, mean, rstd, y, counters);
}

#define TIGER_INSTANTIATE(T)                                                                                \
  template void launch_sliced_forward<T, 16 / sizeof(T)>(const T*, Params, const Dims&, float, bool,         \
                                                          const SlicedPlan&, float*, float*, float*, float*, \
                                                          T*, unsigned*, cudaStream_t);
TIGER_INSTANTIATE(float)
TIGER_INSTANTIATE(__half)
TIGER_INSTANTIATE(__nv_bfloat16)
#undef TIGER_INSTANTIATE

}  // namespace group_norm
}  // namespace tiger

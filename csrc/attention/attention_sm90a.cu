// Self-attention for head dim 40 on Hopper (sm_90a): warpgroup MMAs (wgmma) for both products,
// the online softmax in registers between them.
//
// Why a kernel of our own: the guidances' 64² self-attention (InstructPix2Pix, 8 heads of 40,
// 4096 tokens) runs cuDNN's SDPA at ~0.9 ms a call on an H100, which pads the head dim to 64.
// Here the QKᵀ product runs at head dim 48 (three k16 steps; columns 40-47 are zero in shared
// memory) and PV at n = 40.
//
// One CTA = kWG warpgroups = 64·kWG query rows of one (batch, head); every warpgroup owns 64 rows
// and all of them share each key / value tile, so K and V cross L2 once per 64·kWG query rows
// (with one warpgroup a CTA the kernel was bound by that traffic: 4 GB a 12 x 8 x 4096² call,
// L2 throughput 87 % in Nsight Compute). Per key tile of 128: S = Q Kᵀ (3 x wgmma m64n128k16,
// both operands in shared memory), the running max / sum update and P = exp2(S·scale·log2e − m)
// in registers, then O += P V (8 x wgmma m64n40k16, P from registers in the accumulator's
// layout, V from shared memory as the MN-major operand). Shared-memory operands use the
// no-swizzle ("interleave") layout: 8-row x 16-byte core matrices, addressed by the descriptors'
// leading / stride byte offsets.
//
// Two schedules: "lockstep" (every thread copies, two stages, a CTA-wide barrier per tile) and
// "producer" (a producer warpgroup fills four stages behind mbarriers and gives its registers to
// the consumer warpgroups, which run free of each other, overlap each tile's softmax with the
// previous tile's PV, and compute a quarter of the exponentials on the FMA pipes). Measured on an
// H100 (benchmarks/attention.py, docs/BENCHMARKS.md): the producer schedule with 3 warpgroups is
// the fastest, 0.90-0.92 ms for InstructPix2Pix's 12 x 8 x 4096² layer as CUDA-graph replays,
// level with cuDNN's SDPA (0.91); what did and did not help is in benchmarks/gpu/NOTES.md.
#include <cuda_bf16.h>
#include <cuda_runtime.h>

#include <cstdint>

#include "attention/attention_cuda.h"

// Built for another architecture, the kernel bodies are empty and these helpers unused.
#pragma nv_diag_suppress 177

namespace tiger {
namespace attention {
namespace {

constexpr int kD = 40;            // head dim
constexpr int kChunks = kD / 8;   // 16-byte chunks of a row of q, k or v
constexpr int kDPad = 48;         // QKᵀ's K extent: three k16 steps
constexpr int kBlockN = 128;      // keys per tile
constexpr int kKBytes = kBlockN * kDPad * 2;  // 12288 a stage
constexpr int kVBytes = kBlockN * kD * 2;     // 10240 a stage

template <int kWG>
struct Tile {
  static constexpr int kRows = 64 * kWG;      // query rows per CTA
  static constexpr int kThreads = 128 * kWG;
  static constexpr int kQBytes = kRows * kDPad * 2;
  static constexpr int kSmemBytes = kQBytes + 2 * kKBytes + 2 * kVBytes;
};

// K-major operands (Q, K): core matrix (row / 8, chunk) of a [rows][kDPad] tile.
constexpr uint32_t kQKGroup = (kDPad / 8) * 128;  // stride between 8-row groups (SBO)
constexpr uint32_t kCore = 128;                   // stride between 16-byte chunks (LBO)
// V as stored ([token][dim], the MN-major B operand): core matrix (token / 8, dim / 8).
constexpr uint32_t kVKGroup = kChunks * 128;  // stride between 8-token groups (K direction, LBO)

__device__ __forceinline__ uint32_t qk_offset(int row, int chunk) {
  return (row >> 3) * kQKGroup + chunk * kCore + (row & 7) * 16;
}

__device__ __forceinline__ uint32_t smem_address(const void* p) {
  return static_cast<uint32_t>(__cvta_generic_to_shared(p));
}

// A shared-memory matrix descriptor: start address, leading and stride byte offsets (all in
// 16-byte units), no swizzle (layout type 0 in bits 62-63), base offset 0.
__device__ __forceinline__ uint64_t descriptor(uint32_t address, uint32_t lbo, uint32_t sbo) {
  return static_cast<uint64_t>((address >> 4) & 0x3FFF) | (static_cast<uint64_t>((lbo >> 4) & 0x3FFF) << 16) |
         (static_cast<uint64_t>((sbo >> 4) & 0x3FFF) << 32);
}

__device__ __forceinline__ void cp_async16(uint32_t dst, const void* src) {
  asm volatile("cp.async.cg.shared.global [%0], [%1], 16;\n" ::"r"(dst), "l"(src) : "memory");
}
__device__ __forceinline__ void cp_async_commit() { asm volatile("cp.async.commit_group;\n" ::: "memory"); }
template <int N>
__device__ __forceinline__ void cp_async_wait() {
  asm volatile("cp.async.wait_group %0;\n" ::"n"(N) : "memory");
}
// Generic-proxy writes (cp.async, st.shared) made visible to the MMAs' async-proxy reads.
__device__ __forceinline__ void fence_proxy_async() { asm volatile("fence.proxy.async.shared::cta;\n" ::: "memory"); }
__device__ __forceinline__ void wgmma_fence() { asm volatile("wgmma.fence.sync.aligned;\n" ::: "memory"); }
__device__ __forceinline__ void wgmma_commit() { asm volatile("wgmma.commit_group.sync.aligned;\n" ::: "memory"); }
template <int N>
__device__ __forceinline__ void wgmma_wait() {
  asm volatile("wgmma.wait_group.sync.aligned %0;\n" ::"n"(N) : "memory");
}
// Keeps the compiler from moving reads of an accumulator above the wait that completes it.
__device__ __forceinline__ void fence_register(float& r) { asm volatile("" : "+f"(r)::"memory"); }

__device__ __forceinline__ float exp2_approx(float x) {
  float y;
  asm("ex2.approx.ftz.f32 %0, %1;\n" : "=f"(y) : "f"(x));
  return y;
}

// 2^x on the FMA and integer pipes instead of the SFU (FlashAttention-4's trick, for a share of a
// tile's exponentials: the SFU issues 16 a clock per SM, the FMA pipes 128): x = j + f with j =
// rint(x) from the 1.5·2^23 add, 2^f for f in [-0.5, 0.5] by a cubic (relative error 7.5e-5, far
// below P's bf16 rounding), j added to the exponent bits. Clamped at -126 so that the exponent
// cannot wrap: the cubic is 0.99993 at f = 0, so j = -127 would carry into the sign bit (a NaN);
// x ≤ -126 gives 0 or a subnormal below 2^-125 (ex2.approx.ftz gives 0 below -126).
__device__ __forceinline__ float exp2_fma(float x) {
  x = fmaxf(x, -126.f);
  const float t = x + 12582912.f;
  const float f = x - (t - 12582912.f);
  const float p = fmaf(fmaf(fmaf(0.05517143f, f, 0.24261086f), f, 0.693261f), f, 0.9999281f);
  return __uint_as_float(__float_as_uint(p) + (__float_as_uint(t) << 23));
}

__device__ __forceinline__ uint32_t pack_bf16(float lo, float hi) {
  const __nv_bfloat162 v = __floats2bfloat162_rn(lo, hi);
  return *reinterpret_cast<const uint32_t*>(&v);
}

#define TIGER_F4(i) "+f"(d[i]), "+f"(d[i + 1]), "+f"(d[i + 2]), "+f"(d[i + 3])
#define TIGER_F16(i) TIGER_F4(i), TIGER_F4(i + 4), TIGER_F4(i + 8), TIGER_F4(i + 12)

#if defined(__CUDA_ARCH_FEAT_SM90_ALL)
// d (+)= A·B, A [64 x 16] and B [16 x 128] in shared memory (both K-major); scale_d = 0 ignores d.
__device__ __forceinline__ void mma_qk(float (&d)[64], uint64_t a, uint64_t b, int scale_d) {
  asm volatile(
      "{\n.reg .pred p;\nsetp.ne.b32 p, %66, 0;\n"
      "wgmma.mma_async.sync.aligned.m64n128k16.f32.bf16.bf16 "
      "{%0, %1, %2, %3, %4, %5, %6, %7, %8, %9, %10, %11, %12, %13, %14, %15, "
      "%16, %17, %18, %19, %20, %21, %22, %23, %24, %25, %26, %27, %28, %29, %30, %31, "
      "%32, %33, %34, %35, %36, %37, %38, %39, %40, %41, %42, %43, %44, %45, %46, %47, "
      "%48, %49, %50, %51, %52, %53, %54, %55, %56, %57, %58, %59, %60, %61, %62, %63}, "
      "%64, %65, p, 1, 1, 0, 0;\n}\n"
      : TIGER_F16(0), TIGER_F16(16), TIGER_F16(32), TIGER_F16(48)
      : "l"(a), "l"(b), "r"(scale_d));
}

// d += A·B, A [64 x 16] in registers (the accumulator layout of mma_qk, as bf16 pairs), B
// [16 x 40] in shared memory as the MN-major operand (V as stored; the MMA transposes it).
__device__ __forceinline__ void mma_pv(float (&d)[20], const uint32_t (&a)[4], uint64_t b) {
  asm volatile(
      "{\n.reg .pred p;\nsetp.ne.b32 p, %25, 0;\n"
      "wgmma.mma_async.sync.aligned.m64n40k16.f32.bf16.bf16 "
      "{%0, %1, %2, %3, %4, %5, %6, %7, %8, %9, %10, %11, %12, %13, %14, %15, %16, %17, %18, %19}, "
      "{%20, %21, %22, %23}, %24, p, 1, 1, 1;\n}\n"
      : TIGER_F16(0), TIGER_F4(16)
      : "r"(a[0]), "r"(a[1]), "r"(a[2]), "r"(a[3]), "l"(b), "r"(1));
}
#endif

#undef TIGER_F16
#undef TIGER_F4

#if defined(__CUDA_ARCH_FEAT_SM90_ALL)
// The pieces of one key tile for a warpgroup's 64 query rows. The accumulator layout: this thread
// holds rows r and r + 8 (r = 16·warp + lane / 4), columns 8·nb + 2·(lane % 4) + {0, 1} of each
// 8-column block nb; the other three lanes of its quad hold the rest of the two rows.

// Issues S = Q Kᵀ over the padded head dim (one commit group; the caller waits).
__device__ __forceinline__ void issue_qk(float (&s)[64], uint32_t q_addr, uint32_t k_addr) {
#pragma unroll
  for (int i = 0; i < 64; ++i) fence_register(s[i]);
  wgmma_fence();
#pragma unroll
  for (int ks = 0; ks < kDPad / 16; ++ks)
    mma_qk(s, descriptor(q_addr + ks * 2 * kCore, kCore, kQKGroup), descriptor(k_addr + ks * 2 * kCore, kCore, kQKGroup), ks > 0);
  wgmma_commit();
}

// Issues O += P V (one commit group; P's registers must stay unchanged until it completes).
__device__ __forceinline__ void issue_pv(float (&o)[20], const uint32_t (&pa)[8][4], uint32_t v_addr) {
#pragma unroll
  for (int i = 0; i < 20; ++i) fence_register(o[i]);
  wgmma_fence();
#pragma unroll
  for (int ks = 0; ks < kBlockN / 16; ++ks) mma_pv(o, pa[ks], descriptor(v_addr + ks * 2 * kVKGroup, kVKGroup, kCore));
  wgmma_commit();
}

// The online softmax of a completed S, in place: the new running maxima, row sums rescaled and
// extended, s = exp2(s·scale − max·scale); returns the factor alpha by which O must be rescaled.
// kFmaExp: a quarter of the exponentials (scores i with i % 8 ≥ 6) run on the FMA pipes
// (exp2_fma), the rest on the SFU, whose 16 a clock per SM bound the layer otherwise (the producer
// schedule; the lockstep CTAs of 128 registers would spill its temporaries). Four independent
// max / sum chains a row instead of one measured no faster.
template <bool kFmaExp>
__device__ __forceinline__ void softmax_in_place(float (&s)[64], float scale, float (&row_max)[2], float (&row_sum)[2],
                                                 float (&alpha)[2]) {
  float mx[2] = {row_max[0], row_max[1]};
#pragma unroll
  for (int nb = 0; nb < 16; ++nb) {
    mx[0] = fmaxf(mx[0], fmaxf(s[4 * nb], s[4 * nb + 1]));
    mx[1] = fmaxf(mx[1], fmaxf(s[4 * nb + 2], s[4 * nb + 3]));
  }
  float shift[2];
#pragma unroll
  for (int r = 0; r < 2; ++r) {
    mx[r] = fmaxf(mx[r], __shfl_xor_sync(0xffffffffu, mx[r], 1));
    mx[r] = fmaxf(mx[r], __shfl_xor_sync(0xffffffffu, mx[r], 2));
    alpha[r] = exp2_approx((row_max[r] - mx[r]) * scale);  // 0 on the first tile (row_max = -inf)
    row_max[r] = mx[r];
    row_sum[r] *= alpha[r];
    shift[r] = mx[r] * scale;
  }
#pragma unroll
  for (int i = 0; i < 64; ++i) {
    const float x = fmaf(s[i], scale, -shift[(i >> 1) & 1]);
    s[i] = kFmaExp && (i & 7) >= 6 ? exp2_fma(x) : exp2_approx(x);
  }
#pragma unroll
  for (int nb = 0; nb < 16; ++nb) {
    row_sum[0] += s[4 * nb] + s[4 * nb + 1];
    row_sum[1] += s[4 * nb + 2] + s[4 * nb + 3];
  }
}

__device__ __forceinline__ void rescale(float (&o)[20], const float (&alpha)[2]) {
#pragma unroll
  for (int nb = 0; nb < 5; ++nb) {
    o[4 * nb] *= alpha[0];
    o[4 * nb + 1] *= alpha[0];
    o[4 * nb + 2] *= alpha[1];
    o[4 * nb + 3] *= alpha[1];
  }
}

// P as the A fragments of PV's eight k16 steps: (row r, cols 2c), (row r + 8, cols 2c), (row r,
// cols 8 + 2c), (row r + 8, cols 8 + 2c) of step ks are S's blocks 2·ks and 2·ks + 1.
__device__ __forceinline__ void pack_p(const float (&s)[64], uint32_t (&pa)[8][4]) {
#pragma unroll
  for (int ks = 0; ks < 8; ++ks) {
    pa[ks][0] = pack_bf16(s[8 * ks], s[8 * ks + 1]);
    pa[ks][1] = pack_bf16(s[8 * ks + 2], s[8 * ks + 3]);
    pa[ks][2] = pack_bf16(s[8 * ks + 4], s[8 * ks + 5]);
    pa[ks][3] = pack_bf16(s[8 * ks + 6], s[8 * ks + 7]);
  }
}

// One key tile, start to end (returns when the MMAs have read the tile: the stage may be refilled).
__device__ __forceinline__ void attend_tile(uint32_t q_addr, uint32_t k_addr, uint32_t v_addr, float scale, float (&o)[20],
                                            float (&row_max)[2], float (&row_sum)[2]) {
  float s[64], alpha[2];
  uint32_t pa[8][4];
  issue_qk(s, q_addr, k_addr);
  wgmma_wait<0>();
#pragma unroll
  for (int i = 0; i < 64; ++i) fence_register(s[i]);
  softmax_in_place<false>(s, scale, row_max, row_sum, alpha);
  rescale(o, alpha);
  pack_p(s, pa);
  issue_pv(o, pa, v_addr);
  wgmma_wait<0>();
#pragma unroll
  for (int i = 0; i < 20; ++i) fence_register(o[i]);
}

// This warpgroup's 64 output rows (first one `first_row` of the sequence at `row0`): O / row sums
// as bf16; rows past L are not written.
__device__ __forceinline__ void store_rows(const AttentionParams& p, const float (&o)[20], float (&row_sum)[2],
                                           int first_row, int64_t row0, int head) {
  const int warp = (threadIdx.x >> 5) & 3, lane = threadIdx.x & 31;
#pragma unroll
  for (int r = 0; r < 2; ++r) {
    row_sum[r] += __shfl_xor_sync(0xffffffffu, row_sum[r], 1);
    row_sum[r] += __shfl_xor_sync(0xffffffffu, row_sum[r], 2);
  }
  const float inv[2] = {1.f / row_sum[0], 1.f / row_sum[1]};
  const int r0 = first_row + 16 * warp + (lane >> 2), col = 2 * (lane & 3);
  __nv_bfloat16* out0 = p.out + (row0 + r0) * p.out_stride + head * kD + col;
  __nv_bfloat16* out1 = out0 + 8 * p.out_stride;
#pragma unroll
  for (int nb = 0; nb < 5; ++nb) {
    if (r0 < p.L)
      *reinterpret_cast<__nv_bfloat162*>(out0 + 8 * nb) = __floats2bfloat162_rn(o[4 * nb] * inv[0], o[4 * nb + 1] * inv[0]);
    if (r0 + 8 < p.L)
      *reinterpret_cast<__nv_bfloat162*>(out1 + 8 * nb) =
          __floats2bfloat162_rn(o[4 * nb + 2] * inv[1], o[4 * nb + 3] * inv[1]);
  }
}
#endif

template <int kThreads>
__device__ __forceinline__ void load_kv(const AttentionParams& p, const __nv_bfloat16* kb, const __nv_bfloat16* vb,
                                        int tile, unsigned char* sk, unsigned char* sv, int tid) {
  const int64_t t0 = static_cast<int64_t>(tile) * kBlockN;
  // consecutive threads take consecutive rows of one chunk: eight of them fill one core matrix
#pragma unroll
  for (int i = tid; i < kBlockN * kChunks; i += kThreads) {
    const int row = i % kBlockN, c = i / kBlockN;
    cp_async16(smem_address(sk + qk_offset(row, c)), kb + (t0 + row) * p.k_stride + c * 8);
    cp_async16(smem_address(sv + (row >> 3) * kVKGroup + c * kCore + (row & 7) * 16), vb + (t0 + row) * p.v_stride + c * 8);
  }
}

// The (batch, head) and query rows of this CTA: first query row m0 of the sequence at row0;
// q, k, v point at the sequence's first row, this head's columns.
struct CtaRows {
  int64_t row0;
  int m0, head;
  const __nv_bfloat16 *q, *k, *v;
};

__device__ __forceinline__ CtaRows cta_rows(const AttentionParams& p, int rows_per_cta) {
  CtaRows r;
  r.m0 = blockIdx.x * rows_per_cta;
  r.head = blockIdx.y;
  r.row0 = static_cast<int64_t>(blockIdx.z) * p.L;
  r.q = p.q + r.row0 * p.q_stride + r.head * kD;
  r.k = p.k + r.row0 * p.k_stride + r.head * kD;
  r.v = p.v + r.row0 * p.v_stride + r.head * kD;
  return r;
}

// Columns 40-47 of Q's q_rows rows and of every K stage stay zero: QKᵀ's third k16 step adds
// nothing. Threads tid, tid + threads, ... of the CTA.
__device__ __forceinline__ void zero_pad_columns(unsigned char* sq, int q_rows, unsigned char* sk, int k_stages, int tid,
                                                 int threads) {
  const uint4 zero = make_uint4(0, 0, 0, 0);
  for (int r = tid; r < q_rows; r += threads) *reinterpret_cast<uint4*>(sq + qk_offset(r, kChunks)) = zero;
  for (int r = tid; r < k_stages * kBlockN; r += threads)
    *reinterpret_cast<uint4*>(sk + (r / kBlockN) * kKBytes + qk_offset(r % kBlockN, kChunks)) = zero;
}

// Copies the CTA's query rows first … first + count − 1 into Q's tile (threads tid, tid + threads,
// ...; uncommitted cp.async). Rows past L (the last CTA when 64·warpgroups does not divide L)
// compute on row L − 1 and are not stored.
__device__ __forceinline__ void load_q(const AttentionParams& p, const CtaRows& cta, unsigned char* sq, int first,
                                       int count, int tid, int threads) {
  for (int i = tid; i < count * kChunks; i += threads) {
    const int row = first + i % count, c = i / count;
    const int64_t src = min(cta.m0 + row, p.L - 1);
    cp_async16(smem_address(sq + qk_offset(row, c)), cta.q + src * p.q_stride + c * 8);
  }
}

template <int kWG>
__global__ void __launch_bounds__(Tile<kWG>::kThreads, kWG == 1 ? 3 : kWG == 2 ? 2 : 1) attention_head40_kernel(const AttentionParams p) {
#if defined(__CUDA_ARCH_FEAT_SM90_ALL)
  using T = Tile<kWG>;
  extern __shared__ __align__(128) unsigned char smem[];
  unsigned char* sq = smem;
  unsigned char* sk = smem + T::kQBytes;  // two stages
  unsigned char* sv = sk + 2 * kKBytes;   // two stages
  const int tid = threadIdx.x, wg = tid >> 7;
  const CtaRows cta = cta_rows(p, T::kRows);
  zero_pad_columns(sq, T::kRows, sk, 2, tid, T::kThreads);
  load_q(p, cta, sq, 0, T::kRows, tid, T::kThreads);
  load_kv<T::kThreads>(p, cta.k, cta.v, 0, sk, sv, tid);
  cp_async_commit();

  float o[20];
#pragma unroll
  for (int i = 0; i < 20; ++i) o[i] = 0.f;
  const float neg_inf = -__int_as_float(0x7f800000);
  float row_max[2] = {neg_inf, neg_inf}, row_sum[2] = {0.f, 0.f};
  const float scale = p.scale_log2;
  const int n_tiles = p.L / kBlockN;
  const uint32_t q_addr = smem_address(sq) + wg * 8 * kQKGroup;  // this warpgroup's 64 rows

  for (int j = 0; j < n_tiles; ++j) {
    const int stage = j & 1;
    unsigned char* skj = sk + stage * kKBytes;
    unsigned char* svj = sv + stage * kVBytes;
    if (j + 1 < n_tiles) load_kv<T::kThreads>(p, cta.k, cta.v, j + 1, sk + (stage ^ 1) * kKBytes, sv + (stage ^ 1) * kVBytes, tid);
    cp_async_commit();
    cp_async_wait<1>();  // tile j has landed (tile j + 1 may be in flight)
    fence_proxy_async();
    __syncthreads();

    attend_tile(q_addr, smem_address(skj), smem_address(svj), scale, o, row_max, row_sum);
    __syncthreads();  // every warp is done with this stage before it is refilled
  }

  store_rows(p, o, row_sum, cta.m0 + 64 * wg, cta.row0, cta.head);
#else
  (void)p;  // built for another architecture: the host never launches it there
#endif
}


// -- warp-specialised variant: a producer warpgroup fills kStages key / value stages, the consumer
// warpgroups run free of each other (mbarriers, no CTA-wide barrier in the loop), so one's
// exponentials can overlap another's MMAs ------------------------------------------------------------
constexpr int kStages = 4;

// The producer is a whole warpgroup that hands registers to the consumers (setmaxnreg): registers
// are allocated per SM sub-partition (16K each; warp w runs on sub-partition w % 4), so a lone
// producer warp beside 12 consumer warps caps every thread at 128 registers, too few for the
// overlapped loop below; with the producer warpgroup at kProducerRegs the consumers get
// kConsumerRegs (152 with 3 consumer warpgroups, 232 with 2).
template <int kWG>
struct WsTile {
  static constexpr int kRows = 64 * kWG;
  static constexpr int kConsumers = 128 * kWG;
  static constexpr int kProducers = 128;
  static constexpr int kThreads = kConsumers + kProducers;
  static constexpr int kQBytes = kRows * kDPad * 2;
  static constexpr int kSmemBytes = kQBytes + kStages * (kKBytes + kVBytes) + 2 * kStages * 8;
  static constexpr int kProducerRegs = 56;  // 40 spilled the copy loop's addresses
  // a sub-partition's 512 registers a lane, less the producer's, shared by kWG consumer warps
  // (steps of 8; setmaxnreg takes at most 240 here: it must leave the producer its share)
  static constexpr int kConsumerShare = (512 - kProducerRegs) / kWG / 8 * 8;
  static constexpr int kConsumerRegs = kConsumerShare < 240 ? kConsumerShare : 240;
};

__device__ __forceinline__ void mbar_init(uint32_t bar, int count) {
  asm volatile("mbarrier.init.shared::cta.b64 [%0], %1;\n" ::"r"(bar), "r"(count) : "memory");
}
__device__ __forceinline__ void mbar_arrive(uint32_t bar) {
  asm volatile("mbarrier.arrive.shared::cta.b64 _, [%0];\n" ::"r"(bar) : "memory");
}
// Arrives on `bar` when this thread's earlier cp.async copies have landed (counts as one arrival).
__device__ __forceinline__ void mbar_arrive_copies(uint32_t bar) {
  asm volatile("cp.async.mbarrier.arrive.noinc.shared::cta.b64 [%0];\n" ::"r"(bar) : "memory");
}
__device__ __forceinline__ void mbar_wait(uint32_t bar, int parity) {
  asm volatile(
      "{\n.reg .pred done;\nWAIT:\n"
      "mbarrier.try_wait.parity.shared::cta.b64 done, [%0], %1;\n"
      "@!done bra WAIT;\n}\n" ::"r"(bar),
      "r"(parity)
      : "memory");
}
template <int N>
__device__ __forceinline__ void set_max_registers_dec() {
  asm volatile("setmaxnreg.dec.sync.aligned.u32 %0;\n" ::"n"(N));
}
template <int N>
__device__ __forceinline__ void set_max_registers_inc() {
  asm volatile("setmaxnreg.inc.sync.aligned.u32 %0;\n" ::"n"(N));
}

#if defined(__CUDA_ARCH_FEAT_SM90_ALL)
// A consumer warpgroup's key tiles with FlashAttention-3's intra-warpgroup overlap: QKᵀ of tile j
// and PV of tile j − 1 are issued together and tile j's softmax starts when QKᵀ is done, beside
// PV. S is rewritten in place, so the registers live across an MMA are S (64), P (32) and O (20).
// (ptxas places the wait for PV j − 1 after the first ~25 max instructions of the softmax, not
// after its exponentials, so the overlap is partial: with the FMA-pipe exponentials 0.85 ms against
// 0.86-0.87 without the overlap for the 12-row layer; the overlap alone was slower, 0.88.)
__device__ __forceinline__ void attend_overlapped(uint32_t q_addr, const unsigned char* sk, const unsigned char* sv,
                                                  uint32_t full0, uint32_t empty0, int n_tiles, float scale,
                                                  float (&o)[20], float (&row_max)[2], float (&row_sum)[2]) {
  float s[64], alpha[2];
  uint32_t pa[8][4];
  mbar_wait(full0, 0);
  fence_proxy_async();  // the producer's copies, visible now, before the MMAs read them
  issue_qk(s, q_addr, smem_address(sk));
  wgmma_wait<0>();
#pragma unroll
  for (int i = 0; i < 64; ++i) fence_register(s[i]);
  softmax_in_place<true>(s, scale, row_max, row_sum, alpha);
  pack_p(s, pa);
  for (int j = 1; j < n_tiles; ++j) {
    const int st = j % kStages, prev = (j - 1) % kStages;
    mbar_wait(full0 + 8 * st, (j / kStages) & 1);
    fence_proxy_async();
    issue_qk(s, q_addr, smem_address(sk + st * kKBytes));
    issue_pv(o, pa, smem_address(sv + prev * kVBytes));
    wgmma_wait<1>();  // S of tile j is complete; PV of tile j − 1 may still run
#pragma unroll
    for (int i = 0; i < 64; ++i) fence_register(s[i]);
    softmax_in_place<true>(s, scale, row_max, row_sum, alpha);
    wgmma_wait<0>();
#pragma unroll
    for (int i = 0; i < 20; ++i) fence_register(o[i]);
    mbar_arrive(empty0 + 8 * prev);
    rescale(o, alpha);
    pack_p(s, pa);
  }
  const int last = (n_tiles - 1) % kStages;
  issue_pv(o, pa, smem_address(sv + last * kVBytes));
  wgmma_wait<0>();
#pragma unroll
  for (int i = 0; i < 20; ++i) fence_register(o[i]);
  mbar_arrive(empty0 + 8 * last);
}
#endif

template <int kWG>
__global__ void __launch_bounds__(WsTile<kWG>::kThreads, 1) attention_head40_ws_kernel(const AttentionParams p) {
#if defined(__CUDA_ARCH_FEAT_SM90_ALL)
  using T = WsTile<kWG>;
  extern __shared__ __align__(128) unsigned char smem[];
  unsigned char* sq = smem;
  unsigned char* sk = smem + T::kQBytes;       // kStages stages
  unsigned char* sv = sk + kStages * kKBytes;  // kStages stages
  const uint32_t full0 = smem_address(sv + kStages * kVBytes), empty0 = full0 + kStages * 8;
  const int tid = threadIdx.x;
  const CtaRows cta = cta_rows(p, T::kRows);
  zero_pad_columns(sq, T::kRows, sk, kStages, tid, T::kThreads);
  if (tid == 0) {
    for (int s = 0; s < kStages; ++s) {
      mbar_init(full0 + 8 * s, T::kProducers);   // every producer thread, when its copies land
      mbar_init(empty0 + 8 * s, T::kConsumers);  // every consumer thread, when its MMAs have read it
    }
  }
  __syncthreads();
  const int n_tiles = p.L / kBlockN;

  if (tid >= T::kConsumers) {  // the producer warpgroup
    set_max_registers_dec<T::kProducerRegs>();
    const int lane = tid - T::kConsumers;
    for (int j = 0; j < n_tiles; ++j) {
      const int s = j % kStages;
      if (j >= kStages) mbar_wait(empty0 + 8 * s, (j / kStages - 1) & 1);
      load_kv<T::kProducers>(p, cta.k, cta.v, j, sk + s * kKBytes, sv + s * kVBytes, lane);
      mbar_arrive_copies(full0 + 8 * s);
    }
    cp_async_wait<0>();
  } else {
    set_max_registers_inc<T::kConsumerRegs>();
    const int wg = tid >> 7;
    load_q(p, cta, sq, 64 * wg, 64, tid & 127, 128);  // this warpgroup's 64 query rows
    cp_async_commit();
    cp_async_wait<0>();
    fence_proxy_async();
    asm volatile("bar.sync %0, 128;\n" ::"r"(1 + wg) : "memory");  // the warpgroup's Q rows are in

    float o[20];
#pragma unroll
    for (int i = 0; i < 20; ++i) o[i] = 0.f;
    const float neg_inf = -__int_as_float(0x7f800000);
    float row_max[2] = {neg_inf, neg_inf}, row_sum[2] = {0.f, 0.f};
    const uint32_t q_addr = smem_address(sq) + wg * 8 * kQKGroup;
    attend_overlapped(q_addr, sk, sv, full0, empty0, n_tiles, p.scale_log2, o, row_max, row_sum);
    store_rows(p, o, row_sum, cta.m0 + 64 * wg, cta.row0, cta.head);
  }
#else
  (void)p;
#endif
}

}  // namespace

bool attention_head40_available(int device) {
  // The kernel runs where the cubin loaded for `device` is an sm_90a one with its body (built for
  // another architecture the body is empty: a handful of registers). Known per device once.
  static int known[64] = {0};  // 0 unknown, 1 yes, 2 no
  if (device < 0 || device >= 64) return false;
  if (known[device] == 0) {
    int current = 0;
    cudaFuncAttributes attr{};
    const bool ok = cudaGetDevice(&current) == cudaSuccess && current == device &&
                    cudaFuncGetAttributes(&attr, attention_head40_kernel<1>) == cudaSuccess;
    if (!ok) {
      cudaGetLastError();
      return false;
    }
    known[device] = attr.binaryVersion == 90 && attr.numRegs >= 64 ? 1 : 2;
  }
  return known[device] == 1;
}

namespace {
template <int kWG>
cudaError_t launch(const AttentionParams& p, cudaStream_t stream) {
  using T = Tile<kWG>;
  const dim3 grid(static_cast<unsigned>((p.L + T::kRows - 1) / T::kRows), static_cast<unsigned>(p.heads),
                  static_cast<unsigned>(p.batch));
  const cudaError_t err =
      cudaFuncSetAttribute(attention_head40_kernel<kWG>, cudaFuncAttributeMaxDynamicSharedMemorySize, T::kSmemBytes);
  if (err != cudaSuccess) return err;
  attention_head40_kernel<kWG><<<grid, T::kThreads, T::kSmemBytes, stream>>>(p);
  return cudaGetLastError();
}
template <int kWG>
cudaError_t launch_ws(const AttentionParams& p, cudaStream_t stream) {
  using T = WsTile<kWG>;
  const dim3 grid(static_cast<unsigned>((p.L + T::kRows - 1) / T::kRows), static_cast<unsigned>(p.heads),
                  static_cast<unsigned>(p.batch));
  auto kernel = attention_head40_ws_kernel<kWG>;
  const cudaError_t err = cudaFuncSetAttribute(kernel, cudaFuncAttributeMaxDynamicSharedMemorySize, T::kSmemBytes);
  if (err != cudaSuccess) return err;
  kernel<<<grid, T::kThreads, T::kSmemBytes, stream>>>(p);
  return cudaGetLastError();
}
}  // namespace

cudaError_t attention_head40_cuda(const AttentionParams& p, bool producer, int warpgroups, cudaStream_t stream) {
  if (producer) {
    switch (warpgroups) {
      case 2: return launch_ws<2>(p, stream);
      case 3: return launch_ws<3>(p, stream);
      default: return cudaErrorInvalidValue;
    }
  }
  switch (warpgroups) {
    case 1: return launch<1>(p, stream);
    case 2: return launch<2>(p, stream);
    case 3: return launch<3>(p, stream);
    case 4: return launch<4>(p, stream);
    default: return cudaErrorInvalidValue;
  }
}

}  // namespace attention
}  // namespace tiger

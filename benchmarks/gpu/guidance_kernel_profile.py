"""Where the guidance step's GPU time goes, by kernel category: the eager InstructPix2Pix step
(camera pool: condition cached; fresh cameras) and the MVDream step with the package's default
model kernels (fused norms, channels-last, folded adds, fused GEGLU, 4x4 VAE downsampling),
full-size random models, bf16, 4 views of 512². Prints per call the kernel time per category
(convolutions, GroupNorm, GEMMs, element-wise, attention, tiger's other ops) and the top kernels.

    python -m benchmarks.gpu.guidance_kernel_profile        # CUDA only (about 1 minute)
"""
from __future__ import annotations

import collections

import torch

from benchmarks.common import cuda_kernel_names
from benchmarks.guidance import ring
from benchmarks.guidance_floor import default_cuda_guidances
from tiger.edit.guidance.base import ViewBatch

# first match wins: cuDNN's attention before its convolutions, cuBLAS (nvjet) after them
CATS = [("attention", ("flash", "fmha", "attention", "sdpa")),
        ("conv", ("conv", "xmma", "implicit", "cudnn", "dgrad", "wgrad", "fprop")),
        ("gemm", ("gemm", "cutlass", "cublas", "nvjet")),
        ("group_norm", ("group_norm", "groupnorm")),
        ("tiger other", ("tiger",)),
        ("elementwise", ("elementwise", "vectorized", "unrolled", "reduce", "fill", "copy", "cat", "softmax"))]


def category(name: str) -> str:
    """The category of a CUDA kernel's name (``"other"`` when none matches)."""
    low = name.lower()
    for cat, keys in CATS:
        if any(k in low for k in keys):
            return cat
    return "other"


def profile_calls(cases: dict, reps: int = 5) -> None:
    """Profile ``reps`` calls of each case after 3 warm-up calls; print the breakdown."""
    for name, fn in cases.items():
        per_cat, per_kernel, counts = collections.Counter(), collections.Counter(), collections.Counter()
        for kernel, ms in cuda_kernel_names(fn, reps, warmup=3):
            per_cat[category(kernel)] += ms
            per_kernel[kernel[:110]] += ms
            counts[kernel[:110]] += 1
        total = sum(per_cat.values())
        print(f"\n== {name}: GPU kernel time {total / reps:.2f} ms per call, "
              f"{sum(counts.values()) // reps} kernels per call")
        for cat, ms in per_cat.most_common():
            print(f"  {cat:14s} {ms / reps:7.2f} ms  {100 * ms / total:5.1f} %")
        print("  top kernels (ms per call, launches per call):")
        for k, ms in per_kernel.most_common(22):
            print(f"    {ms / reps:7.3f}  {counts[k] // reps:4d}  {k}")


def main() -> None:
    if not torch.cuda.is_available():
        raise SystemExit("benchmarks.gpu.guidance_kernel_profile needs CUDA")
    ip_models, mv_models, ip, mv = default_cuda_guidances()
    res = 512
    renders = torch.rand(4, 3, res, res, device="cuda")
    originals = torch.rand(4, 3, res, res, device="cuda")
    cams = ring(4, res)

    def views(pooled: bool) -> ViewBatch:
        return ViewBatch(cameras=cams, originals=originals, view_ids=torch.arange(4) if pooled else None,
                         step=0, total_steps=4, object_center=torch.zeros(3))

    profile_calls({"ip2p_pooled": lambda: ip.grad(renders, views(True)),
                   "ip2p_fresh": lambda: ip.grad(renders, views(False)),
                   "mvdream": lambda: mv.grad(renders, views(False))})


if __name__ == "__main__":
    main()

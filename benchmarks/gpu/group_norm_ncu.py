"""The VAE encoder's GroupNorm kernels under Nsight Compute: one eager InstructPix2Pix VAE encode
forward + backward (4 renders of 512², full-size random weights, bf16, the package's default model
kernels) between ``cudaProfilerStart``/``Stop``, for

    ncu --profile-from-start off --kernel-name-base demangled \\
        -k regex:"group_norm.*(apply_kernel|stats_kernel|backward_reduce_kernel|dx_kernel)" \\
        --section SpeedOfLight --section Occupancy --section LaunchStats --section WarpStateStats \\
        --section MemoryWorkloadAnalysis python -m benchmarks.gpu.group_norm_ncu > ncu.txt
    python -m benchmarks.gpu.group_norm_ncu --table ncu.txt      # one row per kernel launch

(CUDA only.) The table gives each launch's grid, duration, DRAM throughput (% of peak), achieved
and theoretical occupancy and registers per thread.
"""
from __future__ import annotations

import argparse
import re
from pathlib import Path

import torch


def profiled_pass() -> None:
    from benchmarks.guidance_floor import default_cuda_guidances
    from tiger.edit.guidance.diffusers_models import render_gradient, vae_downsampling_factor

    ip_models = default_cuda_guidances()[0]  # the guidances put the default kernels on the models
    res = 512
    lat = res // vae_downsampling_factor(ip_models.vae)
    renders = torch.rand(4, 3, res, res, device="cuda")
    noise = torch.randn(4, 4, lat, lat, device="cuda")
    grad = torch.randn(4, 4, lat, lat, device="cuda") * 1e-3
    for _ in range(2):  # cuDNN's algorithm choice and the allocator settle before the profiled pass
        render_gradient(ip_models.vae, renders, (res, res), noise, lambda z: grad)
    torch.cuda.synchronize()
    torch.cuda.cudart().cudaProfilerStart()
    render_gradient(ip_models.vae, renders, (res, res), noise, lambda z: grad)
    torch.cuda.synchronize()
    torch.cuda.cudart().cudaProfilerStop()


def table(path: Path) -> str:
    """One line per profiled launch of an ncu text report (the sections above)."""
    text = path.read_text()
    lines = ["kernel | grid | us | DRAM % | achieved occ. % | theoretical occ. % | registers"]
    for part in re.split(r"\n  void ", text)[1:]:
        head = part.split("\n")[0]
        name = re.search(r"(\w+_kernel)<([^(]*)", head)
        grid = re.search(r"\((\d+, \d+, \d+)\)x\((\d+), 1, 1\)", head)

        def metric(key: str) -> str:
            m = re.search(r"\n\s+" + re.escape(key) + r"\s+\S+\s+([\d.,]+)", part)
            return m.group(1) if m else "-"

        kernel = name.group(1) + "<" + name.group(2).replace("__nv_bfloat16, ", "") if name else head[:40]
        lines.append(" | ".join([kernel, grid.group(1) if grid else "-", metric("Duration"),
                                 metric("DRAM Throughput"), metric("Achieved Occupancy"),
                                 metric("Theoretical Occupancy"), metric("Registers Per Thread")]))
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--table", type=Path, default=None, help="print the table of this ncu report instead")
    args = ap.parse_args()
    if args.table is not None:
        print(table(args.table))
        return
    if not torch.cuda.is_available():
        raise SystemExit("benchmarks.gpu.group_norm_ncu: needs a CUDA device")
    profiled_pass()


if __name__ == "__main__":
    main()

"""The edit's densification step: one row surgery (``clone_and_split``) against the two it replaced
(``duplicate`` then ``split``), on the edit benchmark's scene.

Scene: the demo tabletop at ``--density`` (16 = 317,600 Gaussians, SH degree 3, 64-d ``lang``), the
ball's Gaussians trainable (41,600 at density 16) with warm Adam moments, an edit's statistics;
each call densifies the top 1 % of the trainable rows (``EditConfig.densify_fraction``), a random
half of them large enough to split. Prints milliseconds per densification (synchronised; median
and minimum of ``--repeats``, the two paths alternating, each call on a fresh copy of the
optimizer) and, on CUDA, the kernels, ATen ops and GPU time of one call; the error column is the
largest difference of any parameter, Adam moment, extra or statistic between the two paths (0: the
same rows, bit for bit; tests/recon/test_recon_strategy.py pins it).

    python -m benchmarks.densify                       # CPU, density 1
    python -m benchmarks.densify --device cuda --density 16
"""
from __future__ import annotations

import argparse
import copy
import statistics
import time

import torch

from benchmarks.common import print_table
from benchmarks.edit import demo_scene
from tiger.edit import resolve_target
from tiger.edit.config import DEFAULT_EDIT_LRS
from tiger.recon import SceneOptimizer
from tiger.recon.strategy import clone_and_split, duplicate, split


def optimizer(density: float, device: str) -> tuple[SceneOptimizer, dict]:
    """The edit's optimizer over the ball (warm moments) and a statistics dict (one row per Gaussian)."""
    scene, query = demo_scene(density, device)
    tgt = resolve_target(scene, query, tau=0.5)
    opt = SceneOptimizer(scene, dict(DEFAULT_EDIT_LRS), trainable=tgt.mask,
                         extras={"weight": tgt.mask.float()})
    g = torch.Generator(device=device).manual_seed(0)
    for leaf in opt._leaves.values():
        leaf.grad = torch.randn(leaf.shape, generator=g, device=device, dtype=leaf.dtype)
    opt.update()
    n = len(scene)
    state = {"grad_accum": torch.rand(n, generator=g, device=device), "count": torch.ones(n, device=device),
             "max_radii": torch.zeros(n, device=device)}
    return opt, state


def masks(opt: SceneOptimizer, fraction: float = 0.01) -> tuple[torch.Tensor, torch.Tensor]:
    tr = torch.nonzero(opt.trainable_mask()).reshape(-1)
    g = torch.Generator().manual_seed(1)
    pick = tr[torch.randperm(len(tr), generator=g)[: max(1, int(fraction * len(tr)))].to(tr.device)]
    want = torch.zeros(len(opt.scene), dtype=torch.bool, device=tr.device)
    want[pick] = True
    large = torch.zeros_like(want)
    large[pick[::2]] = True
    return want & ~large, want & large


def two_calls(opt, clone, split_mask, state, gen):
    cloned = duplicate(opt, clone, state)
    return cloned, split(opt, torch.cat([split_mask, split_mask.new_zeros(cloned)]), state, gen)


def flat(opt: SceneOptimizer, state: dict) -> list[torch.Tensor]:
    out = [v.detach() for v in opt.scene.params().values() if v is not None]
    out += list(opt.extras.values()) + list(state.values())
    out += [m for st in opt.optimizer.state.values() for m in st.values() if torch.is_tensor(m) and m.dim() > 0]
    return out


def run(args) -> list[dict]:
    dev = args.device
    base_opt, base_state = optimizer(args.density, dev)
    clone, split_mask = masks(base_opt)
    cuda = dev.startswith("cuda")
    paths = {"duplicate + split (two surgeries)": two_calls, "clone_and_split (one)": clone_and_split}
    times: dict[str, list[float]] = {name: [] for name in paths}
    ends, counts = {}, {}
    for r in range(args.repeats + 1):  # the paths alternate (allocator and clock drift hit both alike)
        for name in (list(paths) if r % 2 else list(paths)[::-1]):
            opt, state = copy.deepcopy(base_opt), {k: v.clone() for k, v in base_state.items()}
            gen = torch.Generator().manual_seed(2)
            if cuda:
                torch.cuda.synchronize()
            t0 = time.perf_counter()
            counts[name] = paths[name](opt, clone, split_mask, state, gen)
            if cuda:
                torch.cuda.synchronize()
            if r:  # the first round: lazy loading, the allocator's first blocks
                times[name].append(1e3 * (time.perf_counter() - t0))
            ends[name] = flat(opt, state)
    rows = []
    for name, fn in paths.items():
        row = {"path": name, "gaussians": len(base_opt.scene), "trainable": base_opt.num_trainable,
               "cloned": counts[name][0], "split": counts[name][1], "ms": statistics.median(times[name]),
               "min_ms": min(times[name])}
        if cuda:
            opt, state = copy.deepcopy(base_opt), {k: v.clone() for k, v in base_state.items()}
            with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CUDA,
                                                    torch.profiler.ProfilerActivity.CPU]) as prof:
                fn(opt, clone, split_mask, state, torch.Generator().manual_seed(2))
                torch.cuda.synchronize()
            ev = prof.key_averages()
            row["kernels"] = sum(e.count for e in ev if e.key == "cudaLaunchKernel")
            row["aten_ops"] = sum(e.count for e in ev if e.key.startswith("aten::"))
            row["gpu_ms"] = sum(e.self_device_time_total for e in ev if e.device_type == torch.autograd.DeviceType.CUDA) / 1e3
        rows.append(row)
    a, b = ends.values()
    err = max(float((x.double() - y.double()).abs().max()) if x.numel() else 0.0 for x, y in zip(a, b))
    for row in rows:
        row["max_abs_diff"] = err
    for row in rows:
        row["speedup"] = rows[0]["ms"] / row["ms"]
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cpu")
    p.add_argument("--density", type=float, default=1.0, help="demo scene density (16 = 317,600 Gaussians)")
    p.add_argument("--repeats", type=int, default=15)
    args = p.parse_args()
    print_table(run(args), f"densification of the edit's scene ({args.device}): ms per call, median of {args.repeats}")


if __name__ == "__main__":
    main()

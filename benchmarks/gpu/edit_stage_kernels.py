"""The edit loop's GPU kernels by stage: which kernels each stage of ``tiger.edit`` runs and for how
long, from torch.profiler, after a warm start.

The benchmark edit of ``benchmarks/edit.py`` (demo tabletop at density 16, 317,600 Gaussians, CSD
with full-size random-weight InstructPix2Pix + MVDream, bf16, CUDA graphs, 4 views of 512²) runs
``--warm`` steps, then ``--steps`` steps under the profiler. Every kernel, memset and copy is
assigned to the loop stage whose GPU range (the ``edit::<stage>`` annotations of
:class:`tiger.train.StageTimer`) it starts in; kernels on a stream other than the busiest one are
listed as ``side:<stage>`` (MVDream's and the view prefetch's side streams, autograd's backward
stream), and ``none`` collects those outside every stage. The GPU-side annotation of an
optimizer's ``step`` is listed like a kernel (``Optimizer.step#...``), so a stage's kernel sum may
exceed its span; a stage annotated on several streams (the guidance: InstructPix2Pix and MVDream)
adds their spans, so its span may exceed the wall time. Printed: wall and GPU-busy ms per step, each stage's GPU span, and per stage the
kernel total and the top kernels (ms per step, launches per step).

    python -m benchmarks.gpu.edit_stage_kernels [--view-pool 256] [--warm 40] [--steps 30]
"""
from __future__ import annotations

import argparse
import bisect
import collections
import time

import torch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--view-pool", type=int, default=256)
    ap.add_argument("--warm", type=int, default=40, help="steps before the profiled ones")
    ap.add_argument("--steps", type=int, default=30, help="profiled steps")
    ap.add_argument("--top", type=int, default=14, help="kernels listed per stage")
    a = ap.parse_args()
    from torch.autograd import DeviceType
    from torch.profiler import ProfilerActivity, profile

    from benchmarks.common import gpu_timeline
    from benchmarks.edit import build, demo_scene, edit_config, parser
    from tiger.edit import resolve_target
    from tiger.edit.loop import EditSession

    # the edit: benchmarks/edit.py's arguments and configuration, 1200 steps
    args = parser().parse_args(["--device", "cuda", "--density", "16", "--guidance", "ip2p+mvdream",
                                "--random-models", "full", "--dtype", "bf16", "--size", "512", "--cuda-graph",
                                "--steps", "1200", "--view-pool", str(a.view_pool)])
    scene, query = demo_scene(args.density, args.device)
    tgt = resolve_target(scene, query, tau=0.5)
    guidance, _ = build(args.guidance[0], scene, tgt.mask, args)
    cfg = edit_config(args)
    session = EditSession(scene, tgt, guidance, None, cfg)
    for _ in range(a.warm):
        session.step_once()
    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        t0 = time.perf_counter()
        for _ in range(a.steps):
            session.step_once()
        torch.cuda.synchronize()
        wall = time.perf_counter() - t0
    n = a.steps
    events = [e for e in prof.events() if e.device_type == DeviceType.CUDA]
    ranges = sorted((e.time_range.start, e.time_range.end, e.name[len("edit::"):]) for e in events
                    if e.name.startswith("edit::"))
    kernels = [e for e in events if not e.name.startswith("edit::")]
    busiest = collections.Counter(e.thread for e in kernels).most_common(1)[0][0]
    starts = [r[0] for r in ranges]
    per: dict[str, dict[str, list[float]]] = collections.defaultdict(lambda: collections.defaultdict(lambda: [0.0, 0]))
    for e in kernels:
        i = bisect.bisect_right(starts, e.time_range.start) - 1
        stage = ranges[i][2] if i >= 0 and e.time_range.start < ranges[i][1] else "none"
        if e.thread != busiest:
            stage = "side:" + stage
        cell = per[stage][e.name[:110]]
        cell[0] += e.time_range.end - e.time_range.start
        cell[1] += 1
    span: dict[str, float] = collections.defaultdict(float)
    for s, e, name in ranges:
        span[name] += e - s
    busy, _ = gpu_timeline((e.time_range.start, e.time_range.end, e.name) for e in kernels)
    print(f"pool {a.view_pool}, {n} steps after {a.warm}: wall {1e3 * wall / n:.2f} ms/step (under the profiler), "
          f"GPU busy {1e-3 * busy / n:.2f} ms/step")
    print("stage GPU spans ms/step:", {k: round(1e-3 * v / n, 3) for k, v in span.items()})
    for stage, cells in sorted(per.items(), key=lambda kv: -sum(v[0] for v in kv[1].values())):
        total = sum(v[0] for v in cells.values())
        print(f"== {stage}: kernels {1e-3 * total / n:.3f} ms/step, "
              f"{sum(v[1] for v in cells.values()) / n:.1f} launches/step")
        for name, (us, count) in sorted(cells.items(), key=lambda kv: -kv[1][0])[:a.top]:
            print(f"   {1e-3 * us / n:7.3f} {count / n:6.1f}  {name}")


if __name__ == "__main__":
    main()

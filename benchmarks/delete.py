"""Object deletion (``tiger.delete``): time per stage and the quality of the result.

Scene: the demo tabletop at ``--density`` (1 = ~20k Gaussians, 15 = ~300k), language features from
its labels (one fixed unit vector per object plus noise, as ``tiger demo`` builds them before
training), target "mug" (cosine > 0.5 to its label vector). ``--carve`` removes the table's
Gaussians under the mug first (a capture never sees them), so the deletion leaves a real hole
that seeds and the refit must fill. Views: ``--views`` cameras around the mug
(``tiger.delete.views_around``), OpenCV Telea inpainting (built in).

Stages: remove (retrieval + floater/unseen/appearance rules), render (before/after removal,
holes, hole weights), inpaint (OpenCV, per view in a window around the hole), refit
(``--steps`` SceneOptimizer steps on cropped views, densification). The error columns are the
result's quality: locality PSNR outside the object's footprint vs the scene before (the rest
must not change), hole PSNR vs the inpainted views, and the reprojection consistency of the fill
between neighbouring views (refit vs the raw 2D inpaints).

    python -m benchmarks.delete                                        # CPU, demo scene
    python -m benchmarks.delete --device cuda --density 15 --views 40 --size 640x480 --steps 300
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import torch

from benchmarks.common import print_table  # noqa: E402

from tiger.demo.run import label_features  # noqa: E402
from tiger.demo.scene import tabletop_scene  # noqa: E402
from tiger.delete import DeleteConfig, delete, views_around  # noqa: E402
from tiger.eval.reprojection import evaluate_delete  # noqa: E402
from tiger.retrieval import retrieve  # noqa: E402

MUG_AXIS = (-0.4, 0.1)  # the mug's (x, z) in the demo scene


def build(density: float, carve: bool, device: torch.device):
    lab = tabletop_scene(density)
    if carve:
        xz = lab.scene.means[:, [0, 2]] - torch.tensor(MUG_AXIS)
        lab = lab.subset(~((lab.labels == lab.names.index("table")) & (xz.norm(dim=1) < 0.1)))
    scene = lab.scene.clone()
    scene.lang = label_features(lab)
    mug = lab.labels == lab.names.index("mug")
    return scene.to(device), scene.lang[mug].mean(0), mug


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cpu")
    p.add_argument("--density", type=float, default=1.0)
    p.add_argument("--views", type=int, default=8)
    p.add_argument("--size", default="240x180")
    p.add_argument("--steps", type=int, default=100)
    p.add_argument("--carve", action="store_true")
    p.add_argument("--repeats", type=int, default=1, help="timed runs after one warm-up run")
    p.add_argument("--json", default=None, help="write the results here")
    a = p.parse_args()
    dev = torch.device(a.device)
    w, h = (int(v) for v in a.size.split("x"))
    scene, query, is_mug = build(a.density, a.carve, dev)
    r = retrieve(scene, query.to(dev), tau=0.5, negatives=None)
    cams = [c.to(dev) for c in views_around(r, a.views, w, h)]
    cfg = DeleteConfig(tau=0.5, steps=a.steps, background=(1.0, 1.0, 1.0))
    load0 = os.getloadavg()
    print(f"tiger.delete on {dev} ({torch.cuda.get_device_name(dev) if dev.type == 'cuda' else 'CPU'}, "
          f"{torch.get_num_threads()} threads): N={len(scene)} Gaussians, {a.views} views {w}x{h}, "
          f"{a.steps} refit steps, carve={a.carve}; load average {load0[0]:.1f}")
    delete(scene, r, cams, config=DeleteConfig(**{**vars(cfg), "steps": 2}), progress=False)  # warm-up
    runs = []
    for _ in range(max(a.repeats, 1)):
        c0, t0 = time.process_time(), time.perf_counter()
        res = delete(scene, r, cams, config=cfg, progress=False)
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)
        runs.append((time.perf_counter() - t0, time.process_time() - c0, res))
    wall, cpu, res = min(runs, key=lambda x: x[0])
    evaluate_delete(res, cfg.background)  # after the timing: the library call does no evaluation
    t, m, c = res.timings, res.metrics, res.counts
    print_table([{"stage": k, "seconds": round(t[k], 3)} for k in ("remove", "render", "inpaint", "refit", "total")],
                "time per stage (best of the timed runs)")
    print(f"wall {wall:.2f} s, process CPU {cpu:.2f} s; load average before {load0[0]:.1f}, "
          f"after {os.getloadavg()[0]:.1f}")
    print_table([{"quality": k, "value": v} for k, v in m.items()], "quality of the result")
    print("counts: " + ", ".join(f"{k} {v}" for k, v in c.items()))
    removed_mug = int((res.removal.mask & is_mug.to(res.removal.mask.device)).sum())
    print(f"mug Gaussians removed: {removed_mug} of {int(is_mug.sum())}")
    if dev.type == "cuda":
        print(f"peak GPU memory {torch.cuda.max_memory_allocated(dev) / 2**30:.2f} GiB")
    if a.json:
        Path(a.json).write_text(json.dumps({
            "device": str(dev), "gaussians": len(scene), "views": a.views, "size": [w, h], "steps": a.steps,
            "carve": a.carve, "wall_s": wall, "cpu_s": cpu, "timings_s": t, "metrics": m, "counts": c,
            "load_before": load0, "load_after": os.getloadavg(), "threads": torch.get_num_threads(),
            "all_runs_wall_s": [x[0] for x in runs]}, indent=2))


if __name__ == "__main__":
    main()

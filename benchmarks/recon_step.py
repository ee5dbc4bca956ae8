"""SceneOptimizer: time per step and optimizer-state bytes, every Gaussian trainable vs a region.

    python -m benchmarks.recon_step                      # CPU, N=20000, 128x128, SH degree 3
    python -m benchmarks.recon_step --device cuda --n 1000000 --size 512

A random scene is fitted to one fixed image (photometric loss) for ``--steps`` steps per
setting; frozen rows are checked bit-identical afterwards. The rasterizer dominates the
step; what the mask saves is the optimizer's work and memory (state proportional to the
trainable count).
"""
from __future__ import annotations

import argparse
import time

import torch


def main(argv: list | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--n", type=int, default=20_000)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--fractions", default="1.0,0.1,0.01", help="trainable fractions")
    args = ap.parse_args(argv)

    from tiger.recon import SceneOptimizer, photometric_loss
    from tiger.render.views import look_at
    from tiger.render import Camera
    from tiger.scene import GaussianScene
    from tiger.scene.cameras import intrinsics

    dev = torch.device(args.device)
    g = torch.Generator().manual_seed(0)
    base = GaussianScene.random_in_box(args.n, [-1, -1, -1], [1, 1, 1], sh_degree=3, generator=g)
    base.log_scales = base.log_scales - 1.5
    base = base.to(dev)
    s = args.size
    cam = Camera(look_at((0.0, -4.0, 1.0), (0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)).double(),
                 intrinsics(1.2 * s, 1.2 * s, s / 2, s / 2), s, s).to(dev, torch.float32)
    target = torch.rand(s, s, 3, generator=g).to(dev)
    lrs = {"means": 1e-4, "log_scales": 5e-3, "quats": 1e-3, "opacity_logits": 5e-2, "sh_dc": 2.5e-3,
           "sh_rest": 1.25e-4}

    def render(scene, _):
        return scene.render(cam, check_finite=False)

    def loss(out, tgt):
        return photometric_loss(out["color"], tgt)

    def sync():
        if dev.type == "cuda":
            torch.cuda.synchronize()

    print(f"N={args.n}, {s}x{s}, SH 3, device {args.device}, {torch.get_num_threads()} CPU threads\n")
    print("| trainable | rows | ms / step | optimizer state (MB) | bytes / trainable row | frozen rows unchanged |")
    print("|---:|---:|---:|---:|---:|---|")
    for frac in (float(f) for f in args.fractions.split(",")):
        mask = torch.rand(args.n, generator=g) < frac
        scene = base.clone()
        opt = SceneOptimizer(scene, lrs, trainable=None if frac >= 1 else mask.to(dev))
        opt.step(loss, target, render)                                  # warm-up (allocations, state)
        sync()
        t0 = time.perf_counter()
        for _ in range(args.steps):
            opt.step(loss, target, render)
        sync()
        ms = 1e3 * (time.perf_counter() - t0) / args.steps
        m = opt.num_trainable
        frozen = ~opt.trainable_mask()
        same = all(torch.equal(getattr(scene, n)[frozen], getattr(base, n)[frozen]) for n in lrs)
        b = opt.optimizer_state_bytes()
        print(f"| {100 * frac:g} % | {m} | {ms:.1f} | {b / 2**20:.2f} | {b / max(m, 1):.0f} | "
              f"{'yes' if same else 'NO'} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

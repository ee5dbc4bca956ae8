"""Training-free lifting against training the language field, on the synthetic labelled scene:
precision / recall of lift only, lift + training and training only, the training given the same
total time; then (``--views``/``--gaussians``) the lifting time on a random scene of the fox's size.

    python -m benchmarks.lift                                   # CPU, synthetic scene only
    python -m benchmarks.lift --device cuda --gaussians 250000 --views 43 --size 1080x1920
"""
from __future__ import annotations

import argparse
import time

import torch


def precision_recall(ls) -> tuple[float, float]:
    from tiger.retrieval import retrieve

    ps, rs = [], []
    for i, name in enumerate(ls.labelled.names):
        r = retrieve(ls.scene, name, encoder=ls.encoder)
        gt = (ls.labelled.labels == i).to(r.mask.device)
        tp = int((r.mask & gt).sum())
        ps.append(tp / max(r.count, 1))
        rs.append(tp / int(gt.sum()))
    return min(ps), min(rs)


def synthetic(device: str, lr: float, batch_views: int) -> None:
    from tiger.language.field import train_field
    from tiger.language.lift import lift
    from tiger.testing.labelled_scene import make_labelled_scene, oracle_feature_maps

    ls = make_labelled_scene()
    ls.labelled.scene = ls.scene.to(device)
    ls.labelled.labels = ls.labelled.labels.to(device)
    maps = oracle_feature_maps(ls)
    pca = (ls.scene.lang_pca_basis, ls.scene.lang_pca_mean)
    kw = dict(pca=pca, lr=lr, batch_views=batch_views, progress=False)
    lift(ls.scene, ls.cameras, maps)  # warm-up
    lifted = lift(ls.scene, ls.cameras, maps)
    ls.scene.lang = lifted.lang
    rows = [("lift only", lifted.seconds, 0, *precision_recall(ls))]
    for steps in (10, 20, 40, 60):
        ls.scene.lang = None
        t0 = time.perf_counter()
        train_field(ls.scene, ls.cameras, maps, steps=steps, init="random", **kw)
        t_train = time.perf_counter() - t0
        rows.append(("training only", t_train, steps, *precision_recall(ls)))
        per_step = t_train / steps
        left = max(0, round((t_train - lifted.seconds) / per_step))  # the same total time
        ls.scene.lang = lifted.lang.clone()
        t0 = time.perf_counter()
        train_field(ls.scene, ls.cameras, maps, steps=left, init="keep", **kw)
        rows.append(("lift + training", lifted.seconds + time.perf_counter() - t0, left, *precision_recall(ls)))
    print(f"synthetic labelled scene ({len(ls.scene)} Gaussians, {len(ls.cameras)} views of 48x48), device {device}; "
          "precision/recall: the worst label")
    print("| method | seconds | training steps | precision | recall |\n|---|---:|---:|---:|---:|")
    for name, sec, steps, p, r in rows:
        print(f"| {name} | {sec:.3f} | {steps} | {p:.3f} | {r:.3f} |")


def timing(device: str, n: int, views: int, size: str, dim: int) -> None:
    from tiger.language.lift import lift
    from tiger.render.views import orbit_cameras_around
    from tiger.scene import GaussianScene

    h, w = (int(v) for v in size.split("x"))
    scene = GaussianScene.random_in_box(n, (-1, -1, -1), (1, 1, 1), sh_degree=0).to(device)
    cams = orbit_cameras_around(scene.means, views, w, h)
    g = torch.Generator().manual_seed(0)
    maps = [(torch.randn(h, w, dim, generator=g).half(), torch.ones(h, w, dtype=torch.bool)) for _ in range(2)]
    load = lambda i: maps[i % 2]  # noqa: E731
    lift(scene, cams[:2], load)  # warm-up
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    res = lift(scene, cams, load)
    print(f"lifting {n} Gaussians from {views} maps of {w}x{h}x{dim} (float16, on the host): {res.seconds:.2f} s "
          f"({res.seconds / views * 1e3:.0f} ms a view, host-to-device copy included), device {device}")


def main(argv: list | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--lr", type=float, default=0.05)
    ap.add_argument("--batch-views", type=int, default=2)
    ap.add_argument("--gaussians", type=int, default=0, help="also time lifting on a random scene of this size")
    ap.add_argument("--views", type=int, default=43)
    ap.add_argument("--size", default="1080x1920", help="HxW of the maps for the timing")
    ap.add_argument("--dim", type=int, default=64)
    args = ap.parse_args(argv)
    synthetic(args.device, args.lr, args.batch_views)
    if args.gaussians:
        timing(args.device, args.gaussians, args.views, args.size, args.dim)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

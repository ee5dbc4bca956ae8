"""Precision and recall of text selection against labels, per object and phrasing, per threshold rule.

The demo's tabletop (``tiger demo`` writes ``OUT/scene.ply`` and ``OUT/text_embeddings.pt``; its
Gaussians are in the order of ``tiger.demo.scene.tabletop_scene()``) and synthetic labelled
scenes with trained fields. Recall is reported over every labelled Gaussian and over the ones the
language field saw (a feature norm of at least 0.1 x the median).

    python -m benchmarks.selection_labelled --demo outputs/demo --rules auto valley

With ``--delete``, each demo object is also deleted as ``tiger delete`` does with its defaults (12
views around the object at 320x240, 150 refit steps, OpenCV inpainting) and a second table gives,
per deleted object, the Gaussians of every other object kept, the deleted object's Gaussians
left, and two pixel measures over the views: the share of the pixels where the object was seen
that still show one of its colours (within 0.2) after the deletion, and the share of the pixels
where another object was seen (outside the deleted one's footprint) that changed by 0.1 or more.
``--delete-out DIR`` writes each deletion's folder (before/after pictures) there.

    python -m benchmarks.selection_labelled --demo outputs/demo --rules auto --no-synthetic --delete
"""
from __future__ import annotations

import argparse

import torch


def _row(name: str, phrase: str, rule: str, r, truth: torch.Tensor, seen: torch.Tensor) -> str:
    tp = int((r.mask & truth).sum())
    p = tp / max(r.count, 1)
    rec = tp / max(int(truth.sum()), 1)
    rec_seen = int((r.mask & truth & seen).sum()) / max(int((truth & seen).sum()), 1)
    return f"| {name} | {phrase} | {rule} | {r.tau:.3f} | {r.count} | {p:.3f} | {rec:.3f} | {rec_seen:.3f} |"


def _seen(scene) -> torch.Tensor:
    norms = scene.lang.detach().norm(dim=1)
    return norms >= 0.1 * norms.median()


def demo_rows(folder: str, rules: list[str]) -> list[str]:
    from tiger.demo.language import SYNONYMS
    from tiger.demo.scene import tabletop_scene
    from tiger.retrieval import EmbeddingTable, retrieve
    from tiger.scene import GaussianScene

    scene = GaussianScene.load_ply(f"{folder}/scene.ply")
    labelled = tabletop_scene(1.0)
    if not torch.allclose(labelled.scene.means, scene.means):
        raise SystemExit(f"{folder}/scene.ply is not the demo's tabletop at density 1")
    enc = EmbeddingTable.load(f"{folder}/text_embeddings.pt")
    seen, rows = _seen(scene), []
    for i, name in enumerate(labelled.names):
        for phrase in SYNONYMS[name]:
            for rule in rules:
                rows.append(_row(name, phrase, rule, retrieve(scene, phrase, encoder=enc, tau=rule),
                                 labelled.labels == i, seen))
    return rows


#: The demo objects' colours (tiger.demo.scene), for the remnant measure.
DEMO_COLOURS = {"table": [(0.55, 0.36, 0.2), (0.4, 0.26, 0.15)], "mug": [(0.93, 0.93, 0.9), (0.85, 0.1, 0.1)],
                "ball": [(0.1, 0.3, 0.85), (0.95, 0.8, 0.1)], "box": [(0.78, 0.6, 0.35)],
                "plant": [(0.15, 0.6, 0.18)]}  # not the pot: its terracotta is within 0.2 of the table


def _seen_by(scene, part: torch.Tensor, cams) -> torch.Tensor:
    """[V, H, W] bool: where the Gaussians ``part`` [N] bool make most of the pixel."""
    ch = part.float()[:, None].expand(-1, 3).contiguous()
    with torch.no_grad():
        return torch.stack([scene.render(c, ch)["color"][..., 0] for c in cams]) > 0.5


def delete_rows(folder: str, out: str | None) -> list[str]:
    """One row per demo object: its deletion at `tiger delete`'s defaults against the labels."""
    from tiger.delete import DeleteConfig, delete, views_around
    from tiger.demo.scene import tabletop_scene
    from tiger.eval.reprojection import evaluate_delete
    from tiger.retrieval import EmbeddingTable, check_selection, retrieve
    from tiger.scene import GaussianScene

    scene = GaussianScene.load_ply(f"{folder}/scene.ply")
    labelled = tabletop_scene(1.0)
    enc = EmbeddingTable.load(f"{folder}/text_embeddings.pt")
    names, labels = labelled.names, labelled.labels
    rows = []
    for k, name in enumerate(names):
        r = retrieve(scene, name, encoder=enc)
        guard = check_selection(scene.means, r.mask)
        cams = views_around(r, 12, 320, 240)
        res = delete(scene, r, cams, config=DeleteConfig(), progress=False)
        evaluate_delete(res, (0.0, 0.0, 0.0))
        if out:
            res.save(f"{out}/delete_{name}", extra={"text": name})
        removed = res.removal.mask
        kept = ", ".join(f"{n} {int((~removed & (labels == i)).sum())}/{int((labels == i).sum())}"
                         for i, n in enumerate(names) if i != k)
        left = int((~removed & (labels == k)).sum())
        seen = _seen_by(scene, labels == k, cams)
        remnant = max(float(((res.after - torch.tensor(rgb)).abs().amax(-1) < 0.2)[seen].float().mean())
                      for rgb in DEMO_COLOURS[name])
        others = _seen_by(scene, (labels != k) & (labels != 0), cams) & ~res.footprint
        changed = float(((res.after - res.before).abs().amax(-1) >= 0.1)[others].float().mean()) \
            if bool(others.any()) else 0.0
        rows.append(f"| {name} | {'ok' if guard.ok else guard.problem} | {kept} | {left}/{int((labels == k).sum())} | "
                    f"{remnant:.4f} | {changed:.4f} | {res.metrics.get('locality_psnr', float('nan')):.1f} |")
        print(rows[-1], flush=True)
    return rows


def synthetic_rows(rules: list[str]) -> list[str]:
    from tiger.language.field import train_field
    from tiger.retrieval import retrieve
    from tiger.testing.labelled_scene import make_labelled_scene, oracle_feature_maps

    rows = []
    for labels in [("red mug", "teddy bear", "green apple", "blue book"),
                   ("lamp", "chair", "vase", "shoe", "clock", "plate")]:
        torch.manual_seed(0)
        ls = make_labelled_scene(labels, seed=1)
        train_field(ls.scene, ls.cameras, oracle_feature_maps(ls), steps=60, init="random",
                    pca=(ls.scene.lang_pca_basis, ls.scene.lang_pca_mean), lr=0.05, batch_views=2, progress=False)
        seen = _seen(ls.scene)
        for i, name in enumerate(ls.labelled.names):
            for rule in rules:
                rows.append(_row(name, name, rule, retrieve(ls.scene, name, encoder=ls.encoder, tau=rule),
                                 ls.labelled.labels == i, seen))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--demo", default=None, help="folder written by `tiger demo` (skip: none)")
    ap.add_argument("--rules", nargs="+", default=["auto", "valley"])
    ap.add_argument("--no-synthetic", action="store_true")
    ap.add_argument("--delete", action="store_true", help="also delete each demo object (needs --demo)")
    ap.add_argument("--delete-out", default=None, help="write each deletion's folder here")
    args = ap.parse_args()
    print("| object | text | tau rule | tau | selected | precision | recall | recall (seen) |")
    print("| --- | --- | --- | ---: | ---: | ---: | ---: | ---: |")
    rows = (demo_rows(args.demo, args.rules) if args.demo else []) + \
        ([] if args.no_synthetic else synthetic_rows(args.rules))
    print("\n".join(rows))
    if args.delete and args.demo:
        print("\n| deleted | guard | other objects' Gaussians kept | its Gaussians left | its colours left "
              "(share of its pixels) | other objects' pixels changed | locality PSNR dB |")
        print("| --- | --- | --- | ---: | ---: | ---: | ---: |")
        delete_rows(args.demo, args.delete_out)


if __name__ == "__main__":
    main()

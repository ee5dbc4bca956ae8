"""Precision and recall of text selection against labels, per object and phrasing, per threshold rule.

The demo's tabletop (``tiger demo`` writes ``OUT/scene.ply`` and ``OUT/text_embeddings.pt``; its
Gaussians are in the order of ``tiger.demo.scene.tabletop_scene()``) and synthetic labelled
scenes with trained fields. Recall is reported over every labelled Gaussian and over the ones the
language field saw (a feature norm of at least 0.1 x the median).

    python benchmarks/selection_labelled.py --demo outputs/demo --rules auto valley
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


def synthetic_rows(rules: list[str]) -> list[str]:
    from tiger.language.field import train_field
    from tiger.retrieval import retrieve
    from tiger.retrieval.synthetic import make_labelled_scene, oracle_feature_maps

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
    args = ap.parse_args()
    print("| object | text | tau rule | tau | selected | precision | recall | recall (seen) |")
    print("| --- | --- | --- | ---: | ---: | ---: | ---: | ---: |")
    rows = (demo_rows(args.demo, args.rules) if args.demo else []) + \
        ([] if args.no_synthetic else synthetic_rows(args.rules))
    print("\n".join(rows))


if __name__ == "__main__":
    main()

#!/usr/bin/env python
"""Evaluate language-embedded scenes on a LERF-OVS-layout dataset (paper Table 1).

The LERF-OVS release (LangSplat's) is laid out as::

    ROOT/label/<scene>/frame_00041.json   LabelMe-style boxes and polygons per test frame
    ROOT/label/<scene>/frame_00041.jpg
    ROOT/<scene>/                          the capture: COLMAP (sparse/0, images/) or transforms.json

For every scene in ``ROOT/label`` (or those named with ``--scenes``) this script loads the
trained scene from ``--ply`` (a pattern with ``{scene}``, e.g. ``outputs/{scene}/scene_lang.ply``,
holding ``lang_*`` and the PCA basis), renders the relevancy of every labelled category at each
labelled frame's camera, and scores it with :mod:`tiger.eval.lerf`: localization accuracy (the
smoothed relevancy maximum falls in a box of the category) and LangSplat's mIoU. It prints the
table next to the published numbers and writes ``OUT/results.json``, ``OUT/table.md`` and one
picture per query.

The text encoder is CLIP (``--clip`` folder, or found through ``--models``/``$TIGER_MODELS``),
or a saved table ``{text: embedding}`` (``--text-embeddings``) computed elsewhere.

Example::

    python examples/evaluate_lerf.py data/lerf_ovs --ply "outputs/{scene}/scene_lang.ply" \\
        --out outputs/lerf_eval
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Any, Optional, Sequence

import torch

log = logging.getLogger("evaluate_lerf")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                epilog="example: python examples/evaluate_lerf.py data/lerf_ovs "
                                       "--ply 'outputs/{scene}/scene_lang.ply' --out outputs/lerf_eval")
    p.add_argument("root", help="LERF-OVS root: label/<scene>/ and <scene>/ (the captures)")
    p.add_argument("--ply", required=True, help="scene PLY path pattern with {scene}")
    p.add_argument("--out", required=True, help="output folder (results.json, table.md, pictures)")
    p.add_argument("--scenes", nargs="+", default=None, help="scene names (default: all in ROOT/label)")
    p.add_argument("--data", default="{root}/{scene}",
                   help="capture path pattern (COLMAP folder or transforms.json; default: %(default)s)")
    enc = p.add_mutually_exclusive_group()
    enc.add_argument("--clip", default=None, help="CLIP folder (save_pretrained layout) for the text encoder")
    enc.add_argument("--text-embeddings", default=None, help="torch.save'd {text: [F] tensor}")
    p.add_argument("--models", default=None, help="model config JSON {name: path} (default: $TIGER_MODELS)")
    p.add_argument("--score", choices=("relevancy", "cosine"), default="relevancy")
    p.add_argument("--filter-size", type=int, default=30, help="mean filter size of the metric")
    p.add_argument("--mask-thresh", type=float, default=0.4, help="mIoU mask threshold")
    p.add_argument("--no-pictures", action="store_true")
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    return p


def text_encoder(args: argparse.Namespace) -> Any:
    """The encoder of the category names: an embedding table, or CLIP's text tower."""
    from tiger.retrieval.text import EmbeddingTable

    if args.text_embeddings:
        return EmbeddingTable.load(args.text_embeddings)
    from tiger.language.maskclip import MaskCLIP
    from tiger.models.paths import resolve_model_path

    return MaskCLIP.from_pretrained(resolve_model_path("clip", args.clip, config=args.models), device=args.device)


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    from tiger.eval import lerf
    from tiger.scene import GaussianScene
    from tiger.scene.dataset import load_dataset

    root = Path(args.root)
    label_root = root / "label"
    if not label_root.is_dir():
        raise SystemExit(f"evaluate_lerf: {label_root} does not exist (expected ROOT/label/<scene>/*.json)")
    if "{scene}" not in args.ply:
        raise SystemExit(f"evaluate_lerf: --ply must contain {{scene}}, got '{args.ply}'")
    names = args.scenes or sorted(p.name for p in label_root.iterdir() if p.is_dir())
    if not names:
        raise SystemExit(f"evaluate_lerf: no scene folders in {label_root}")
    for name in names:  # every input checked before the slow steps
        missing = [f"{what} {p}" for what, p in (("label folder", label_root / name),
                                                  ("PLY", Path(args.ply.format(scene=name))),
                                                  ("capture", Path(args.data.format(root=root, scene=name))))
                   if not p.exists()]
        if missing:
            raise SystemExit(f"evaluate_lerf: scene '{name}': {', '.join(missing)} not found")
    encoder = text_encoder(args)
    results = []
    for name in names:
        ply = Path(args.ply.format(scene=name))
        data = Path(args.data.format(root=root, scene=name))
        scene = GaussianScene.load_ply(ply).to(args.device)
        if scene.lang is None:
            raise SystemExit(f"evaluate_lerf: {ply} has no language features (lang_*); train them first")
        labels = lerf.load_scene_labels(label_root / name)
        cams = [c.to(args.device) for c in load_dataset(data).cameras]
        fn = lerf.scene_relevancy_fn(scene, cams, labels, encoder=encoder, score=args.score)
        results.append(lerf.evaluate_scene(name, labels, fn, out_dir=args.out, size=args.filter_size,
                                           mask_thresh=args.mask_thresh, pictures=not args.no_pictures))
    print(lerf.format_table(results))
    j, t = lerf.write_results(results, args.out)
    print(f"\nwrote {j} and {t}")
    return 0


def cli(argv: Optional[Sequence[str]] = None) -> int:
    """``main`` with bad input reported in one line (SystemExit with the message), no traceback."""
    from tiger.scene import SceneFormatError

    try:
        return main(argv)
    except (SceneFormatError, FileNotFoundError, KeyError) as exc:
        raise SystemExit(f"evaluate_lerf: {exc}") from exc


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    sys.exit(cli())

#!/usr/bin/env python
"""Language-embed a COLMAP scene and query it with text: the TIGER pipeline in one script.

Steps (SPEC §4, paper §3):

1. extract per-pixel 64-d language feature maps of the dataset's images (MaskCLIP dense CLIP
   features, FeatUp upsampling, SAM masked averages, one PCA over all images), cached under
   ``OUT/features`` so a second run resumes;
2. train each Gaussian's language embedding L with the geometry frozen (features-only backward)
   and write ``OUT/scene_lang.ply`` (with ``lang_*`` and the PCA basis);
3. for every ``--query``: select the Gaussians whose cosine (or LERF relevancy) passes ``--tau``,
   write heat maps of the query in a few training views (``OUT/heatmaps``) and the selected
   Gaussians as ``OUT/selection_<query>.ply``.

Model weights are found as :mod:`tiger.models` finds them: ``--models`` (a folder laid out like
``$TIGER_MODELS`` or a JSON file ``{name: path}``), else ``$TIGER_MODELS``. ``--random-models``
builds tiny randomly initialised CLIP and SAM of the same architectures instead: a smoke run
of the whole pipeline without weights (the retrieved selection is then meaningless).

Example::

    python examples/embed_and_query_colmap.py data/figurines outputs/figurines/scene.ply \\
        --out outputs/figurines/query --query "rubber duck" --query "green apple"
"""
from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path
from typing import Any, Optional, Sequence

import torch

log = logging.getLogger("embed_and_query_colmap")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                epilog="example: python examples/embed_and_query_colmap.py data/figurines "
                                       "scene.ply --out outputs/q --query 'rubber duck'")
    p.add_argument("data", help="COLMAP scene folder (sparse/0 + images/)")
    p.add_argument("ply", help="the trained Gaussian scene of that capture (INRIA-layout PLY)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--query", action="append", required=True, help="a text query (repeat for several)")
    p.add_argument("--images", default="images", help="image folder inside DATA (default: images)")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--models", default=None,
                     help="model folder (laid out like $TIGER_MODELS) or JSON config {name: path}")
    src.add_argument("--random-models", action="store_true",
                     help="tiny random-init CLIP and SAM (smoke run without weights)")
    p.add_argument("--upsampler", choices=("implicit", "jbu", "bilinear"), default="implicit",
                   help="FeatUp implicit (the paper's), JBU (needs its checkpoint) or bilinear")
    p.add_argument("--no-sam", action="store_true", help="skip SAM's masked average")
    p.add_argument("--sam-points", type=int, default=32, help="SAM point grid per side")
    p.add_argument("--feature-long-side", type=int, default=None,
                   help="feature-map long side in pixels (default: each image's own size)")
    p.add_argument("--clip-long-side", type=int, default=448)
    p.add_argument("--pca-dim", type=int, default=64, help="language dimension D (64 in TIGER)")
    p.add_argument("--steps", type=int, default=3000, help="language-field training steps")
    p.add_argument("--lr", type=float, default=2.5e-3)
    p.add_argument("--score", choices=("cosine", "relevancy"), default="cosine")
    p.add_argument("--tau", default="auto", help="selection threshold, or 'auto' (Otsu / 0.5)")
    p.add_argument("--heatmap-views", type=int, default=2, help="training views drawn per query")
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    return p


def model_config(args: argparse.Namespace, out: Path) -> Optional[Any]:
    """What to pass as ``models`` to :mod:`tiger.models` (None: ``$TIGER_MODELS``)."""
    if args.random_models:
        from tiger.testing.random_models import save_random_clip, save_random_sam

        root = out / "random_models"
        clip_dir, sam_dir = root / "clip-vit-base-patch16", root / "sam-vit-huge"
        if not (clip_dir / "config.json").is_file():
            save_random_clip(clip_dir)
        if not (sam_dir / "config.json").is_file():
            save_random_sam(sam_dir)
        return {"clip": str(clip_dir), "sam": str(sam_dir)}
    if args.models is None:
        return None
    path = Path(args.models).expanduser()
    if path.is_dir():  # a $TIGER_MODELS-style root: resolve every model inside it
        from tiger.models.paths import REGISTRY, ModelNotFoundError, resolve_model_path

        os.environ["TIGER_MODELS"] = str(path)
        cfg = {}
        for name in REGISTRY:
            try:
                cfg[name] = str(resolve_model_path(name))
            except ModelNotFoundError:
                pass  # reported by the loader that needs it, with every place looked at
        return cfg
    if path.is_file():
        return str(path)
    raise SystemExit(f"embed_and_query_colmap: --models {path} is neither a folder nor a JSON file")


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    from tiger.language.extract import FeatureConfig, extract_features
    from tiger.language.field import train_field
    from tiger.language.maskclip import MaskCLIP
    from tiger.language.sam_masks import SamMaskConfig
    from tiger.models.paths import resolve_model_path
    from tiger.retrieval import retrieve, write_relevancy_pictures
    from tiger.scene import GaussianScene
    from tiger.scene.dataset import load_colmap
    from tiger.utils.io import file_slug

    data, ply, out = Path(args.data), Path(args.ply), Path(args.out)
    if not data.is_dir():
        raise SystemExit(f"embed_and_query_colmap: COLMAP folder not found: {data}")
    if not ply.is_file():
        raise SystemExit(f"embed_and_query_colmap: PLY file not found: {ply}")
    tau: Any = args.tau if args.tau == "auto" else float(args.tau)
    dev = torch.device(args.device)
    out.mkdir(parents=True, exist_ok=True)

    cams = load_colmap(data, images=args.images).cameras
    scene = GaussianScene.load_ply(ply).to(dev)
    print(f"{len(cams)} cameras from {data}; {scene!r}")
    models = model_config(args, out)
    clip_path = resolve_model_path("clip", config=models)  # fail early, before the slow steps
    clip = MaskCLIP.from_pretrained(clip_path, device=dev)
    proj_dim = int(clip.clip.config.projection_dim)
    if args.pca_dim > proj_dim:
        log.warning("--pca-dim %d exceeds CLIP's %d dims: using %d", args.pca_dim, proj_dim, proj_dim)
    cfg = FeatureConfig(upsampler=args.upsampler, use_sam=not args.no_sam,
                        clip_long_side=args.clip_long_side, output_long_side=args.feature_long_side,
                        pca_dim=min(args.pca_dim, proj_dim),
                        sam=SamMaskConfig(points_per_side=args.sam_points))
    names = [str(c.image_name).replace("/", "_") for c in cams]
    fs = extract_features([c.image_path for c in cams], out / "features", names=names, config=cfg,
                          clip=clip, models=models, device=dev)

    cams = [c.to(device=dev) for c in cams]
    res = train_field(scene, cams, lambda i: fs.load(names[i]), pca=fs.pca,
                      checkpoint=out / "field.ckpt.pt", steps=args.steps, lr=args.lr)
    scene.save_ply(out / "scene_lang.ply")
    print(f"language field: loss {res.losses[0]:.4f} -> {res.losses[-1]:.4f}; "
          f"scene with lang_* -> {out / 'scene_lang.ply'}")

    for q in args.query:
        r = retrieve(scene, q, encoder=clip, score=args.score, tau=tau)
        # the views that see the selection best; all training views when nothing was selected
        order = _views_by_coverage(scene, r.mask, cams) if r.count else list(range(len(cams)))
        views = [cams[i] for i in order[:args.heatmap_views]]
        pics = write_relevancy_pictures(scene, views, q, out / "heatmaps", encoder=clip, score=args.score)
        sel_path = out / f"selection_{file_slug(q)}.ply"
        r.subscene(scene).save_ply(sel_path)
        print(f"'{q}': {r.count} of {len(scene)} Gaussians ({args.score} > {r.tau:.3f}) -> {sel_path}; "
              f"heat maps: {', '.join(p.name for p in pics)}")
    return 0


def _views_by_coverage(scene: Any, mask: torch.Tensor, cams: Sequence[Any]) -> list[int]:
    """Camera indices ordered by how much of the selection they show (its rendered alpha)."""
    sel = mask.to(scene.means.dtype)[:, None]
    seen = []
    for cam in cams:
        s = 64 / max(cam.width, cam.height)  # a thumbnail render is enough to rank views
        thumb = cam.resized(max(1, round(cam.width * s)), max(1, round(cam.height * s)))
        with torch.no_grad():
            r = scene.render(thumb, sel)
        seen.append(float(r["color"].sum()))
    return sorted(range(len(cams)), key=lambda i: -seen[i])


def cli(argv: Optional[Sequence[str]] = None) -> int:
    """``main`` with bad input reported in one line (SystemExit with the message), no traceback."""
    from tiger.models.paths import ModelNotFoundError
    from tiger.scene import SceneFormatError

    try:
        return main(argv)
    except (ModelNotFoundError, SceneFormatError) as exc:
        raise SystemExit(f"embed_and_query_colmap: {exc}") from exc


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    sys.exit(cli())

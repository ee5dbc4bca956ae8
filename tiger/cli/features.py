"""``tiger features``: images -> cached 64-d language feature maps (MaskCLIP, FeatUp, SAM, PCA)."""
from __future__ import annotations

import argparse
from pathlib import Path

from .common import (Summary, add_common, add_skip_missing, claim_output, device_of, existing, finish_output,
                     open_dataset, run_settings)


def add_parser(sub) -> None:
    p = sub.add_parser(
        "features", help="extract per-pixel language features of a dataset's images",
        description="MaskCLIP dense CLIP features, FeatUp upsampling, SAM finest-mask averaging and "
                    "a PCA to 64-d over all images (SPEC §4). Results are cached per image under "
                    "OUT (an interrupted run resumes; finished images are skipped). Under torchrun "
                    "each rank handles its own images.",
        epilog="example: tiger features data/figurines --out outputs/figurines/features "
               "--upsampler jbu --models ~/models",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("data", help="dataset folder (COLMAP or transforms.json) or a folder of images")
    add_common(p, models=True)
    p.add_argument("--upsampler", choices=("implicit", "jbu", "bilinear"), default="implicit",
                   help="quality/speed switch: FeatUp implicit (paper), JBU, or bilinear")
    add_skip_missing(p)
    p.add_argument("--no-sam", action="store_true", help="skip the SAM masked average")
    p.add_argument("--long-side", type=int, default=None,
                   help="feature-map long side in pixels (default: each image's own size)")
    p.add_argument("--clip-long-side", type=int, default=448)
    p.add_argument("--pca-dim", type=int, default=64, help="language dimension after the PCA")
    p.set_defaults(func=run)


def _images(path, skip_missing: bool = False):
    from pathlib import Path

    folder = Path(path)
    exts = {".jpg", ".jpeg", ".png", ".JPG", ".PNG", ".JPEG"}
    if folder.is_dir() and not any((folder / f).exists() for f in ("sparse", "transforms.json")):
        files = sorted(f for f in folder.iterdir() if f.suffix in exts)
        return files, [f.stem for f in files]
    cams = open_dataset(str(folder), skip_missing).cameras
    return [c.image_path for c in cams], [str(c.image_name).replace("/", "_") for c in cams]


def run(args: argparse.Namespace) -> int:
    from tiger.language.extract import FeatureConfig, extract_features

    data = existing(args.data, "dataset")
    files, names = _images(data, args.skip_missing)
    if not files:
        raise SystemExit(f"tiger features: no images found in {data}")
    cfg = FeatureConfig(upsampler=args.upsampler, use_sam=not args.no_sam,
                        output_long_side=args.long_side, clip_long_side=args.clip_long_side,
                        pca_dim=args.pca_dim)
    if not (Path(args.out) / "cache").is_dir():  # a fresh run: name every missing model at once
        from tiger.models.paths import require_models

        require_models(["clip"] + ([] if args.no_sam else ["sam"]) + (["featup_jbu"] if args.upsampler == "jbu" else []),
                       config=args.models, hint="(--no-sam skips SAM; --upsampler implicit or bilinear needs no FeatUp weights)")
    # an unfinished run in OUT resumes (finished images are skipped): only with the same settings
    out = claim_output(args.out, "features", run_settings(args), force=args.force, resume=not args.force)
    summary = Summary("tiger features")
    fs = extract_features(files, args.out, names=names, config=cfg, models=args.models,
                          device=device_of(args.device))
    finish_output(out, "features")
    summary.add(f"{len(fs.names)} feature maps in {fs.out_dir / 'features'}; PCA in {fs.out_dir / 'pca.pt'}")
    summary.print()
    return 0

"""``tiger features``: images -> cached 64-d language feature maps (MaskCLIP, FeatUp, SAM, PCA)."""
from __future__ import annotations

import argparse
from pathlib import Path

from .common import (CliError, Summary, add_common, add_skip_missing, claim_output, device_of, existing,
                     finish_output, open_dataset, run_settings)


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
    add_sam_precision(p)
    p.set_defaults(func=run)


def add_sam_precision(p: argparse.ArgumentParser, passthrough: bool = False) -> None:
    """``--sam-precision`` (``passthrough``: no default of its own, `tiger features`' applies)."""
    p.add_argument("--sam-precision", choices=("auto", "bf16", "fp32"), default=None if passthrough else "auto",
                   help="`tiger features --sam-precision`" if passthrough else
                   "SAM's arithmetic: bf16 (image encoder weights in bfloat16, prompt decoder under bf16 "
                   "autocast; about 1.7x faster on an H100, masks not bit-identical to float32's), fp32, or "
                   "auto: bf16 on CUDA, fp32 on the CPU (default: %(default)s)")


def _images(path, skip_missing: bool = False):
    from pathlib import Path

    folder = Path(path)
    exts = {".jpg", ".jpeg", ".png", ".JPG", ".PNG", ".JPEG"}
    if folder.is_dir() and not any((folder / f).exists() for f in ("sparse", "transforms.json")):
        files = sorted(f for f in folder.iterdir() if f.suffix in exts)
        return files, [f.stem for f in files]
    cams = open_dataset(str(folder), skip_missing).cameras
    return [c.image_path for c in cams], [str(c.image_name).replace("/", "_") for c in cams]


def distributed(device: str | None) -> tuple[int, int]:
    """(rank, world size) under torchrun, the process group initialised once (NCCL for a CUDA
    device, gloo for the CPU); (0, 1) otherwise. ``tiger.language.extract_features`` shards its
    images over the group it finds."""
    import os

    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return 0, 1
    import torch
    import torch.distributed as dist

    if not dist.is_initialized():
        cuda = torch.cuda.is_available() and not str(device or "").startswith("cpu")
        if cuda:
            torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", "0")) % torch.cuda.device_count())
        dist.init_process_group("nccl" if cuda else "gloo")
    return dist.get_rank(), dist.get_world_size()


def on_first_rank(world: int, rank: int, work):
    """Run ``work()`` on rank 0 only and hand its result (or its one-line error) to every rank, so
    an error stops all ranks with the same line instead of leaving the others at a barrier."""
    if world <= 1:
        return work()
    import torch.distributed as dist

    box: list = [None, None]
    failure: BaseException | None = None
    if rank == 0:
        try:
            box[0] = work()
        except (CliError, SystemExit) as e:
            failure, box[1] = e, str(e) or type(e).__name__
    dist.broadcast_object_list(box, src=0)
    if failure is not None:
        raise failure
    if box[1] is not None:
        raise SystemExit(1)  # rank 0 prints the line
    return box[0]


def run(args: argparse.Namespace) -> int:
    from tiger.language.extract import FeatureConfig, extract_features

    data = existing(args.data, "dataset")
    files, names = _images(data, args.skip_missing)
    if not files:
        raise CliError(f"no images found in {data}")
    from tiger.language.sam_masks import SamMaskConfig

    cfg = FeatureConfig(upsampler=args.upsampler, use_sam=not args.no_sam,
                        output_long_side=args.long_side, clip_long_side=args.clip_long_side,
                        pca_dim=args.pca_dim, sam=SamMaskConfig(precision=args.sam_precision))
    rank, world = distributed(args.device)
    # the output folder is claimed once, by rank 0, before any rank writes into it
    out = on_first_rank(world, rank, lambda: _claim(args))
    summary = Summary("tiger features")
    fs = extract_features(files, args.out, names=names, config=cfg, models=args.models,
                          device=device_of(args.device))
    if rank != 0:
        return 0
    finish_output(out, "features")
    summary.add(f"{len(fs.names)} feature maps in {fs.out_dir / 'features'}; PCA in {fs.out_dir / 'pca.pt'}"
                + (f" ({world} ranks)" if world > 1 else ""))
    if fs.timings:
        summary.add("seconds by stage" + (" (rank 0's images)" if world > 1 else "") + ": "
                    + ", ".join(f"{k} {v:.1f}" for k, v in fs.timings.items()))
    summary.print()
    return 0


def _claim(args: argparse.Namespace):
    """OUT claimed for this run (an unfinished run with the same settings continues), the models
    checked first on a fresh run."""
    settings, started = run_settings(args), Path(args.out).is_dir() and any(Path(args.out).iterdir())
    out = None
    if started:  # an unfinished run in OUT continues (finished images are skipped): same settings only
        out = claim_output(args.out, "features", settings, force=args.force, resume=not args.force)
    if not (Path(args.out) / "cache").is_dir():  # a fresh run: name every missing model at once
        from tiger.models.paths import require_models

        require_models(["clip"] + ([] if args.no_sam else ["sam"]) + (["featup_jbu"] if args.upsampler == "jbu" else []),
                       config=args.models, hint="(--no-sam skips SAM; --upsampler implicit or bilinear needs no FeatUp weights)")
    if not started:  # the folder is made only once the models are known to be there
        out = claim_output(args.out, "features", settings, force=args.force, resume=False)
    return out

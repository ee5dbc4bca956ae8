"""extract_features on one GPU vs sharded over GPUs with torchrun + NCCL: same outputs? how fast?

Three steps (benchmarks/gpu/multigpu_features.sh runs them in one device call):

  python -m benchmarks.multigpu_features prepare WORK [--images N]
      full-size random-weight CLIP ViT-B/16 and SAM ViT-H saved in the public folder layouts
      (tiger.testing.random_models), a random 512-channel JBU checkpoint, N synthetic 1920x1080 PNGs
  python -m benchmarks.multigpu_features run WORK OUT_NAME            (plain, or under torchrun)
      one warm-up call (two images per rank) through the library's own torchrun set-up, then the
      timed extract_features over all images, models already loaded; WORK/OUT_NAME/timing.json
  python -m benchmarks.multigpu_features compare WORK A B [C ...]
      every written tensor (features, validity, stage-1 caches, PCA) of runs B, C, ... against A

Models are loaded through the real loaders from the saved folders, each rank onto its own GPU.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import torch

from benchmarks.features import synthetic_image  # noqa: E402
from benchmarks.prepare import _stage1_record  # noqa: E402

from tiger.language.extract import FeatureConfig, extract_features  # noqa: E402



def _models(work: Path) -> dict[str, str]:
    return {"clip": str(work / "models" / "clip-vit-base-patch16"), "sam": str(work / "models" / "sam-vit-huge"),
            "featup_jbu": str(work / "models" / "maskclip_jbu_stack_cocostuff.ckpt")}


def prepare(work: Path, n_images: int, size: str = "full", image_hw: tuple[int, int] = (1080, 1920)) -> None:
    from PIL import Image

    from tiger.language.featup import JBUStack
    from tiger.testing.random_models import save_random_clip, save_random_sam

    t = time.perf_counter()
    m = _models(work)
    save_random_clip(m["clip"], size=size)
    save_random_sam(m["sam"], size=size)
    torch.manual_seed(0)
    dim = 512 if size == "full" else 24
    state = {f"upsampler.{k}": v for k, v in JBUStack(dim).state_dict().items()}
    torch.save({"state_dict": state}, m["featup_jbu"])
    img_dir = work / "images"
    img_dir.mkdir(parents=True, exist_ok=True)
    for k in range(n_images):
        img = synthetic_image(*image_hw, seed=k)
        Image.fromarray((img.permute(1, 2, 0) * 255).round().byte().numpy()).save(img_dir / f"{k:04d}.png")
    print(f"prepared models and {n_images} images in {time.perf_counter() - t:.1f} s", flush=True)


def _images(work: Path) -> list[Path]:
    return sorted((work / "images").glob("*.png"))


def _image_size(path: Path) -> tuple[int, int]:
    from PIL import Image

    with Image.open(path) as im:
        return im.size


def run(work: Path, name: str, config: dict) -> None:
    from tiger.language.maskclip import MaskCLIP
    from tiger.language.sam_masks import SamMaskGenerator

    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    cuda = torch.cuda.is_available()
    dev = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0"))) if cuda else torch.device("cpu")
    if cuda:
        torch.cuda.set_device(dev)
    t0 = time.perf_counter()
    m = _models(work)
    clip = MaskCLIP.from_pretrained(m["clip"], device=dev)
    sam = SamMaskGenerator.from_pretrained(m["sam"], device=dev)
    from tiger.language.featup import JBUStack

    jbu = JBUStack.from_checkpoint(config=m).to(dev)
    t_load = time.perf_counter() - t0
    cfg = FeatureConfig(**config)
    files = _images(work)
    # Warm-up (CUDA context, kernels, and under torchrun the library's own NCCL set-up).
    extract_features(files[: 2 * world], work / f"{name}_warmup", clip=clip, sam=sam, jbu=jbu, config=cfg,
                     progress=False)
    import torch.distributed as dist

    use_dist = dist.is_available() and dist.is_initialized()
    if use_dist:
        assert dist.get_backend() == ("nccl" if cuda else "gloo"), dist.get_backend()
        dist.barrier()
    if cuda:
        torch.cuda.synchronize()
    t1 = time.perf_counter()
    fs = extract_features(files, work / name, clip=clip, sam=sam, jbu=jbu, config=cfg, progress=False)
    if cuda:
        torch.cuda.synchronize()
    if use_dist:
        dist.barrier()
    seconds = time.perf_counter() - t1
    if rank == 0:
        rec = {"world_size": world, "backend": dist.get_backend() if use_dist else None, "images": len(files),
               "image_size": "x".join(map(str, _image_size(files[0]))), "config": config, "model_load_s": t_load, "extract_s": seconds,
               "images_per_s": len(files) / seconds, "gpu": torch.cuda.get_device_name(dev) if cuda else "cpu",
               "torch": torch.__version__, "n_features": len(fs.names)}
        (work / name / "timing.json").write_text(json.dumps(rec, indent=2))
        print(json.dumps(rec), flush=True)
    if use_dist:
        dist.destroy_process_group()


def _tensors(obj, prefix=""):
    if isinstance(obj, torch.Tensor):
        yield prefix, obj
    elif isinstance(obj, dict):
        for k in sorted(obj):
            yield from _tensors(obj[k], f"{prefix}.{k}")
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            yield from _tensors(v, f"{prefix}[{i}]")


def compare(work: Path, ref: str, others: list[str]) -> int:
    status = 0
    ref_dir = work / ref
    files = sorted(p.relative_to(ref_dir) for p in ref_dir.rglob("*.pt"))
    for other in others:
        n_same, diffs = 0, []
        for rel in files:
            a = torch.load(ref_dir / rel, map_location="cpu", weights_only=True)
            b_path = work / other / rel
            if not b_path.is_file() and _stage1_record(rel):
                continue  # a record kept in memory is written only while the disk keeps up
            if not b_path.is_file():
                diffs.append(f"{rel}: missing")
                continue
            b = torch.load(b_path, map_location="cpu", weights_only=True)
            ta, tb = dict(_tensors(a)), dict(_tensors(b))
            for key in ta:
                x, y = ta[key], tb.get(key)
                if y is None or x.shape != y.shape or x.dtype != y.dtype:
                    diffs.append(f"{rel}{key}: shape/dtype {tuple(x.shape)} vs {None if y is None else tuple(y.shape)}")
                elif not torch.equal(x, y):
                    err = (x.double() - y.double()).abs().max().item() if x.is_floating_point() else "ints differ"
                    diffs.append(f"{rel}{key}: max |diff| {err}")
                else:
                    n_same += 1
        print(f"{other} vs {ref}: {len(files)} files, {n_same} tensors bit-identical, {len(diffs)} differ")
        for d in diffs[:20]:
            print(f"  {d}")
        status |= bool(diffs)
    return int(status)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    a = sub.add_parser("prepare")
    a.add_argument("work", type=Path)
    a.add_argument("--images", type=int, default=32)
    a.add_argument("--size", choices=("full", "tiny"), default="full", help="tiny: a CPU smoke test")
    a.add_argument("--image-hw", type=int, nargs=2, default=(1080, 1920))
    b = sub.add_parser("run")
    b.add_argument("work", type=Path)
    b.add_argument("name")
    b.add_argument("--upsampler", default="jbu")
    b.add_argument("--long-side", type=int, default=960, help="feature-map long side")
    b.add_argument("--pca-dim", type=int, default=64)
    c = sub.add_parser("compare")
    c.add_argument("work", type=Path)
    c.add_argument("ref")
    c.add_argument("others", nargs="+")
    args = p.parse_args()
    if args.cmd == "prepare":
        prepare(args.work, args.images, args.size, tuple(args.image_hw))
    elif args.cmd == "run":
        run(args.work, args.name, dict(upsampler=args.upsampler, output_long_side=args.long_side,
                                       pca_dim=args.pca_dim))
    else:
        return compare(args.work, args.ref, args.others)
    return 0


if __name__ == "__main__":
    sys.exit(main())

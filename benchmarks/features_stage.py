"""Where the feature stage's time goes: ``extract_features`` on the first N frames of a capture,
models loaded once, split into the per-image model work (CLIP, FeatUp, SAM, masked average,
statistics; timed around ``compute_image_features`` with the device synchronised) and the rest
(record hand-over and writes, PCA fit, projection, map writes), with the bytes written.

    python -m benchmarks.features_stage --device cuda --models full --images 12 --upsampler jbu
    python -m benchmarks.features_stage --device cpu --models tiny --images 4 --upsampler jbu --long-side 256

``--modes memory disk``: 'memory' is the default path (records kept on the device between the
passes); 'disk' forces every record through ``cache/`` (``memory_budget=0``, the fall-back when
memory is short). ``--cli`` also times ``tiger features`` end to end (model loading included).
``--models full|tiny`` writes random models of that size in their real formats first
(benchmarks/gpu/write_random_models.py) and points $TIGER_MODELS at them; another value is a
models folder or JSON config. The data is ``--data`` (default as benchmarks/prepare.py: the fox).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import torch

from benchmarks.prepare import REPO, _default_data


def _frames(data: Path, n: int | None) -> tuple[list[Path], list[str]]:
    """The capture's image files (transforms.json order, or a folder's sorted images), first ``n``."""
    meta = data / "transforms.json"
    if meta.is_file():
        frames = json.loads(meta.read_text())["frames"]
        files = [data / f["file_path"] for f in frames]
        files = [f if f.suffix else f.with_suffix(".png") for f in files]
    else:
        files = sorted(p for p in data.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
    files = files[:n] if n else files
    return files, [f.stem for f in files]


def _bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file()) if folder.is_dir() else 0


def _sync(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def run_mode(mode: str, files: list[Path], names: list[str], out: Path, cfg, clip, sam, jbu, dev) -> dict:
    """One timed ``extract_features`` run from an empty folder."""
    from tiger.language import extract as extract_mod

    shutil.rmtree(out, ignore_errors=True)
    model_s = [0.0]
    real = extract_mod.compute_image_features

    def timed_compute(*a, **kw):
        _sync(dev)
        t = time.perf_counter()
        rec = real(*a, **kw)
        _sync(dev)
        model_s[0] += time.perf_counter() - t
        return rec

    extract_mod.compute_image_features = timed_compute
    try:
        _sync(dev)
        t0 = time.perf_counter()
        extract_mod.extract_features(files, out, names=names, config=cfg, clip=clip, sam=sam, jbu=jbu,
                                     device=dev, progress=False, **({"memory_budget": 0} if mode == "disk" else {}))
        _sync(dev)
        wall = time.perf_counter() - t0
    finally:
        extract_mod.compute_image_features = real
    n = len(files)
    records = len([p for p in (out / "cache").glob("*.pt") if not p.name.endswith(".stats.pt")])
    return {"mode": mode, "images": n, "wall_s": wall, "s_per_image": wall / n, "models_s_per_image": model_s[0] / n,
            "other_s_per_image": (wall - model_s[0]) / n, "cache_MB": _bytes(out / "cache") / 1e6,
            "maps_MB": _bytes(out / "features") / 1e6, "records_written": records}


def main(argv: list | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=_default_data())
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--models", default="full", help="full, tiny (random models written first) or a path")
    ap.add_argument("--images", type=int, default=12)
    ap.add_argument("--upsampler", default="jbu", choices=("implicit", "jbu", "bilinear"))
    ap.add_argument("--long-side", type=int, default=None, help="feature-map long side (default: full size)")
    ap.add_argument("--pca-dim", type=int, default=None, help="default 64 (16 with --models tiny)")
    ap.add_argument("--sam-precision", default="auto", choices=("auto", "bf16", "fp32"))
    ap.add_argument("--modes", nargs="+", default=["memory", "disk"], choices=("memory", "disk"))
    ap.add_argument("--cli", action="store_true", help="also time `tiger features` end to end")
    ap.add_argument("--out", type=Path, default=REPO / "outputs" / "features_stage_bench")
    ap.add_argument("--json", type=Path, default=None, help="also write the rows here")
    args = ap.parse_args(argv)
    if not args.data.is_dir():
        print(f"no capture at {args.data}; skipping")
        return 0
    files, names = _frames(args.data, args.images)
    models = args.models
    if models in ("full", "tiny"):
        folder = (args.out / f"models_{models}").resolve()
        if not (folder / "featup" / "maskclip_jbu_stack_cocostuff.ckpt").is_file():
            subprocess.run([sys.executable, "-m", "benchmarks.gpu.write_random_models", str(folder), "--size", models],
                           check=True, cwd=REPO)
        os.environ["TIGER_MODELS"] = str(folder)
        models = None

    from tiger.language.extract import FeatureConfig, extract_features
    from tiger.language.featup import JBUStack
    from tiger.language.maskclip import MaskCLIP
    from tiger.language.sam_masks import SamMaskConfig, SamMaskGenerator

    dev = torch.device(args.device)
    pca_dim = args.pca_dim or (16 if args.models == "tiny" else 64)
    # (a checkout from before the SAM precision option runs too, in float32: before/after timings)
    precision = {"precision": args.sam_precision} if "precision" in SamMaskConfig.__dataclass_fields__ else {}
    cfg = FeatureConfig(upsampler=args.upsampler, output_long_side=args.long_side, pca_dim=pca_dim,
                        sam=SamMaskConfig(**precision))
    t0 = time.perf_counter()
    clip = MaskCLIP.from_pretrained(device=dev, config=models)
    sam = SamMaskGenerator.from_pretrained(device=dev, config=models, mask_config=cfg.sam)
    jbu = JBUStack.from_checkpoint(config=models).to(dev) if args.upsampler == "jbu" else None
    load_s = time.perf_counter() - t0
    extract_features(files[:1], args.out / "warmup", names=names[:1], config=cfg, clip=clip, sam=sam, jbu=jbu,
                     device=dev, progress=False)  # CUDA context, kernels, allocator
    rows = [run_mode(m, files, names, args.out / m, cfg, clip, sam, jbu, dev) for m in args.modes]
    if args.cli:
        del clip, sam, jbu
        if dev.type == "cuda":
            torch.cuda.empty_cache()
        from tiger.cli.main import main as tiger

        out = args.out / "cli"
        cmd = ["features", str(args.data), "--out", str(out), "--force", "--device", args.device,
               "--upsampler", args.upsampler, "--pca-dim", str(pca_dim), "--sam-precision", args.sam_precision,
               *(["--models", str(models)] if models else []),
               *(["--long-side", str(args.long_side)] if args.long_side else [])]
        data = args.data
        if args.images and (args.data / "transforms.json").is_file():  # the first N frames as their own capture
            from benchmarks.prepare import _first_frames

            data = _first_frames(args.data, args.images, args.out / f"capture_{args.images}")
            cmd[1] = str(data)
        t0 = time.perf_counter()
        code = tiger(cmd)
        wall = time.perf_counter() - t0
        if code:
            print(f"tiger features exited {code}")
            return code
        rows.append({"mode": "tiger features (CLI)", "images": len(files), "wall_s": wall,
                     "s_per_image": wall / len(files), "cache_MB": _bytes(out / "cache") / 1e6,
                     "maps_MB": _bytes(out / "features") / 1e6})
    gpu = torch.cuda.get_device_name(dev) if dev.type == "cuda" else "cpu"
    print(f"\nfeature stage: {len(files)} images of {args.data}, upsampler {args.upsampler}, models {args.models}, "
          f"SAM precision {sam_precision_of(cfg, dev)}, device {gpu}; models loaded once in {load_s:.1f} s")
    keys = ["mode", "images", "wall_s", "s_per_image", "models_s_per_image", "other_s_per_image", "cache_MB",
            "maps_MB", "records_written"]
    print("| " + " | ".join(keys) + " |")
    print("|" + "---|" * len(keys))
    for r in rows:
        print("| " + " | ".join(f"{r[k]:.4g}" if isinstance(r.get(k), float) else str(r.get(k, "-")) for k in keys)
              + " |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


def sam_precision_of(cfg, dev: torch.device) -> str:
    return cfg.sam.resolved(dev).precision if hasattr(cfg.sam, "resolved") else "fp32"


if __name__ == "__main__":
    raise SystemExit(main())

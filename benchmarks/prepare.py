"""The fox from photos to a language-embedded scene with `tiger prepare`: seconds per stage and in
total, with the stage quality (held-out PSNR, Gaussians, field loss), for each upsampler asked for.

    python -m benchmarks.prepare --device cuda --models full --upsampler implicit jbu --downscale 2 --recon-steps 7000
    python -m benchmarks.prepare --device cuda --images 12 --upsampler jbu --ranks 2   # + the same on 2 GPUs
    python -m benchmarks.prepare --device cpu --models tiny --images 3 --downscale 8 --recon-steps 30 \
        --upsampler jbu --long-side 96 --embed-steps 10 --ranks 2              # a CPU smoke run (gloo)

``--models full|tiny`` writes random models of that size in their real formats first
(benchmarks/gpu/write_random_models.py) and points $TIGER_MODELS at them; another value is passed
to ``--models`` (a JSON config of name -> path). The data is ``--data`` (default
``.carry/realscene/fox``, else ``.carry/fox``, else ``<repo>/../shared/data/fox``); ``--images N``
takes its first N frames as a capture of their own. Each run starts from scratch (--force) in
``--out/<upsampler>``; prepare.json is kept there.

``--ranks N`` (N > 1) also runs ``tiger prepare`` under ``torchrun --nproc_per_node N`` (NCCL on
CUDA, gloo on the CPU) from the one-process run's scene (``--scene``), so that only the feature
stage is sharded, and compares every file of its features folder with the one-process run's:
bytes, and each tensor with ``torch.equal``.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _default_data() -> Path:
    for folder in (REPO / ".carry" / "realscene" / "fox", REPO / ".carry" / "fox"):
        if (folder / "transforms.json").is_file():
            return folder
    return REPO.parent / "shared" / "data" / "fox"


def _first_frames(data: Path, n: int, folder: Path) -> Path:
    """The first ``n`` frames of a transforms.json capture as a capture of their own in ``folder``
    (its images folder linked, not copied)."""
    meta = json.loads((data / "transforms.json").read_text())
    meta["frames"] = meta["frames"][:n]
    folder.mkdir(parents=True, exist_ok=True)
    link = folder / "images"
    if not link.exists():
        link.symlink_to((data / "images").resolve(), target_is_directory=True)
    (folder / "transforms.json").write_text(json.dumps(meta))
    return folder


def _tensors(obj, prefix=""):
    if isinstance(obj, dict):
        for k in sorted(obj, key=str):
            yield from _tensors(obj[k], f"{prefix}.{k}")
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            yield from _tensors(v, f"{prefix}[{i}]")
    else:
        yield prefix, obj


def _stage1_record(rel: Path) -> bool:
    """A features folder's per-image stage-1 record (cache/<name>.pt, not its .stats.pt): written
    only while the disk keeps up when it stayed in memory, so either run may lack it."""
    return "cache" in rel.parts and not rel.name.endswith(".stats.pt")


def compare_folders(ref: Path, other: Path) -> dict:
    """Every file under ``ref`` against ``other``: byte-identical files, and for .pt files whose
    bytes differ, whether every tensor and value is equal (``torch.equal``). A stage-1 record that
    only one run wrote is counted under ``records_in_one_run_only``, not as a difference."""
    import torch

    files = sorted(p.relative_to(ref) for p in ref.rglob("*") if p.is_file() and p.suffix in (".pt", ".json"))
    same_bytes, same_values, differ, one_only = 0, 0, [], 0
    for rel in files:
        b = other / rel
        if not b.is_file() and _stage1_record(rel):
            one_only += 1
            continue
        if not b.is_file():
            differ.append(f"{rel}: missing")
            continue
        if (ref / rel).read_bytes() == b.read_bytes():
            same_bytes += 1
            continue
        if rel.suffix != ".pt":
            differ.append(f"{rel}: bytes differ")
            continue
        x = dict(_tensors(torch.load(ref / rel, map_location="cpu", weights_only=True)))
        y = dict(_tensors(torch.load(b, map_location="cpu", weights_only=True)))
        bad = [k for k in x if k not in y or not (torch.equal(x[k], y[k]) if isinstance(x[k], torch.Tensor)
                                                   else x[k] == y[k])]
        if bad:
            differ.append(f"{rel}: {', '.join(bad[:4])} differ")
        else:
            same_values += 1
    return {"files": len(files), "byte_identical": same_bytes, "equal_values_other_bytes": same_values,
            "differ": differ, "records_in_one_run_only": one_only}


def main(argv: list | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=_default_data())
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--models", default="full", help="full, tiny (random models written first) or a path")
    ap.add_argument("--upsampler", nargs="+", default=["implicit", "jbu"], choices=("implicit", "jbu", "bilinear"))
    ap.add_argument("--downscale", type=float, default=2.0)
    ap.add_argument("--recon-steps", type=int, default=7000)
    ap.add_argument("--long-side", type=int, default=None, help="feature-map long side (default: full size)")
    ap.add_argument("--embed-steps", type=int, default=None, help="default: `tiger embed`'s")
    ap.add_argument("--pca-dim", type=int, default=None,
                    help="`tiger features --pca-dim` (default: its 64; 16 with --models tiny, whose CLIP has 24 channels)")
    ap.add_argument("--images", type=int, default=None, help="the first N frames of the capture only")
    ap.add_argument("--ranks", type=int, default=1,
                    help="N > 1: also the feature stage sharded over N processes under torchrun, compared")
    ap.add_argument("--out", type=Path, default=REPO / "outputs" / "prepare_bench")
    ap.add_argument("--json", type=Path, default=None, help="also write the table here")
    args = ap.parse_args(argv)
    args.out, args.data = args.out.resolve(), args.data.resolve()
    if not (args.data / "transforms.json").is_file():
        print(f"fox data not found at {args.data} (expected transforms.json + images/); skipping")
        return 0
    if args.images:
        args.data = _first_frames(args.data, args.images, args.out / f"capture_{args.images}")
    models = args.models
    if models in ("full", "tiny"):
        folder = args.out / f"models_{models}"
        if not (folder / "featup" / "maskclip_jbu_stack_cocostuff.ckpt").is_file():
            t0 = time.perf_counter()
            subprocess.run([sys.executable, "-m", "benchmarks.gpu.write_random_models", str(folder),
                            "--size", models, "--only", "clip", "sam", "featup_jbu"], check=True, cwd=REPO)
            print(f"random {models} models written in {time.perf_counter() - t0:.1f} s")
        models = None
        os.environ["TIGER_MODELS"] = str(folder)  # found as a user's $TIGER_MODELS folder

    from tiger.cli.main import main as tiger

    status = 0
    rows = []
    for up in args.upsampler:
        out = args.out / up
        options = ["--device", args.device, *(["--models", models] if models else []), "--upsampler", up]
        if args.long_side:
            options += ["--long-side", str(args.long_side)]
        if args.embed_steps is not None:
            options += ["--embed-steps", str(args.embed_steps)]
        pca_dim = args.pca_dim or (16 if args.models == "tiny" else None)
        if pca_dim:
            options += ["--pca-dim", str(pca_dim)]
        cmd = ["prepare", str(args.data), "--out", str(out), "--force", *options,
               "--downscale", str(args.downscale), "--recon-steps", str(args.recon_steps)]
        t0 = time.perf_counter()
        code = tiger(cmd)
        wall = time.perf_counter() - t0
        if code:
            print(f"tiger prepare ({up}) exited {code}")
            return code
        rows.append(_row(up, 1, wall, out))
        if args.ranks > 1:
            sharded = args.out / f"{up}_{args.ranks}ranks"
            cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node",
                   str(args.ranks), "-m", "tiger.cli.main", "prepare", str(args.data), "--out", str(sharded),
                   "--force", "--scene", str(out / "recon" / "scene.ply"), *options]
            env = {**os.environ, "NCCL_NVLS_ENABLE": "0", "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "4")}
            t0 = time.perf_counter()
            code = subprocess.run(cmd, env=env, cwd=REPO).returncode
            wall = time.perf_counter() - t0
            if code:
                print(f"torchrun tiger prepare ({up}, {args.ranks} ranks) exited {code}")
                return code
            cmp = compare_folders(out / "features", sharded / "features")
            print(f"features of {args.ranks} ranks vs 1 ({up}): {cmp['files']} files, {cmp['byte_identical']} "
                  f"byte-identical, {cmp['equal_values_other_bytes']} equal values in other bytes, "
                  f"{len(cmp['differ'])} differ" + "".join(f"\n  {d}" for d in cmp["differ"][:20]))
            rows.append({**_row(up, args.ranks, wall, sharded), "identical_files": cmp["byte_identical"],
                         "files": cmp["files"]})
            if cmp["differ"]:
                status = 1
    keys = ["upsampler", "ranks", "reconstruct_s", "features_s", "embed_s", "wall_s", "held_out_psnr_db",
            "gaussians", "field_loss", "identical_files", "files"]
    print(f"\nfox, downscale {args.downscale:g} for the reconstruction, {args.recon_steps} steps, device {args.device}, "
          f"models {args.models}")
    print("| " + " | ".join(keys) + " |")
    print("|" + "---|" * len(keys))
    for r in rows:
        print("| " + " | ".join(f"{r.get(k):.4g}" if isinstance(r.get(k), float) else str(r.get(k, "-"))
                                for k in keys) + " |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return status


def _row(upsampler: str, ranks: int, wall: float, out: Path) -> dict:
    """One table row from a finished prepare folder's prepare.json."""
    stages = json.loads((out / "prepare.json").read_text())["stages"]
    return {"upsampler": upsampler, "ranks": ranks, "wall_s": wall,
            **{f"{k}_s": v["seconds"] for k, v in stages.items()},
            **{k: v for s in stages.values() for k, v in (s.get("quality") or {}).items()
               if isinstance(v, (int, float))}}


if __name__ == "__main__":
    raise SystemExit(main())

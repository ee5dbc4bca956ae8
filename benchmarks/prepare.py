"""The fox from photos to a language-embedded scene with `tiger prepare`: seconds per stage and in
total, with the stage quality (held-out PSNR, Gaussians, field loss), for each upsampler asked for.

    python -m benchmarks.prepare --device cuda --models full --upsampler implicit jbu --downscale 2 --recon-steps 7000
    python -m benchmarks.prepare --device cpu --models tiny --downscale 8 --recon-steps 200 --upsampler bilinear \
        --long-side 120 --embed-steps 50                       # a CPU smoke run

``--models full|tiny`` writes random models of that size in their real formats first
(benchmarks/gpu/write_random_models.py) and points $TIGER_MODELS at them; another value is passed
to ``--models`` (a JSON config of name -> path). The data is
``--data`` (default ``.carry/fox`` when present, else ``<repo>/../shared/data/fox``). Each run
starts from scratch (--force) in ``--out/<upsampler>``; prepare.json is kept there.
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
    carried = REPO / ".carry" / "fox"
    return carried if (carried / "transforms.json").is_file() else REPO.parent / "shared" / "data" / "fox"


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
    ap.add_argument("--out", type=Path, default=REPO / "outputs" / "prepare_bench")
    ap.add_argument("--json", type=Path, default=None, help="also write the table here")
    args = ap.parse_args(argv)
    if not (args.data / "transforms.json").is_file():
        print(f"fox data not found at {args.data} (expected transforms.json + images/); skipping")
        return 0
    models = args.models
    if models in ("full", "tiny"):
        folder = args.out / f"models_{models}"
        if not (folder / "featup" / "maskclip_jbu_stack_cocostuff.ckpt").is_file():
            t0 = time.perf_counter()
            subprocess.run([sys.executable, str(REPO / "benchmarks" / "gpu" / "write_random_models.py"), str(folder),
                            "--size", models], check=True)
            print(f"random {models} models written in {time.perf_counter() - t0:.1f} s")
        models = None
        os.environ["TIGER_MODELS"] = str(folder)  # found as a user's $TIGER_MODELS folder

    from tiger.cli.main import main as tiger

    rows = []
    for up in args.upsampler:
        out = args.out / up
        cmd = ["prepare", str(args.data), "--out", str(out), "--force", "--device", args.device,
               *(["--models", models] if models else []), "--upsampler", up, "--downscale", str(args.downscale), "--recon-steps", str(args.recon_steps)]
        if args.long_side:
            cmd += ["--long-side", str(args.long_side)]
        if args.embed_steps is not None:
            cmd += ["--embed-steps", str(args.embed_steps)]
        t0 = time.perf_counter()
        code = tiger(cmd)
        wall = time.perf_counter() - t0
        if code:
            print(f"tiger prepare ({up}) exited {code}")
            return code
        stages = json.loads((out / "prepare.json").read_text())["stages"]
        rows.append({"upsampler": up, "wall_s": wall, **{f"{k}_s": v["seconds"] for k, v in stages.items()},
                     **{k: v for s in stages.values() for k, v in (s.get("quality") or {}).items()
                        if isinstance(v, (int, float))}})
    keys = ["upsampler", "reconstruct_s", "features_s", "embed_s", "wall_s", "held_out_psnr_db", "gaussians",
            "field_loss"]
    print(f"\nfox, downscale {args.downscale:g} for the reconstruction, {args.recon_steps} steps, device {args.device}, "
          f"models {args.models}")
    print("| " + " | ".join(keys) + " |")
    print("|" + "---|" * len(keys))
    for r in rows:
        print("| " + " | ".join(f"{r.get(k):.4g}" if isinstance(r.get(k), float) else str(r.get(k, "-"))
                                for k in keys) + " |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

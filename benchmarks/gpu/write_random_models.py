"""Write full-size randomly initialised models, in their real formats, into a $TIGER_MODELS folder:
CLIP ViT-B/16 and SAM ViT-H (Hugging Face folders), FeatUp's JBU stack (a bare state dict in the
released checkpoint's file name), InstructPix2Pix (diffusers folder) and MVDream (the original LDM
checkpoint). Every command then finds them as it would find the real weights.

    python -m benchmarks.gpu.write_random_models OUT_FOLDER [--size full|tiny] [--only clip sam ...]
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch


MODELS = ("clip", "sam", "ip2p", "mvdream", "featup_jbu")


def main(argv: list | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path)
    ap.add_argument("--size", choices=("full", "tiny"), default="full")
    ap.add_argument("--only", nargs="+", choices=MODELS, default=list(MODELS),
                    help="write these models only (default: all; `tiger prepare` needs clip, sam, featup_jbu)")
    args = ap.parse_args(argv)
    from tiger.testing.random_models import save_random_ip2p, save_random_mvdream
    from tiger.language.featup import JBUStack
    from tiger.models.paths import REGISTRY
    from tiger.testing.random_models import save_random_clip, save_random_sam

    root = args.out
    root.mkdir(parents=True, exist_ok=True)
    jobs = {
        "clip": lambda p: save_random_clip(p, args.size),
        "sam": lambda p: save_random_sam(p, args.size),
        "ip2p": lambda p: save_random_ip2p(p, args.size),
        "mvdream": lambda p: save_random_mvdream(p, args.size),
    }
    for name, write in jobs.items():
        if name not in args.only:
            continue
        t0 = time.perf_counter()
        folder = root / REGISTRY[name].folder
        write(folder)
        print(f"{name}: {folder} ({time.perf_counter() - t0:.1f} s)", flush=True)
    if "featup_jbu" not in args.only:
        return 0
    spec = REGISTRY["featup_jbu"]
    jbu_file = root / spec.folder / spec.files[0]
    jbu_file.parent.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(0)
    from tiger.testing.random_models import clip_config

    dim = int(clip_config(args.size).projection_dim)  # the JBU stack upsamples CLIP's features
    torch.save(JBUStack(dim).state_dict(), jbu_file)
    print(f"featup_jbu: {jbu_file}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

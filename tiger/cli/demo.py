"""``tiger demo``: the built-in tabletop demo."""
from __future__ import annotations

import argparse

from .common import CliError


def add_parser(sub) -> None:
    p = sub.add_parser(
        "demo", help="run the built-in tabletop demo and write pictures",
        description="Build a procedural tabletop scene (table, mug, ball, box, plant), render it, "
                    "train its language field, retrieve objects by text and write pictures "
                    "(renders, relevancy heat maps, highlighted and retrieved objects), then recolour the ball "
                    "red through the edit loop (edit_before_after.png).",
        epilog="example: tiger demo --out outputs/demo --force",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="outputs/demo", help="output folder (default: %(default)s)")
    p.add_argument("--width", type=int, default=480)
    p.add_argument("--height", type=int, default=360)
    p.add_argument("--views", type=int, default=4, help="number of orbit views")
    p.add_argument("--queries", nargs="*", default=["mug", "ball", "plant"],
                   help="text queries to retrieve (default: %(default)s; none: render only)")
    p.add_argument("--steps", type=int, default=300, help="language-field training steps")
    p.add_argument("--edit-steps", type=int, default=40,
                   help="steps of the 'make the ball red' recolour edit (0: skip; needs 'ball' in --queries)")
    p.add_argument("--models", default=None,
                   help="model folder or config (default: $TIGER_MODELS); CLIP enables free text")
    p.add_argument("--force", action="store_true", help="overwrite an existing output folder")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    out = Path(args.out)
    if out.exists() and any(out.iterdir()) and not args.force:
        raise CliError(f"{out} already exists and is not empty; pass --force to overwrite it")
    if args.width <= 0 or args.height <= 0 or args.views <= 0 or args.steps < 0 or args.edit_steps < 0:
        raise CliError("--width, --height and --views must be positive, --steps and --edit-steps non-negative")
    from tiger.demo.run import run_demo

    run_demo(str(out), args.width, args.height, args.views, queries=args.queries,
             models=args.models, steps=args.steps, edit_steps=args.edit_steps)
    return 0

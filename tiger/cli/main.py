"""``tiger``: the command-line entry point. Each subcommand lives in its own module."""
from __future__ import annotations

import argparse
import logging
import sys
from typing import Callable, Optional, Sequence

EPILOG = "Run `tiger <command> --help` for the options and an example of each command."


class CliError(Exception):
    """An error the user can act on: printed as one line, exit code 2."""


def _add_demo(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo", help="run the built-in tabletop demo and write pictures",
        description="Build a procedural tabletop scene (table, mug, ball, box, plant), render it, "
                    "train its language field, retrieve objects by text and write pictures "
                    "(renders, relevancy heat maps, highlighted and retrieved objects).",
        epilog="example: tiger demo --out outputs/demo --force",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="outputs/demo", help="output folder (default: %(default)s)")
    p.add_argument("--width", type=int, default=480)
    p.add_argument("--height", type=int, default=360)
    p.add_argument("--views", type=int, default=4, help="number of orbit views")
    p.add_argument("--queries", nargs="*", default=["mug", "ball", "plant"],
                   help="text queries to retrieve (default: %(default)s; none: render only)")
    p.add_argument("--steps", type=int, default=300, help="language-field training steps")
    p.add_argument("--models", default=None,
                   help="model folder or config (default: $TIGER_MODELS); CLIP enables free text")
    p.add_argument("--force", action="store_true", help="overwrite an existing output folder")
    p.set_defaults(func=_run_demo)


def _run_demo(args: argparse.Namespace) -> int:
    from pathlib import Path

    out = Path(args.out)
    if out.exists() and any(out.iterdir()) and not args.force:
        raise CliError(f"{out} already exists and is not empty; pass --force to overwrite it")
    if args.width <= 0 or args.height <= 0 or args.views <= 0 or args.steps < 0:
        raise CliError("--width, --height and --views must be positive, --steps non-negative")
    from tiger.demo.run import run_demo

    run_demo(str(out), args.width, args.height, args.views, queries=args.queries,
             models=args.models, steps=args.steps)
    return 0


COMMANDS: list[Callable[[argparse._SubParsersAction], None]] = [_add_demo]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="tiger", description="TIGER: text-instructed retrieval and editing of 3D Gaussian "
                                  "Splatting scenes.", epilog=EPILOG)
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = p.add_subparsers(dest="command", metavar="<command>")
    for add in COMMANDS:
        add(sub)
    return p


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(levelname)s %(name)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except CliError as e:
        print(f"tiger {args.command}: error: {e}", file=sys.stderr)
        return 2
    except (FileNotFoundError, ValueError, TypeError, RuntimeError, ImportError) as e:
        if args.verbose:
            raise
        print(f"tiger {args.command}: error: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"tiger {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())

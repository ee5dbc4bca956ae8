"""``tiger``: the command-line entry point. Each subcommand lives in its own module."""
from __future__ import annotations

import argparse
import logging
import sys
from typing import Optional, Sequence

from . import delete, demo, edit, embed, eval_edit, features, info, lerf, query, reconstruct, render, view
from .common import CliError

EPILOG = "Run `tiger <command> --help` for the options and an example of each command."
COMMANDS = [reconstruct, features, embed, query, edit, eval_edit, delete, render, view, lerf, info, demo]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="tiger", description="TIGER: text-instructed retrieval and editing of 3D Gaussian "
                                  "Splatting scenes.", epilog=EPILOG)
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = p.add_subparsers(dest="command", metavar="<command>")
    for mod in COMMANDS:
        mod.add_parser(sub)
    return p


def main(argv: Optional[Sequence[str]] = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "eval-lerf":  # its own parser (tiger.eval.lerf)
        try:
            return lerf.delegate(argv[1:])
        except SystemExit as e:
            if isinstance(e.code, str):
                print(e.code, file=sys.stderr)
                return 2
            return int(e.code or 0)
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
    except SystemExit as e:
        if isinstance(e.code, str):  # a command's own one-line error
            print(e.code, file=sys.stderr)
            return 2
        raise
    except (FileNotFoundError, ValueError, TypeError, RuntimeError, ImportError, KeyError) as e:
        if args.verbose:
            raise
        print(f"tiger {args.command}: error: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt as e:  # a command may say where it stopped (the message)
        print(f"tiger {args.command}: interrupted" + (f": {e}" if str(e) else ""), file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())

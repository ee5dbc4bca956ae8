"""``tiger``: the command-line entry point. Each subcommand lives in its own module.

Exit codes (one handler, :func:`main`): 0 success; 2 bad input or setup (a wrong argument, a
missing or malformed file, an unknown text, missing model weights or optional package: one line
on stderr naming it); 1 a failure while running (the error's one line; ``-v`` shows the
traceback); 130 interrupted (Ctrl-C); 141 the reader of the output went away (``| head``).
"""
from __future__ import annotations

import argparse
import logging
import os
import sys
from typing import Callable, Optional, Sequence

from . import (delete, demo, edit, embed, eval_edit, export, features, info, lerf, prepare, query, reconstruct,
               render, view)
from .common import CliError, mark_command_start

EPILOG = ("Run `tiger <command> --help` for the options and an example of each command. Exit codes: "
          "0 done, 2 bad input (arguments, files, texts, missing weights), 1 failure while running, "
          "130 interrupted.")
COMMANDS = [prepare, reconstruct, features, embed, query, edit, eval_edit, delete, render, view, export, lerf, info,
            demo]

EXIT_OK, EXIT_FAILURE, EXIT_BAD_INPUT, EXIT_INTERRUPTED, EXIT_BROKEN_PIPE = 0, 1, 2, 130, 141

#: Exceptions that mean the input or the setup is wrong (exit 2); anything else that escapes a
#: command is a failure while running (exit 1). FileNotFoundError covers missing model weights
#: (tiger.models.ModelNotFoundError), ImportError a missing optional package (its install hint).
BAD_INPUT = (CliError, ValueError, TypeError, KeyError, FileNotFoundError, NotADirectoryError,
             IsADirectoryError, ImportError)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="tiger", description="TIGER: text-instructed retrieval and editing of 3D Gaussian "
                                  "Splatting scenes.", epilog=EPILOG)
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = p.add_subparsers(dest="command", metavar="<command>")
    for mod in COMMANDS:
        mod.add_parser(sub)
    return p


def _one_line(exc: BaseException) -> str:
    text = str(exc.args[0]) if isinstance(exc, KeyError) and exc.args else str(exc)
    return " ".join(text.split()) or type(exc).__name__


def _quiet_stdout() -> None:
    """After a broken pipe: point stdout at /dev/null so the interpreter's final flush is silent."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):
        pass


def run_command(name: str, func: Callable[[], Optional[int]], verbose: bool = False) -> int:
    """Run one command and turn what escapes it into the exit-code convention of this module."""
    try:
        code = int(func() or 0)
        sys.stdout.flush()
        return code
    except BrokenPipeError:
        _quiet_stdout()
        return EXIT_BROKEN_PIPE
    except SystemExit as e:
        if isinstance(e.code, str):  # a command's own one-line error
            print(e.code, file=sys.stderr)
            return EXIT_BAD_INPUT
        return int(e.code or 0)
    except KeyboardInterrupt as e:  # a command may say where it stopped (the message)
        print(f"tiger {name}: interrupted" + (f": {e}" if str(e) else ""), file=sys.stderr)
        return EXIT_INTERRUPTED
    except BAD_INPUT as e:
        if verbose and not isinstance(e, CliError):
            raise
        print(f"tiger {name}: error: {_one_line(e)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except Exception as e:  # noqa: BLE001 - a failure while running: one line unless -v
        if verbose:
            raise
        print(f"tiger {name}: error: {type(e).__name__}: {_one_line(e)} (run with -v for the traceback)",
              file=sys.stderr)
        return EXIT_FAILURE


def main(argv: Optional[Sequence[str]] = None) -> int:
    mark_command_start()
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "eval-lerf":  # its own parser (tiger.eval.lerf)
        return run_command("eval-lerf", lambda: lerf.delegate(argv[1:]), verbose="-v" in argv)
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(levelname)s %(name)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_BAD_INPUT
    try:
        return run_command(args.command, lambda: args.func(args), verbose=args.verbose)
    finally:
        _leave_process_group()


def _leave_process_group() -> None:
    """Under torchrun, tear down the process group a command set up before the interpreter exits:
    a rank that exited with its group alive could abort in the backend's threads at exit
    ("terminate called without an active exception": seen on a gloo rank with nothing to do)."""
    dist = sys.modules.get("torch.distributed")  # never imported here: only commands that use it
    if dist is not None and dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()


if __name__ == "__main__":
    sys.exit(main())

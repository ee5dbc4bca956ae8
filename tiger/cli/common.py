"""Shared pieces of the subcommands: options, errors, output folders, device choice."""
from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Optional

import torch


class CliError(Exception):
    """An error the user can act on: printed as one line, exit code 2."""


_command_start: Optional[float] = None


def mark_command_start() -> None:
    """Note when the command began (``tiger.cli.main`` calls it first): summaries time from here."""
    global _command_start
    _command_start = time.perf_counter()


def command_elapsed_s() -> float:
    """Seconds since :func:`mark_command_start` (0 when no command was marked)."""
    return 0.0 if _command_start is None else time.perf_counter() - _command_start


def positive_size(width: int, height: int, option: str = "--size") -> tuple[int, int]:
    """(width, height) when both are positive pixel counts, else a CliError naming ``option``."""
    if width <= 0 or height <= 0:
        raise CliError(f"{option} must be two positive pixel counts W H, got {width} {height}")
    return width, height


#: Bytes a rendered pixel costs on its way to a picture, per colour channel and fixed: the
#: rasterizer's float32 colour, alpha and depth, its per-pixel bookkeeping, the clamped copy
#: and the 8-bit pictures. Peak memory of a 3000x3000 colour + depth render of the demo scene on
#: the CPU grew by 79 bytes a pixel; 12 * 3 + 44 = 80.
_BYTES_PER_PIXEL_CHANNEL, _BYTES_PER_PIXEL_FIXED = 12, 44


def render_bytes(width: int, height: int, channels: int = 3) -> int:
    """Estimated peak memory of rendering one ``width`` x ``height`` picture with ``channels``."""
    return width * height * (channels * _BYTES_PER_PIXEL_CHANNEL + _BYTES_PER_PIXEL_FIXED)


def available_bytes(device: torch.device) -> int:
    """Free memory on ``device``: the GPU's free memory, or the host's MemAvailable."""
    if device.type == "cuda":
        return int(torch.cuda.mem_get_info(device)[0])
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    import os

    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_AVPHYS_PAGES")


def check_render_size(width: int, height: int, device: torch.device, channels: int = 3,
                      option: str = "--size") -> None:
    """Refuse, before any work, a picture whose render would not fit in ``device``'s memory."""
    need, have = render_bytes(width, height, channels), available_bytes(device)
    if need > have:
        raise CliError(f"{option} {width}x{height}: one view needs about {need / 2**30:.1f} GiB to render, "
                       f"{device.type} memory has {have / 2**30:.1f} GiB free; choose a smaller size")


def views_per_pass(width: int, height: int, device: torch.device, channels: int = 3) -> int:
    """How many views of ``width`` x ``height`` to render together (:func:`tiger.scene.render_view_chunks`):
    up to its default, as many as half of ``device``'s free memory holds by :func:`render_bytes`
    (at least one: :func:`check_render_size` has refused a view that does not fit)."""
    from tiger.scene.gaussian_scene import RGB_VIEWS_PER_PASS

    fit = available_bytes(device) // (2 * render_bytes(width, height, channels))
    return int(max(1, min(RGB_VIEWS_PER_PASS, fit)))


def add_common(p: argparse.ArgumentParser, out_default: Optional[str] = None,
               models: bool = False) -> None:
    """--device, --out, --force (and --models) with the same meaning in every subcommand."""
    p.add_argument("--device", default="auto",
                   help="cpu, cuda, cuda:N or auto (cuda when available; default: %(default)s)")
    p.add_argument("--out", default=out_default, required=out_default is None,
                   help="output path" + (" (default: %(default)s)" if out_default else ""))
    p.add_argument("--force", action="store_true", help="overwrite existing outputs")
    if models:
        p.add_argument("--models", default=None,
                       help="model folder or JSON config {name: path} (default: $TIGER_MODELS)")


def device_of(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
    except RuntimeError as e:
        raise CliError(f"--device {name!r} is not a device (use cpu, cuda, cuda:N or auto)") from e
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise CliError(f"--device {name}: CUDA is not available on this machine")
    return dev


def output_dir(path: str, force: bool, create: bool = True, ignore: tuple[str, ...] = ()) -> Path:
    """A folder to write into: refuses a non-empty one unless --force. ``create=False`` only
    checks (for commands that validate everything else before making the folder); entries
    named in ``ignore`` (caches a rerun reuses) do not count as content."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise CliError(f"{out} exists and is not a folder")
    if out.exists() and any(p.name not in ignore for p in out.iterdir()) and not force:
        raise CliError(f"{out} already exists and is not empty; pass --force to overwrite it")
    if create:
        out.mkdir(parents=True, exist_ok=True)
    return out


def output_file(path: str, force: bool) -> Path:
    out = Path(path)
    if out.exists() and not force:
        raise CliError(f"{out} already exists; pass --force to overwrite it")
    out.parent.mkdir(parents=True, exist_ok=True)
    return out


def existing(path: str, what: str) -> Path:
    p = Path(path)
    if not p.exists():
        raise CliError(f"{what} {p} does not exist")
    return p


def add_skip_missing(p: argparse.ArgumentParser) -> None:
    p.add_argument("--skip-missing", action="store_true",
                   help="drop the dataset's views whose image file is missing (default: refuse, naming them)")


def open_dataset(path: str, skip_missing: bool = False):
    """``tiger.scene.dataset.load_dataset`` with its errors in the command line's terms."""
    from tiger.scene import MissingImagesError
    from tiger.scene.dataset import load_dataset

    try:
        return load_dataset(existing(path, "dataset"), skip_missing=skip_missing)
    except MissingImagesError as e:
        raise CliError(str(e.with_hint("pass --skip-missing to skip them"))) from None


def load_scene(path: str, device: Optional[torch.device] = None):
    """A scene PLY, or the scene of a `tiger prepare` folder."""
    from tiger.scene import GaussianScene

    from .prepare import prepared_scene

    scene = GaussianScene.load_ply(prepared_scene(existing(path, "scene file")))
    return scene.to(device) if device is not None else scene


class Summary:
    """Collects lines for the summary printed at the end of a command."""

    def __init__(self, title: str) -> None:
        self.title, self.lines = title, []
        # The command's own start (tiger.cli.main marks it), not this object's: summaries are
        # often made after the work.
        self.t0 = _command_start if _command_start is not None else time.perf_counter()

    def add(self, text: str) -> None:
        self.lines.append(text)

    def print(self) -> None:
        print(f"\n{self.title} done in {time.perf_counter() - self.t0:.1f} s")
        for line in self.lines:
            print(f"  {line}")


# --- selection: one --tau parser and one guard for every command that selects by text ---------

TAU_RULE_NAMES = ("auto", "valley", "kittler", "otsu")
TAU_HELP = ("selection threshold: a number, or a rule: auto (default: the emptiest stretch below "
            "the highest-scoring cluster of scores, so 'plant' does not also take the other objects "
            "on the table), valley (the same between two classes only), kittler "
            "(Kittler-Illingworth minimum error), otsu. Rules run on the cosine, or on the margin to "
            "the hardest canonical negative for --score relevancy (never below 0.5 there)")


def parse_tau(text: str):
    """argparse ``type`` of ``--tau``: a rule name (case-insensitive) or a finite number."""
    low = text.strip().lower()
    if low in TAU_RULE_NAMES:
        return low
    try:
        value = float(low)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number or one of {', '.join(TAU_RULE_NAMES)}, "
                                         f"got {text!r}") from None
    if value != value or value in (float("inf"), float("-inf")):
        raise argparse.ArgumentTypeError(f"must be finite, got {text!r}")
    return value


def add_selection_options(p: argparse.ArgumentParser, guarded: bool) -> None:
    """--score and --tau; ``guarded``: the command refuses a suspect selection without --force."""
    p.add_argument("--score", choices=("cosine", "relevancy"), default="cosine",
                   help="per-Gaussian score: cosine with the text (default), or LERF relevancy "
                        "against the canonical negatives (object, things, stuff, texture)")
    guard = ("A selection holding more than half of the scene's Gaussians, or falling into several "
             "separate groups in space, is " + ("refused unless --force is given" if guarded else
                                                 "reported with a warning") + ".")
    p.add_argument("--tau", type=parse_tau, default="auto", help=f"{TAU_HELP}. {guard}")


def check_selection_or_refuse(scene, mask, text: str, force: bool, command: str) -> None:
    """The selection guard (:mod:`tiger.retrieval.guard`) for edit and delete: a CliError naming
    the problem unless ``force``; with ``force`` a warning."""
    from tiger.retrieval import check_selection

    check = check_selection(scene.means, mask)
    if check.ok:
        return
    msg = f"{text!r}: {check.problem}"
    if not force:
        raise CliError(f"{msg}; look at `tiger query` pictures and choose --tau or --score, or pass "
                       f"--force to {command} it anyway")
    warn(f"{msg} (going on: --force)")


def warn(text: str) -> None:
    """One warning line on stderr."""
    import sys

    print(f"warning: {text}", file=sys.stderr)


# --- run records: a resume continues the same run, nothing finished is overwritten ----------------

RUN_RECORD = "tiger_run.json"
#: Options that do not change a command's result: they may differ between a run and its resume.
NOT_SETTINGS = frozenset({"func", "command", "device", "force", "resume", "out", "verbose"})


def _file_id(path: Path) -> dict:
    """What identifies an input file's contents cheaply: size and a hash of its first and last MiB."""
    import hashlib

    h = hashlib.sha1()
    size = path.stat().st_size
    with open(path, "rb") as fh:
        h.update(fh.read(1 << 20))
        if size > 2 << 20:
            fh.seek(size - (1 << 20))
            h.update(fh.read())
    return {"path": str(path.resolve()), "bytes": size, "sha1_ends": h.hexdigest()}


def run_settings(args: argparse.Namespace, ignore: tuple = ()) -> dict:
    """The options of a command that decide its result (``NOT_SETTINGS`` and ``ignore`` left out);
    an option naming an existing file is recorded with its size and content hash, a folder by its
    absolute path, so a resume on a changed scene is caught even under the same name."""
    out = {}
    for key, value in sorted(vars(args).items()):
        if key in NOT_SETTINGS or key in ignore:
            continue
        if isinstance(value, str) and value and Path(value).is_file():
            value = _file_id(Path(value))
        elif isinstance(value, str) and value and Path(value).is_dir():
            value = str(Path(value).resolve())
        elif isinstance(value, tuple):
            value = list(value)
        out[key] = value
    return out


def _differences(old: dict, new: dict) -> list[str]:
    """'--name: was A, now B' for each setting that differs."""
    lines = []
    for key in sorted(set(old) | set(new)):
        a, b = old.get(key), new.get(key)
        if a != b:
            show = lambda v: v.get("path", v) if isinstance(v, dict) else v  # noqa: E731
            what = "contents changed" if isinstance(a, dict) and isinstance(b, dict) and \
                a.get("path") == b.get("path") else f"was {show(a)!r}, now {show(b)!r}"
            lines.append(f"--{key.replace('_', '-')} ({what})")
    return lines


def check_record(rec: Path, command: str, settings: dict, where: str) -> None:
    """A CliError unless the run record ``rec`` is of ``command`` with these ``settings``; the
    message names every setting that differs."""
    import json

    try:
        old = json.loads(rec.read_text())
    except (OSError, ValueError) as e:
        raise CliError(f"--resume: cannot read {rec}: {e}") from None
    if old.get("command") != command:
        raise CliError(f"--resume: {where} holds a `tiger {old.get('command')}` run, not `tiger {command}`")
    diff = _differences(old.get("settings", {}), settings)
    if diff:
        raise CliError(f"--resume: {where} holds another `tiger {command}` run; these differ: "
                       f"{'; '.join(diff)}. Use another --out, or the same settings")


def write_record(rec: Path, command: str, settings: dict, finished: bool = False,
                 results: Optional[dict] = None) -> None:
    """Write the run record ``rec`` atomically (``results``: what the finished run measured)."""
    import json

    from tiger.utils.io import atomic_write

    rec.parent.mkdir(parents=True, exist_ok=True)
    data = {"command": command, "settings": settings, "finished": finished}
    if results is not None:
        data["results"] = results
    with atomic_write(rec, "w") as fh:
        json.dump(data, fh, indent=2, default=str)


def claim_output(path: str, command: str, settings: dict, *, force: bool, resume: bool,
                 record: Optional[Path] = None, leftovers: tuple = ()) -> Path:
    """Check and make a command's output folder, before anything is written into it.

    * ``resume``: an empty or missing folder starts afresh; otherwise the folder must hold the run
      record of the same command with the same ``settings`` (``record``, default
      ``OUT/tiger_run.json``), else a CliError naming what differs (whatever ``force`` says: a
      resume never continues another run's state).
    * otherwise a non-empty folder is refused unless ``force`` (then the run starts afresh in it).

    * ``leftovers``: names (caches) that a stopped run may leave; a folder holding only those and
      an unfinished record of the same command is not a finished result, so a rerun may reuse it.

    Writes the record with ``finished: false``; :func:`finish_output` marks it finished.
    """
    import json

    out = Path(path)
    rec = record or out / RUN_RECORD
    if out.exists() and not out.is_dir():
        raise CliError(f"{out} exists and is not a folder")
    busy = out.is_dir() and any(out.iterdir())
    if busy and not resume and leftovers and rec.is_file():
        try:
            stopped = json.loads(rec.read_text())
        except (OSError, ValueError):
            stopped = {}
        rest = [q.name for q in out.iterdir() if q.name not in leftovers and q != rec]
        busy = bool(rest) or stopped.get("command") != command or bool(stopped.get("finished"))
    if resume and busy:
        if not rec.is_file():
            held = ", ".join(sorted(p.name for p in out.iterdir())[:5])
            raise CliError(f"--resume: {out} holds no record of a `tiger {command}` run ({rec.name} is "
                           f"missing; it holds {held}), so it cannot be resumed; use another --out, or "
                           "--force without --resume to start afresh in it")
        check_record(rec, command, settings, str(out))
    elif busy and not force:
        raise CliError(f"{out} already exists and is not empty; pass --force to overwrite it"
                       + (" or --resume to continue it" if rec.is_file() else ""))
    out.mkdir(parents=True, exist_ok=True)
    write_record(rec, command, settings)
    return out


def finish_output(out: Path, command: str, record: Optional[Path] = None) -> None:
    """Mark the run record in ``out`` finished (after every result is written)."""
    import json

    from tiger.utils.io import atomic_write

    rec = record or Path(out) / RUN_RECORD
    data = json.loads(rec.read_text()) if rec.is_file() else {"command": command, "settings": {}}
    data["finished"] = True
    with atomic_write(rec, "w") as fh:
        json.dump(data, fh, indent=2, default=str)

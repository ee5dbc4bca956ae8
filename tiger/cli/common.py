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

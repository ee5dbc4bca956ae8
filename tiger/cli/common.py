"""Shared pieces of the subcommands: options, errors, output folders, device choice."""
from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Optional

import torch


class CliError(Exception):
    """An error the user can act on: printed as one line, exit code 2."""


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


def output_dir(path: str, force: bool, create: bool = True) -> Path:
    """A folder to write into: refuses a non-empty one unless --force. ``create=False`` only
    checks (for commands that validate everything else before making the folder)."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise CliError(f"{out} exists and is not a folder")
    if out.exists() and any(out.iterdir()) and not force:
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
        self.title, self.lines, self.t0 = title, [], time.perf_counter()

    def add(self, text: str) -> None:
        self.lines.append(text)

    def print(self) -> None:
        print(f"\n{self.title} done in {time.perf_counter() - self.t0:.1f} s")
        for line in self.lines:
            print(f"  {line}")

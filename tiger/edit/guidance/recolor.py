"""``recolor``: a built-in guidance that needs no weights (SPEC §6).

Per view, a target image is made from the *original* render: where the edited object is (the
rendered object mask ``m`` of :class:`~tiger.edit.guidance.base.ViewBatch`), the pixel becomes
the requested colour times the pixel's shading; elsewhere it stays the original:

    Y(p)      = 0.2126 R + 0.7152 G + 0.0722 B                  (Rec. 709 luminance)
    shade(p)  = Y(p) / Y_ref,  Y_ref = mask-weighted mean of Y over the object in that view
    target(p) = (1 - m(p)) · original(p) + m(p) · clamp(colour · shade(p) · strength + original(p) · (1 - strength), 0, 1)

so dark folds stay dark and highlights stay bright, with the object's mean brightness set by the
colour. The loss is ``0.5 · mean((x - target)²)`` over all pixels of all views and the returned
gradient is its derivative times the pixel count of one view, ``(x - target) / V``: outside the
object it pulls back toward the original (a locality anchor). Deterministic.
"""
from __future__ import annotations

import re
import time
from typing import Any, Optional, Sequence, Union

import torch

from .base import GuidanceInfo, ViewBatch, check_renders

#: Colour names understood in instructions (sRGB in [0, 1]).
COLORS: dict[str, tuple[float, float, float]] = {
    "red": (0.86, 0.08, 0.08), "green": (0.1, 0.65, 0.15), "blue": (0.1, 0.25, 0.9),
    "yellow": (0.95, 0.85, 0.1), "orange": (1.0, 0.5, 0.05), "purple": (0.5, 0.15, 0.7),
    "violet": (0.55, 0.3, 0.85), "pink": (1.0, 0.45, 0.7), "white": (0.95, 0.95, 0.95),
    "black": (0.05, 0.05, 0.05), "gray": (0.5, 0.5, 0.5), "grey": (0.5, 0.5, 0.5),
    "brown": (0.45, 0.27, 0.1), "cyan": (0.1, 0.8, 0.85), "magenta": (0.85, 0.1, 0.75),
    "gold": (0.9, 0.72, 0.2), "golden": (0.9, 0.72, 0.2), "silver": (0.75, 0.75, 0.78),
    "teal": (0.0, 0.5, 0.5), "turquoise": (0.25, 0.85, 0.8), "beige": (0.9, 0.85, 0.7),
}

#: Words before a colour name that change it: darker (x 0.55), lighter (halfway to white), brighter.
SHADES: dict[str, str] = {"dark": "dark", "deep": "dark", "light": "light", "pale": "light",
                          "pastel": "light", "bright": "bright", "vivid": "bright"}
#: Words that negate a colour ("not red"): refused, since no single colour is meant.
NEGATIONS = frozenset({"not", "no", "non", "without", "except", "never", "nor"})

ColorLike = Union[str, Sequence[float], torch.Tensor]
_LUMA = (0.2126, 0.7152, 0.0722)


def parse_color(color: ColorLike) -> torch.Tensor:
    """[3] RGB in [0, 1] from a colour name, an instruction naming one ("make the ball red"; with
    several, the last: "make the green ball red" is red), optionally shaded by the word before it
    ("dark green", "light blue": :data:`SHADES`), ``#rrggbb``, ``"r,g,b"`` (0-1 or 0-255) or a
    sequence / tensor of 3 numbers. A negated colour ("not red") is a ValueError."""
    if isinstance(color, str):
        text = color.strip().lower()
        hexm = re.fullmatch(r"#?([0-9a-f]{6})", text)
        if hexm:
            v = int(hexm.group(1), 16)
            return torch.tensor([(v >> 16) & 255, (v >> 8) & 255, v & 255], dtype=torch.float64) / 255
        nums = re.fullmatch(r"\(?\s*([\d.]+)\s*,\s*([\d.]+)\s*,\s*([\d.]+)\s*\)?", text)
        if nums:
            return parse_color([float(g) for g in nums.groups()])
        words = re.findall(r"[a-z]+", text)
        found = [i for i, w in enumerate(words) if w in COLORS]
        if not found:
            raise ValueError(f"tiger.edit.recolor: no colour found in {color!r}; use one of "
                             f"{sorted(COLORS)}, '#rrggbb' or 'r,g,b'")
        negated = [words[i] for i in found if any(w in NEGATIONS for w in words[max(0, i - 3):i])]
        if negated:
            raise ValueError(f"tiger.edit.recolor: {color!r} negates {negated[0]!r}; name the colour to use "
                             "(e.g. --color blue or '#3366cc')")
        i = found[-1]
        rgb = torch.tensor(COLORS[words[i]], dtype=torch.float64)
        shade = SHADES.get(words[i - 1]) if i > 0 else None
        if shade == "dark":
            rgb = rgb * 0.55
        elif shade == "light":
            rgb = rgb + (1 - rgb) * 0.5
        elif shade == "bright":
            rgb = (rgb * 1.25).clamp(max=1.0)
        return rgb
    t = torch.as_tensor(color, dtype=torch.float64).reshape(-1)
    if t.numel() != 3 or not bool(torch.isfinite(t).all()) or float(t.min()) < 0:
        raise ValueError(f"tiger.edit.recolor: a colour needs 3 non-negative numbers, got {color!r}")
    return t / 255 if float(t.max()) > 1 else t


class RecolorGuidance:
    """Pulls the object's pixels toward a colour, keeping their shading (see the module docstring).

    Args:
        instruction: the edit text; the colour is the last colour word in it ("make the ball red"),
            or ``#rrggbb`` / ``r,g,b`` (:func:`parse_color`) unless ``color`` is given.
        color: the colour, overriding the instruction's: a name, ``#rrggbb``, ``r,g,b`` or 3 numbers.
        strength: 1 replaces the object's colour; smaller values blend toward the original.
    """

    name = "recolor"

    def __init__(self, instruction: str, *, color: Optional[ColorLike] = None, strength: float = 1.0) -> None:
        if not isinstance(instruction, str) or not instruction.strip():
            raise ValueError("tiger.edit.recolor: the instruction must be a non-empty string")
        self.instruction = instruction
        self.color = parse_color(instruction if color is None else color)
        if not 0.0 < float(strength) <= 1.0:
            raise ValueError(f"tiger.edit.recolor: strength must be in (0, 1], got {strength}")
        self.strength = float(strength)

    def settings(self) -> dict[str, Any]:
        """The colour (sRGB in [0, 1]) and the strength."""
        return {"color": [round(float(c), 6) for c in self.color], "strength": self.strength}

    def generators(self) -> list[torch.Generator]:
        """None: recolor is deterministic."""
        return []

    def reset_caches(self) -> None:
        """Nothing is cached across steps."""

    def targets(self, views: ViewBatch) -> torch.Tensor:
        """[V, 3, H, W] target images for the views (original outside the object)."""
        orig = views.originals
        if views.masks is None:
            raise ValueError("tiger.edit.recolor: needs views.masks (the rendered object mask)")
        m = views.masks.to(orig)
        if m.shape != (orig.shape[0], 1, *orig.shape[2:]):
            raise ValueError(f"tiger.edit.recolor: masks must be [V, 1, H, W] = "
                             f"{[orig.shape[0], 1, *orig.shape[2:]]}, got {list(m.shape)}")
        luma = torch.tensor(_LUMA, dtype=orig.dtype, device=orig.device).view(1, 3, 1, 1)
        y = (orig * luma).sum(1, keepdim=True)
        y_ref = (y * m).sum((1, 2, 3), keepdim=True) / m.sum((1, 2, 3), keepdim=True).clamp_min(1e-6)
        shade = y / y_ref.clamp_min(1e-4)
        col = self.color.to(orig).view(1, 3, 1, 1)
        s = self.strength
        recol = (col * shade * s + orig * (1 - s)).clamp(0, 1)
        return (1 - m) * orig + m * recol

    def grad(self, renders: torch.Tensor, views: ViewBatch) -> tuple[torch.Tensor, GuidanceInfo]:
        """``(x - target) / V`` and the loss ``0.5 mean((x - target)^2)``."""
        t0 = time.perf_counter()
        check_renders(renders, self.name)
        if views.originals.shape != renders.shape:
            raise ValueError(f"tiger.edit.recolor: views.originals {list(views.originals.shape)} must match "
                             f"renders {list(renders.shape)}")
        tgt = self.targets(views).to(renders)
        diff = renders - tgt
        loss = 0.5 * float(diff.square().mean())
        g = diff / renders.shape[0]
        return g, GuidanceInfo(loss=loss, timings_ms={"recolor": 1e3 * (time.perf_counter() - t0)})


__all__ = ["COLORS", "NEGATIONS", "SHADES", "RecolorGuidance", "parse_color"]

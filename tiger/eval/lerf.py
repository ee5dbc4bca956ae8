"""LERF localization accuracy and mIoU (the paper's Table 1; LangSplat's protocol on LERF-OVS).

Labels: one LabelMe-style JSON per test frame, ``<scene>/frame_00041.json``::

    {"info": {"name": "frame_00041.jpg", "width": W, "height": H},
     "objects": [{"category": "red cup", "bbox": [x1, y1, x2, y2], "segmentation": [[x, y], ...]}, ...]}

Instances of one category are merged (all their boxes; the union of their polygons). For every
(frame, category): render the relevancy map, smooth it with a 30x30 mean filter (OpenCV's
filter2D, exactly), take the pixel(s) of maximum value; a hit if any of them lies inside any box
of the category (bounds inclusive). Accuracy per scene = hits / queries, overall = mean over scenes.
mIoU (LangSplat's variant): ``v = (map + filtered) / 2``, min-max normalised, ``clip(2 v - 1, 0, 1)
> thresh`` (0.4), 7x7 majority smoothing, IoU with the polygon mask.

CLI: ``python -m tiger.eval.lerf --labels LABEL_DIR --scene NAME=PLY --data NAME=DATASET ...``
(see ``--help``); prints the table and writes ``results.json``, ``table.md`` and pictures.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import re
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional, Sequence, Union

import numpy as np
import torch

from tiger.retrieval.text import EmbeddingTable, PCASource, TextEncoder
from tiger.render import Camera
from tiger.scene import GaussianScene
from tiger.utils.io import atomic_write, file_slug

from .filters import argmax_points, majority_smooth, mean_filter
from .polygon import polygon_mask

log = logging.getLogger(__name__)
PathLike = Union[str, os.PathLike]

#: Reported localization accuracies (%) on LERF-OVS, paper Table 1 (TIGER's re-run of LangSplat).
PUBLISHED = {"LERF": 73.6, "LangSplat": 77.4, "TIGER": 87.0}


# ---------------------------------------------------------------------------------- labels
@dataclass
class CategoryLabel:
    """Ground truth of one category in one frame: boxes [K, 4] (x1, y1, x2, y2) and the union of
    its instance polygons as an [H, W] bool mask."""

    boxes: np.ndarray
    mask: np.ndarray


@dataclass
class FrameLabels:
    """One labelled frame: ``name`` (file stem, e.g. ``frame_00041``), ``index`` (the frame
    number - 1, LangSplat's index into the sorted views), size, and labels by category."""

    name: str
    index: int
    height: int
    width: int
    categories: dict
    image_path: Optional[Path] = None


def _field(d: Any, key: str, path: Path, where: str) -> Any:
    if not isinstance(d, dict) or key not in d:
        raise ValueError(f"tiger.eval.lerf: {path}: missing field '{key}' in {where}")
    return d[key]


def load_frame_labels(path: PathLike) -> FrameLabels:
    """Read one LabelMe-style label file (see the module docstring)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"tiger.eval.lerf: {path} is not valid JSON ({exc})") from exc
    info = _field(data, "info", path, "the file")
    h, w = int(_field(info, "height", path, "info")), int(_field(info, "width", path, "info"))
    if h <= 0 or w <= 0:
        raise ValueError(f"tiger.eval.lerf: {path}: image size must be positive, got {w}x{h}")
    name = str(info.get("name", path.stem + ".jpg"))
    stem = Path(name).stem
    m = re.search(r"(\d+)$", stem)
    index = int(m.group(1)) - 1 if m else -1
    objs = _field(data, "objects", path, "the file")
    if not isinstance(objs, list):
        raise ValueError(f"tiger.eval.lerf: {path}: 'objects' must be a list")
    cats: dict[str, CategoryLabel] = {}
    for i, ob in enumerate(objs):
        where = f"objects[{i}]"
        cat = str(_field(ob, "category", path, where))
        box = np.asarray(_field(ob, "bbox", path, where), dtype=np.float64).reshape(-1)
        if box.shape != (4,) or not np.isfinite(box).all():
            raise ValueError(f"tiger.eval.lerf: {path}: {where}.bbox must be 4 finite numbers [x1, y1, x2, y2]")
        seg = ob.get("segmentation") or []
        try:
            mask = polygon_mask(h, w, seg) if len(seg) else np.zeros((h, w), dtype=bool)
        except (ValueError, TypeError) as exc:
            raise ValueError(f"tiger.eval.lerf: {path}: {where}.segmentation must be [[x, y], ...] ({exc})") from exc
        if cat in cats:
            cats[cat].boxes = np.concatenate([cats[cat].boxes, box[None]], axis=0)
            cats[cat].mask |= mask
        else:
            cats[cat] = CategoryLabel(boxes=box[None].copy(), mask=mask)
    img = None
    for cand in (path.with_name(name), path.with_suffix(".jpg"), path.with_suffix(".png")):
        if cand.is_file():
            img = cand
            break
    return FrameLabels(name=stem, index=index, height=h, width=w, categories=cats, image_path=img)


def load_scene_labels(folder: PathLike) -> list[FrameLabels]:
    """All ``*.json`` label files of one scene's folder, sorted by name."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"tiger.eval.lerf: label folder {folder} does not exist")
    files = sorted(folder.glob("*.json"))
    if not files:
        raise FileNotFoundError(f"tiger.eval.lerf: no label files (*.json) in {folder}")
    return [load_frame_labels(f) for f in files]


# ---------------------------------------------------------------------------------- metric
def localize(relevancy_map: torch.Tensor, size: int = 30) -> tuple[torch.Tensor, torch.Tensor]:
    """(maximum points [P, 2] as (x, y), smoothed map [H, W]) of a relevancy map [H, W]."""
    return argmax_points(relevancy_map, size)


def points_in_boxes(points: torch.Tensor, boxes: np.ndarray) -> bool:
    """True when any (x, y) point lies in any box (x1, y1, x2, y2), bounds inclusive, corners in
    any order."""
    if len(points) == 0 or len(boxes) == 0:
        return False
    p = points.detach().cpu().double().numpy().reshape(-1, 1, 2)
    b = np.asarray(boxes, dtype=np.float64).reshape(1, -1, 4)
    x0, x1 = np.minimum(b[..., 0], b[..., 2]), np.maximum(b[..., 0], b[..., 2])
    y0, y1 = np.minimum(b[..., 1], b[..., 3]), np.maximum(b[..., 1], b[..., 3])
    inside = (p[..., 0] >= x0) & (p[..., 0] <= x1) & (p[..., 1] >= y0) & (p[..., 1] <= y1)
    return bool(inside.any())


def langsplat_mask(relevancy_map: torch.Tensor, size: int = 30, thresh: float = 0.4) -> torch.Tensor:
    """LangSplat's predicted mask for the IoU (see the module docstring): [H, W] bool."""
    v = 0.5 * (mean_filter(relevancy_map, size) + relevancy_map.detach().double())
    v = v - v.min()
    v = v / (v.max() + 1e-9)
    v = (v * 2.0 - 1.0).clamp(0.0, 1.0)
    return majority_smooth(v > thresh)


def mask_iou(pred: torch.Tensor, gt: np.ndarray) -> float:
    """IoU of two [H, W] masks (0 when both are empty)."""
    g = torch.as_tensor(np.asarray(gt, dtype=bool))
    p = pred.detach().cpu().bool()
    union = int((p | g).sum())
    return int((p & g).sum()) / union if union else 0.0


# ------------------------------------------------------------------------------ evaluation
@dataclass
class QueryResult:
    frame: str
    category: str
    hit: bool
    points: list
    peak: float
    iou: float


@dataclass
class SceneResult:
    name: str
    queries: list = field(default_factory=list)

    @property
    def accuracy(self) -> float:
        return sum(q.hit for q in self.queries) / len(self.queries) if self.queries else float("nan")

    @property
    def miou(self) -> float:
        return sum(q.iou for q in self.queries) / len(self.queries) if self.queries else float("nan")

    @property
    def hits(self) -> int:
        return sum(q.hit for q in self.queries)


RelevancyFn = Callable[[FrameLabels, list], torch.Tensor]
ImageFn = Callable[[FrameLabels], Optional[torch.Tensor]]


def _fit(map_: torch.Tensor, h: int, w: int) -> torch.Tensor:
    if tuple(map_.shape[-2:]) == (h, w):
        return map_
    return torch.nn.functional.interpolate(map_[None].float(), size=(h, w), mode="bilinear",
                                           align_corners=False)[0]


def evaluate_scene(name: str, labels: Sequence[FrameLabels], relevancy_fn: RelevancyFn, *,
                   image_fn: Optional[ImageFn] = None, out_dir: Optional[PathLike] = None,
                   size: int = 30, mask_thresh: float = 0.4, pictures: bool = True,
                   progress: bool = True) -> SceneResult:
    """Localization accuracy and mIoU of one scene.

    Args:
        labels: the scene's frames (:func:`load_scene_labels`).
        relevancy_fn: ``(frame, categories) -> [Q, h, w]`` relevancy maps (resized to the label
            size when they differ).
        image_fn: ``frame -> [H, W, 3]`` picture background (default: the frame's image file).
        out_dir: where pictures go (``<out_dir>/<frame>/<category>.png``).
    """
    from tiger.utils.progress import progress as progress_bar

    res = SceneResult(name)
    for fr in progress_bar(labels, f"lerf {name}", unit="frame", disable=not progress):
        cats = list(fr.categories)
        if not cats:
            continue
        maps = torch.as_tensor(relevancy_fn(fr, cats))
        if maps.dim() != 3 or maps.shape[0] != len(cats):
            raise ValueError(f"tiger.eval.lerf: relevancy_fn returned {list(maps.shape)} for {len(cats)} "
                             f"categories of {fr.name}; expected [Q, H, W]")
        maps = _fit(maps.detach().cpu().double(), fr.height, fr.width)
        image = None
        if pictures and out_dir is not None:
            image = image_fn(fr) if image_fn is not None else _read_image(fr)
        for q, cat in enumerate(cats):
            lab = fr.categories[cat]
            pts, smoothed = localize(maps[q], size)
            hit = points_in_boxes(pts, lab.boxes)
            iou = mask_iou(langsplat_mask(maps[q], size, mask_thresh), lab.mask)
            res.queries.append(QueryResult(fr.name, cat, hit, pts.tolist(), float(smoothed.max()), iou))
            if pictures and out_dir is not None:
                _picture(Path(out_dir) / name / fr.name / f"{file_slug(cat)}.png", maps[q], smoothed, image,
                         lab.boxes, pts, f"{cat}: {'hit' if hit else 'miss'}")
    log.info("lerf %s: %d/%d hits (%.1f %%), mIoU %.3f", name, res.hits, len(res.queries),
             100 * res.accuracy, res.miou)
    return res


def _read_image(fr: FrameLabels) -> Optional[torch.Tensor]:
    if fr.image_path is None:
        return None
    from PIL import Image

    with Image.open(fr.image_path) as im:
        arr = np.asarray(im.convert("RGB").resize((fr.width, fr.height)), dtype=np.float32) / 255.0
    return torch.from_numpy(arr)


def _picture(path: Path, raw: torch.Tensor, smoothed: torch.Tensor, image: Optional[torch.Tensor],
             boxes: np.ndarray, points: torch.Tensor, title: str) -> None:
    from tiger.retrieval.maps import save_heatmap

    # LangSplat's display: the mean of the map and its smoothed version, shown above 0.5.
    shown = 0.5 * (raw + smoothed)
    save_heatmap(path, shown, image, title=title, vmin=0.5, vmax=1.0, below=0.5, boxes=boxes.tolist(),
                 points=points.tolist(), label="relevancy")


def format_table(results: Sequence[SceneResult]) -> str:
    """Markdown table: per scene queries, hits, accuracy, mIoU; the mean over scenes; the paper's
    reported numbers for reference."""
    lines = ["| scene | queries | hits | localization acc. (%) | mIoU (%) |",
             "|---|---:|---:|---:|---:|"]
    for r in results:
        lines.append(f"| {r.name} | {len(r.queries)} | {r.hits} | {100 * r.accuracy:.1f} | {100 * r.miou:.1f} |")
    if results:
        acc = sum(r.accuracy for r in results) / len(results)
        miou = sum(r.miou for r in results) / len(results)
        lines.append(f"| **mean over scenes** | {sum(len(r.queries) for r in results)} | "
                     f"{sum(r.hits for r in results)} | **{100 * acc:.1f}** | {100 * miou:.1f} |")
    lines.append("")
    lines.append("Reported overall localization accuracy (paper Table 1): " +
                 ", ".join(f"{k} {v:.1f} %" for k, v in PUBLISHED.items()))
    return "\n".join(lines)


def write_results(results: Sequence[SceneResult], out_dir: PathLike) -> tuple[Path, Path]:
    """``results.json`` (every query) and ``table.md`` in ``out_dir``, written atomically."""
    out = Path(out_dir)
    data = {"scenes": [{"name": r.name, "accuracy": r.accuracy, "miou": r.miou, "hits": r.hits,
                        "queries": [asdict(q) for q in r.queries]} for r in results]}
    if results:
        data["mean_accuracy"] = sum(r.accuracy for r in results) / len(results)
        data["mean_miou"] = sum(r.miou for r in results) / len(results)
    j, t = out / "results.json", out / "table.md"
    with atomic_write(j, "w") as fh:
        json.dump(data, fh, indent=1)
    with atomic_write(t, "w") as fh:
        fh.write(format_table(results) + "\n")
    return j, t


# --------------------------------------------------------------------- scenes -> relevancy
def match_cameras(labels: Sequence[FrameLabels], cameras: Sequence[Camera]) -> dict[str, Camera]:
    """frame name -> camera: by image name stem (``frame_00041``), else by LangSplat's index
    (frame number - 1 into the cameras sorted by name)."""
    by_stem = {Path(c.image_name).stem: c for c in cameras}
    ordered = sorted(cameras, key=lambda c: c.image_name)
    out = {}
    for fr in labels:
        if fr.name in by_stem:
            out[fr.name] = by_stem[fr.name]
        elif 0 <= fr.index < len(ordered):
            out[fr.name] = ordered[fr.index]
            log.debug("lerf: %s matched to camera %d by index", fr.name, fr.index)
        else:
            raise ValueError(f"tiger.eval.lerf: no camera for label frame {fr.name} (by name or index "
                             f"{fr.index} among {len(cameras)} cameras)")
    return out


def scene_relevancy_fn(scene: GaussianScene, cameras: Sequence[Camera], labels: Sequence[FrameLabels],
                       *, encoder: Optional[TextEncoder] = None, pca: PCASource = None,
                       score: str = "relevancy",
                       negatives: Union[None, Sequence[str], torch.Tensor] = None) -> RelevancyFn:
    """A ``relevancy_fn`` that renders the scene's L at each frame's camera and scores the pixels
    (one render per frame, all of its categories in one relevancy pass)."""
    from tiger.retrieval.maps import relevancy_maps
    from tiger.retrieval.text import CANONICAL_NEGATIVES, embed_negatives, embed_queries

    cams = match_cameras(labels, cameras)
    d = scene.lang.shape[1]
    pca_src = pca if pca is not None else scene
    neg = embed_negatives(CANONICAL_NEGATIVES if negatives is None else negatives, dim=d, encoder=encoder,
                          pca=pca_src) if score == "relevancy" else None

    def fn(fr: FrameLabels, cats: list) -> torch.Tensor:
        q = embed_queries(cats, dim=d, encoder=encoder, pca=pca_src)
        maps = relevancy_maps(scene, cams[fr.name], q, neg)
        return maps["relevancy"] if score == "relevancy" else maps["cosine"]

    return fn


# -------------------------------------------------------------------------------------- CLI
def _pairs(items: Optional[Sequence[str]], flag: str) -> dict[str, str]:
    out = {}
    for it in items or []:
        if "=" not in it:
            raise SystemExit(f"tiger eval-lerf: {flag} takes NAME=PATH, got '{it}'")
        k, v = it.split("=", 1)
        out[k] = v
    return out


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m tiger.eval.lerf",
                                description="LERF-OVS localization accuracy (and mIoU) of language-embedded scenes.")
    p.add_argument("--labels", required=True, help="LERF-OVS label folder: one subfolder per scene with frame_*.json")
    p.add_argument("--scene", action="append", metavar="NAME=PLY", help="a scene PLY with lang_* (repeat per scene)")
    p.add_argument("--data", action="append", metavar="NAME=DATASET",
                   help="its cameras: COLMAP folder or transforms.json (tiger.scene.load_dataset)")
    p.add_argument("--clip", default=None, help="CLIP model folder (save_pretrained layout) for the text encoder")
    p.add_argument("--models", default=None,
                   help="model folder or JSON config {name: path} to find CLIP in when no --clip "
                        "(default: $TIGER_MODELS)")
    p.add_argument("--text-embeddings", default=None, help="torch.save'd {text: [F] tensor} instead of --clip")
    p.add_argument("--score", choices=("relevancy", "cosine"), default="relevancy")
    p.add_argument("--filter-size", type=int, default=30)
    p.add_argument("--mask-thresh", type=float, default=0.4)
    p.add_argument("--device", default="auto",
                   help="cpu, cuda, cuda:N or auto (cuda when available; default: %(default)s)")
    p.add_argument("--out", required=True, help="output folder (results.json, table.md, pictures)")
    p.add_argument("--force", action="store_true", help="write into a non-empty --out folder")
    p.add_argument("--no-pictures", action="store_true")
    return p


def _load_encoder(args: argparse.Namespace) -> TextEncoder:
    if args.text_embeddings:
        return EmbeddingTable.load(args.text_embeddings)
    from tiger.language.maskclip import MaskCLIP
    from tiger.models.paths import ModelNotFoundError

    try:
        return MaskCLIP.from_pretrained(args.clip, device=args.device, config=args.models)
    except ModelNotFoundError as e:
        raise SystemExit(f"tiger eval-lerf: {e}\n(give --clip MODEL_DIR, --models CONFIG or "
                         "--text-embeddings FILE)") from None


def main(argv: Optional[Sequence[str]] = None) -> int:
    """CLI entry (``python -m tiger.eval.lerf``); returns the exit status."""
    args = build_parser().parse_args(argv)
    if args.device == "auto":
        args.device = "cuda" if torch.cuda.is_available() else "cpu"
    out = Path(args.out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())) and not args.force:
        raise SystemExit(f"tiger eval-lerf: {out} already exists and is not empty; pass --force to write into it")
    scenes, data = _pairs(args.scene, "--scene"), _pairs(args.data, "--data")
    if not scenes:
        raise SystemExit("tiger eval-lerf: give at least one --scene NAME=PLY")
    missing = sorted(set(scenes) - set(data))
    if missing:
        raise SystemExit(f"tiger eval-lerf: no --data NAME=DATASET for {missing}")
    from tiger.scene.dataset import load_dataset

    encoder = _load_encoder(args)
    results = []
    for name, ply in scenes.items():
        folder = Path(args.labels) / name
        labels = load_scene_labels(folder if folder.is_dir() else args.labels)
        scene = GaussianScene.load_ply(ply).to(args.device)
        if scene.lang is None:
            raise SystemExit(f"tiger eval-lerf: {ply} has no language features (lang_*); train them first")
        cams = [c.to(args.device) for c in load_dataset(data[name]).cameras]
        fn = scene_relevancy_fn(scene, cams, labels, encoder=encoder, score=args.score)
        results.append(evaluate_scene(name, labels, fn, out_dir=args.out, size=args.filter_size,
                                      mask_thresh=args.mask_thresh, pictures=not args.no_pictures))
    print(format_table(results))
    j, t = write_results(results, args.out)
    print(f"\nwrote {j} and {t}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

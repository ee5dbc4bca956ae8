"""``extract_features``: per-pixel 64-d language feature maps for an image set (SPEC §1, §4).

Per image (stage 1, cached): MaskCLIP features -> FeatUp upsampling to the output resolution ->
L2 normalisation -> SAM finest-level masks -> masked average. The cache keeps the result
compactly (mask id map, per-mask means, and the features of pixels in no mask, float16) plus the
image's PCA statistics. Then (stage 2) one PCA 512 -> 64 is fitted over all images and every
image's map is projected and written as float16 [H, W, 64] with a validity mask.

Every file is written atomically; images already done are skipped, so an interrupted run
resumes. Under ``torchrun`` (or with ``rank``/``world_size``) each rank handles images
``rank, rank + world_size, ...`` on its own GPU; rank 0 fits the PCA between two barriers.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Sequence, Union

import torch
import torch.nn.functional as F

from tiger.ops.masked_average import masked_average
from tiger.utils.io import atomic_torch_save

from .featup import UPSAMPLERS, ImplicitConfig, JBUStack, upsample_features
from .maskclip import MaskCLIP, normalize_images, resize_for_patches
from .pca import PCABasis, StreamingPCA
from .sam_masks import SamMaskConfig, SamMaskGenerator

logger = logging.getLogger(__name__)

ImageLike = Union[str, os.PathLike, torch.Tensor]
CACHE_VERSION = 1


@dataclass
class FeatureConfig:
    """Settings of :func:`extract_features`.

    upsampler: the quality/speed switch, 'implicit' (FeatUp implicit, the paper's), 'jbu' or 'bilinear'.
    clip_long_side: MaskCLIP input long side in pixels (rounded to multiples of 16; 448 -> 28 patches).
    output_long_side / output_size: feature-map resolution (default: each image's own size).
    use_sam: SAM masked average on (the paper) or off.
    unmasked: pixels in no SAM mask 'keep' their upsampled feature, or are marked invalid ('ignore').
    """

    upsampler: str = "implicit"
    clip_long_side: int = 448
    output_long_side: int | None = None
    output_size: tuple[int, int] | None = None
    pca_dim: int = 64
    use_sam: bool = True
    unmasked: str = "keep"
    implicit: ImplicitConfig = field(default_factory=ImplicitConfig)
    sam: SamMaskConfig = field(default_factory=SamMaskConfig)

    def validate(self) -> None:
        if self.upsampler not in UPSAMPLERS:
            raise ValueError(f"tiger.FeatureConfig: upsampler must be one of {UPSAMPLERS}, got {self.upsampler!r}")
        if self.unmasked not in ("keep", "ignore"):
            raise ValueError(f"tiger.FeatureConfig: unmasked must be 'keep' or 'ignore', got {self.unmasked!r}")
        if self.clip_long_side < 16:
            raise ValueError(f"tiger.FeatureConfig: clip_long_side must be >= 16, got {self.clip_long_side}")

    def fingerprint(self, stage1: bool = False) -> str:
        """Hash of the settings; ``stage1=True`` leaves out what only the PCA uses (``pca_dim``), so
        changing it refits the PCA without recomputing the cached images."""
        d = dataclasses.asdict(self)
        if stage1:
            d.pop("pca_dim")
        blob = json.dumps(d, sort_keys=True, default=str)
        return hashlib.sha1(blob.encode()).hexdigest()[:16]

    def out_size(self, h: int, w: int) -> tuple[int, int]:
        if self.output_size is not None:
            return int(self.output_size[0]), int(self.output_size[1])
        if self.output_long_side is not None:
            s = self.output_long_side / max(h, w)
            return max(1, int(round(h * s))), max(1, int(round(w * s)))
        return h, w


@dataclass
class FeatureSet:
    """What :func:`extract_features` wrote: ``out_dir/features/<name>.pt`` per image and ``pca.pt``."""

    out_dir: Path
    names: list[str]
    pca: PCABasis

    def path(self, name: str) -> Path:
        return self.out_dir / "features" / f"{name}.pt"

    def load(self, name: str) -> tuple[torch.Tensor, torch.Tensor]:
        """(features [H, W, k] float16, valid [H, W] bool) of image ``name``."""
        d = torch.load(str(self.path(name)), map_location="cpu", weights_only=True)
        return d["features"], d["valid"]


def read_rgb_image(path: str | os.PathLike) -> torch.Tensor:
    """An image file as [3, H, W] float32 RGB in [0, 1]."""
    from PIL import Image

    with Image.open(path) as im:
        arr = torch.frombuffer(bytearray(im.convert("RGB").tobytes()), dtype=torch.uint8)
        w, h = im.size
    return arr.view(h, w, 3).permute(2, 0, 1).float() / 255.0


def _as_image(img: ImageLike) -> torch.Tensor:
    if isinstance(img, torch.Tensor):
        if img.dim() != 3 or img.shape[0] != 3:
            raise ValueError(f"tiger.extract_features: image tensors must be [3, H, W], got {tuple(img.shape)}")
        return img.float() / 255.0 if img.dtype == torch.uint8 else img.float()
    return read_rgb_image(img)


def _names(images: Sequence[ImageLike], names: Sequence[str] | None) -> list[str]:
    if names is not None:
        if len(names) != len(images):
            raise ValueError(f"tiger.extract_features: {len(names)} names for {len(images)} images")
        out = [str(n) for n in names]
    else:
        out = [Path(i).stem if not isinstance(i, torch.Tensor) else f"{k:05d}" for k, i in enumerate(images)]
    if len(set(out)) != len(out):
        raise ValueError("tiger.extract_features: image names must be unique (pass names=...)")
    return out


@torch.no_grad()
def compute_image_features(image: torch.Tensor, clip: MaskCLIP, sam: SamMaskGenerator | None,
                           jbu: JBUStack | None, cfg: FeatureConfig) -> dict[str, Any]:
    """Stage 1 for one image [3, H, W] in [0, 1] (on the models' device): the compact cached record
    (ids [h, w] int32, means [M, D] and unmasked [U, D] float16) and its PCA statistics."""
    h, w = image.shape[-2:]
    size = cfg.out_size(h, w)
    clip_in = resize_for_patches(image[None], cfg.clip_long_side, clip.patch_size)[0]
    with torch.enable_grad():
        hr = upsample_features(clip_in, clip, size, cfg.upsampler, jbu=jbu, implicit=cfg.implicit,
                               guidance_normalizer=lambda x: normalize_images(x, "imagenet"))
    d = hr.shape[0]
    feats = F.normalize(hr.detach().float(), dim=0).permute(1, 2, 0).reshape(-1, d)
    if sam is not None:
        ids = sam(image, size).id_map().reshape(-1)
    else:
        ids = torch.full((feats.shape[0],), -1, dtype=torch.int64, device=feats.device)
    n_masks = int(ids.max().item()) + 1 if ids.numel() else 0
    _, means, counts = masked_average(feats, ids, n_masks)
    means = F.normalize(means, dim=1).half()
    unmasked = feats[ids < 0].half() if cfg.unmasked == "keep" else feats.new_zeros(0, d).half()
    rows = torch.cat([means, unmasked]).double()
    weights = torch.cat([counts.double(), torch.ones(unmasked.shape[0], dtype=torch.float64, device=rows.device)])
    stats = StreamingPCA.statistics(rows[weights > 0], weights[weights > 0])
    return {
        "version": CACHE_VERSION, "size": size, "ids": ids.reshape(size).int().cpu(), "means": means.cpu(),
        "unmasked": unmasked.cpu(), "stats": stats,
    }


def project_record(rec: dict[str, Any], pca: PCABasis, unmasked: str) -> tuple[torch.Tensor, torch.Tensor]:
    """Stage 2: the [h, w, k] float16 map and [h, w] validity of a cached record."""
    h, w = rec["size"]
    ids = rec["ids"].reshape(-1).long()
    out = torch.zeros(h * w, pca.dim, dtype=torch.float32)
    valid = ids >= 0
    if rec["means"].shape[0]:
        out[valid] = pca.project(rec["means"].float())[ids[valid]]
    if unmasked == "keep":
        out[~valid] = pca.project(rec["unmasked"].float())
        valid = torch.ones_like(valid)
    return out.reshape(h, w, -1).half(), valid.reshape(h, w)


def _dist_setup(rank: int | None, world_size: int | None) -> tuple[int, int, bool]:
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size(), True
    env_world = int(os.environ.get("WORLD_SIZE", "1"))
    if rank is None and world_size is None and env_world > 1 and dist.is_available():
        backend = "nccl" if torch.cuda.is_available() else "gloo"
        if backend == "nccl":  # NCCL collectives run on the rank's own GPU
            torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", "0")) % torch.cuda.device_count())
        dist.init_process_group(backend)
        return dist.get_rank(), dist.get_world_size(), True
    return int(rank or 0), int(world_size or 1), False


def _barrier(use_dist: bool) -> None:
    if use_dist:
        import torch.distributed as dist

        dist.barrier()


def _default_device() -> torch.device:
    if torch.cuda.is_available():
        return torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")) % torch.cuda.device_count())
    return torch.device("cpu")


def _load_record(path: Path, fingerprint: str) -> dict[str, Any] | None:
    if not path.is_file():
        return None
    try:
        rec = torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - a torn/old file is recomputed, never trusted
        logger.warning("ignoring unreadable cache %s (%s)", path, exc)
        return None
    if rec.get("version") != CACHE_VERSION or rec.get("config") != fingerprint:
        return None
    return rec


def extract_features(
    images: Sequence[ImageLike],
    out_dir: str | os.PathLike,
    *,
    names: Sequence[str] | None = None,
    config: FeatureConfig | None = None,
    clip: MaskCLIP | None = None,
    sam: SamMaskGenerator | None = None,
    jbu: JBUStack | None = None,
    models: Any = None,
    device: str | torch.device | None = None,
    rank: int | None = None,
    world_size: int | None = None,
    progress: bool = True,
) -> FeatureSet:
    """Language feature maps for ``images`` (paths or [3, H, W] tensors in [0, 1]) under ``out_dir``.

    Models not passed are loaded through :mod:`tiger.models` (``models``: a config mapping or
    JSON file; else ``$TIGER_MODELS``). Models are loaded onto ``device`` (default: the passed
    ``clip``'s device, else this rank's GPU when there is one, else the CPU) and every image is
    processed there. Returns a :class:`FeatureSet`; ``out_dir/pca.pt`` holds the basis for
    projecting text (``FeatureSet.pca.project(clip.encode_text(...))``).
    """
    from tiger.utils.progress import progress as progress_lines

    cfg = config or FeatureConfig()
    cfg.validate()
    out = Path(out_dir)
    all_names = _names(images, names)
    rank, world, use_dist = _dist_setup(rank, world_size)
    # Passed-in models decide the device unless one is named: images follow the models.
    dev = (torch.device(device) if device is not None
           else clip.device if clip is not None else _default_device())
    fp = cfg.fingerprint(stage1=True)
    full_fp = cfg.fingerprint()
    mine = list(range(rank, len(images), world))
    cache_dir, feat_dir = out / "cache", out / "features"

    todo = [i for i in mine if _load_record(cache_dir / f"{all_names[i]}.pt", fp) is None]
    if todo:
        if clip is None:
            clip = MaskCLIP.from_pretrained(device=dev, config=models)
        if cfg.use_sam and sam is None:
            sam = SamMaskGenerator.from_pretrained(device=dev, config=models, mask_config=cfg.sam)
        if cfg.upsampler == "jbu" and jbu is None:
            jbu = JBUStack.from_checkpoint(config=models).to(dev)
    bar = progress_lines(len(mine), f"language features (rank {rank})", disable=not progress or rank != 0)
    bar.update(len(mine) - len(todo))
    for i in todo:
        img = _as_image(images[i]).to(dev)
        rec = compute_image_features(img, clip, sam if cfg.use_sam else None, jbu, cfg)
        rec["config"] = fp
        atomic_torch_save(rec, cache_dir / f"{all_names[i]}.pt")
        bar.update(1)
    bar.close()
    _barrier(use_dist)

    pca_path = out / "pca.pt"
    if rank == 0:
        pca_meta = out / "pca.json"
        stale = not pca_path.is_file() or not pca_meta.is_file() or \
            json.loads(pca_meta.read_text()).get("config") != full_fp or \
            json.loads(pca_meta.read_text()).get("names") != all_names
        if stale:
            acc = StreamingPCA(int(_load_record(cache_dir / f"{all_names[0]}.pt", fp)["means"].shape[1]), cfg.pca_dim)
            for name in all_names:
                rec = _load_record(cache_dir / f"{name}.pt", fp)
                if rec is None:
                    raise RuntimeError(f"tiger.extract_features: the cache of image '{name}' is missing after stage 1")
                acc.add_statistics(rec["stats"])
            basis = acc.fit()
            basis.save(pca_path)
            with open(pca_meta.with_suffix(".json.tmp"), "w") as fh:
                json.dump({"config": full_fp, "names": all_names, "pca": basis.fingerprint()}, fh)
            os.replace(pca_meta.with_suffix(".json.tmp"), pca_meta)
    _barrier(use_dist)
    pca = PCABasis.load(pca_path)
    pfp = pca.fingerprint()
    for i in mine:
        target = feat_dir / f"{all_names[i]}.pt"
        if target.is_file():
            try:
                if torch.load(str(target), map_location="cpu", weights_only=True).get("pca") == pfp:
                    continue
            except Exception:  # noqa: BLE001 - recompute a torn file
                pass
        rec = _load_record(cache_dir / f"{all_names[i]}.pt", fp)
        feats, valid = project_record(rec, pca, cfg.unmasked)
        atomic_torch_save({"features": feats, "valid": valid, "pca": pfp}, target)
    _barrier(use_dist)
    return FeatureSet(out, all_names, pca)

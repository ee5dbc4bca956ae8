"""``extract_features``: per-pixel 64-d language feature maps for an image set (SPEC §1, §4).

Per image (stage 1): MaskCLIP features -> FeatUp upsampling to the output resolution ->
L2 normalisation -> SAM finest-level masks -> masked average. The result is a compact record
(mask id map, per-mask means, and the features of pixels in no mask, float16) plus the image's PCA
statistics. Then (stage 2) one PCA 512 -> 64 is fitted over all images from the per-image
statistics, and every image's map is projected and written as float16 [H, W, 64] with a validity
mask.

Records stay in device memory between the two stages when they fit (``extract_io``): the 512-d
features are not read back from the disk, and only the 64-d maps are copied to the host. Each
image's statistics are written to ``cache/<name>.stats.pt``; its record to ``cache/<name>.pt`` in
the background (always when it did not fit in memory, else while the disk keeps up). Cache files
are renamed into place atomically but not fsync'ed (a lost one costs a recomputation); the maps
and ``pca.pt`` are. An interrupted run resumes: an image with a record, or with its map written
with the current PCA, is not computed again. Under ``torchrun`` (or with ``rank``/``world_size``)
each rank handles images ``rank, rank + world_size, ...`` on its own GPU; rank 0 fits the PCA
between two barriers, summing the per-image statistics in image order, so any number of ranks
writes the same bits.
"""
from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence, Union

import torch
import torch.nn.functional as F

from tiger.ops.masked_average import masked_average
from tiger.train.timing import StageTimer
from tiger.utils.io import atomic_torch_save
from tiger.utils.streams import run_beside

from .extract_io import BackgroundSaver, DiskBudget, KeptRecords, load_mapped, record_bytes
from .featup import UPSAMPLERS, ImplicitConfig, ImplicitNet, ImplicitUpsampler, JBUStack, upsample_features
from .maskclip import MaskCLIP, normalize_images, resize_for_patches
from .pca import PCABasis, StreamingPCA
from .sam_masks import SamMaskConfig, SamMaskGenerator

logger = logging.getLogger(__name__)

ImageLike = Union[str, os.PathLike, torch.Tensor]
# maps written at once by the projection pass (265 MB files at 1080p). Where the disk is the bound
# (the H100 machine with fsync'd writes: ~0.9 GB/s, 13.7-15.0 s for the fox's 50 maps with two or
# four) it changes nothing; where serialisation is (it releases the GIL), four overlap it
MAP_WRITERS = 4
CACHE_VERSION = 2  # 2: the unmasked rows are regenerated from the record's upsampler state


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
        self.sam.resolved("cpu")  # names a bad precision

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
    #: seconds per stage of this process's images in this run (empty when nothing was computed)
    timings: dict[str, float] = field(default_factory=dict)

    def path(self, name: str) -> Path:
        return self.out_dir / "features" / f"{name}.pt"

    def load(self, name: str) -> tuple[torch.Tensor, torch.Tensor]:
        """(features [H, W, k] float16, valid [H, W] bool) of image ``name``, memory-mapped: the
        bytes are read when first touched (``tiger embed`` copies 50 fox maps, 13.4 GB, to the GPU
        on threads that read them at once; one eager ``torch.load`` after another took 12.3 s)."""
        d = torch.load(str(self.path(name)), map_location="cpu", weights_only=True, mmap=True)
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


def _upsampled(image: torch.Tensor, clip: MaskCLIP, jbu: JBUStack | None, cfg: FeatureConfig,
               size: tuple[int, int]) -> tuple[torch.Tensor, dict[str, Any]]:
    """The upsampled features [D, *size] of ``image`` and what regenerates them exactly
    (:func:`regenerate_features`): the fitted implicit network's state, or the backbone's low-res
    map (JBU and bilinear re-run on the image). A few MB against the full map's GBs."""
    clip_in = resize_for_patches(image[None], cfg.clip_long_side, clip.patch_size)[0]
    if cfg.upsampler == "implicit":
        with torch.enable_grad():
            up = ImplicitUpsampler.fit(clip_in, clip, cfg.implicit)
        regen = {"kind": "implicit", "fit_image": up.image, "mean": up.mean, "basis": up.basis}
        regen.update({f"net.{k}": v.detach() for k, v in up.net.state_dict().items()})
        return up(size), regen
    lowres = clip(clip_in[None])[0].float()
    return _upsample_lowres(clip_in, clip, jbu, cfg, size, lowres), {"kind": cfg.upsampler, "lowres": lowres}


def _upsample_lowres(clip_in: torch.Tensor, clip: MaskCLIP, jbu: JBUStack | None, cfg: FeatureConfig,
                     size: tuple[int, int], lowres: torch.Tensor) -> torch.Tensor:
    return upsample_features(clip_in, clip, size, cfg.upsampler, jbu=jbu, lowres=lowres,
                             guidance_normalizer=lambda x: normalize_images(x, "imagenet"))


@torch.no_grad()
def regenerate_features(regen: dict[str, Any], image: torch.Tensor | None, clip: MaskCLIP | None,
                        jbu: JBUStack | None, cfg: FeatureConfig, size: tuple[int, int]) -> torch.Tensor:
    """The upsampled features [D, *size] that :func:`_upsampled` returned with ``regen``, computed
    again on ``regen``'s device: the implicit network evaluated from its saved state (no fit), or
    JBU / bilinear from the saved low-res map (``image`` [3, H, W] and ``clip`` needed)."""
    dev = regen["fit_image" if regen["kind"] == "implicit" else "lowres"].device
    if regen["kind"] == "implicit":
        icfg = cfg.implicit or ImplicitConfig()
        state = {k[4:]: v for k, v in regen.items() if k.startswith("net.")}
        net = ImplicitNet(regen["basis"].shape[1], icfg.n_freqs, None, icfg.dropout).to(dev)
        net.load_state_dict(state)
        net.eval()
        return ImplicitUpsampler(net, regen["fit_image"], regen["mean"], regen["basis"], [])(size)
    if image is None or clip is None:
        raise ValueError("tiger.regenerate_features: JBU / bilinear features need the image and the CLIP model")
    clip_in = resize_for_patches(image.to(dev)[None], cfg.clip_long_side, clip.patch_size)[0]
    return _upsample_lowres(clip_in, clip, jbu, cfg, size, regen["lowres"])


def _unit_rows(hr: torch.Tensor) -> torch.Tensor:
    """[D, h, w] features -> [h * w, D] unit rows (float32)."""
    return F.normalize(hr.detach().float(), dim=0).permute(1, 2, 0).reshape(-1, hr.shape[0])


@torch.no_grad()
def compute_image_features(image: torch.Tensor, clip: MaskCLIP, sam: SamMaskGenerator | None,
                           jbu: JBUStack | None, cfg: FeatureConfig, timer: StageTimer | None = None) -> dict[str, Any]:
    """Stage 1 for one image [3, H, W] in [0, 1] (on the models' device): the compact record (ids
    [h, w] int32 and means [M, D] float16 on the image's device; ``regen``, the upsampler state
    that gives back the features of the pixels in no mask, :func:`regenerate_features`) and its
    PCA statistics (float64, on the CPU), which count those pixels' features too. ``timer``
    adds the seconds of the upsampling, of the masks beyond it and of the averages."""
    h, w = image.shape[-2:]
    size = cfg.out_size(h, w)
    stage = timer if timer is not None else (lambda name: contextlib.nullcontext())
    # SAM does not depend on the features: on CUDA it runs on a side stream while the upsampler
    # (the implicit fit: ~400 small graphed steps) leaves most of the GPU idle
    masks = run_beside(lambda: sam(image, size).id_map().reshape(-1), image.device, (image,)) \
        if sam is not None else None
    with stage("upsample"):
        hr, regen = _upsampled(image, clip, jbu, cfg, size)
    d = hr.shape[0]
    feats = _unit_rows(hr)
    del hr
    with stage("masks beyond the upsampling"):
        ids = masks() if masks is not None else \
            torch.full((feats.shape[0],), -1, dtype=torch.int64, device=feats.device)
    with stage("mask averages, statistics"):
        n_masks = int(ids.max().item()) + 1 if ids.numel() else 0
        _, means, counts = masked_average(feats, ids, n_masks)
        means = F.normalize(means, dim=1).half()
        unmasked = feats[ids < 0].half() if cfg.unmasked == "keep" else feats.new_zeros(0, d).half()
        del feats
        stats = image_statistics(means, counts, unmasked)
    rec = {"version": CACHE_VERSION, "size": size, "ids": ids.reshape(size).int(), "means": means, "stats": stats}
    if cfg.unmasked == "keep" and unmasked.shape[0]:
        rec["regen"] = regen
    return rec


def unmasked_rows(rec: dict[str, Any], image: torch.Tensor | None, clip: MaskCLIP | None, jbu: JBUStack | None,
                  cfg: FeatureConfig) -> torch.Tensor:
    """[U, D] float16: the features of the record's pixels in no mask, regenerated from its
    ``regen`` (the bits stage 1 computed them with); empty when every pixel is in a mask."""
    if "regen" not in rec:
        d = rec["means"].shape[1] if rec["means"].numel() else 0
        return rec["means"].new_zeros(0, d)
    feats = _unit_rows(regenerate_features(rec["regen"], image, clip, jbu, cfg, tuple(rec["size"])))
    return feats[rec["ids"].reshape(-1).to(feats.device) < 0].half()


def image_statistics(means: torch.Tensor, counts: torch.Tensor, unmasked: torch.Tensor,
                     chunk_rows: int = 1 << 18) -> dict[str, torch.Tensor]:
    """PCA statistics (count, sum [D], outer [D, D]; float64 on the CPU) of one image's features:
    each mask mean [M, D] weighted by its pixel count [M], each unmasked row [U, D] once. Computed
    on the rows' device in a fixed order (float64 chunks of ``chunk_rows`` rows), so the same image
    gives the same bits whichever process computes it."""
    stats = StreamingPCA.statistics(means.double(), counts.double())
    for start in range(0, unmasked.shape[0], chunk_rows):
        part = StreamingPCA.statistics(unmasked[start : start + chunk_rows].double())
        stats = {k: stats[k] + part[k] for k in stats}
    return stats


def project_record(rec: dict[str, Any], pca: PCABasis, unmasked: str) -> tuple[torch.Tensor, torch.Tensor]:
    """Stage 2: the [h, w, k] float16 map and [h, w] validity of a stage-1 record, on the device of
    the record's tensors."""
    h, w = rec["size"]
    ids = rec["ids"].reshape(-1).long()
    out = torch.zeros(h * w, pca.dim, dtype=torch.float32, device=ids.device)
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
    """A stage-1 record (or statistics file) written with these settings, memory-mapped (its
    tensors are read when touched); None when missing, unreadable or made with other settings."""
    rec = load_mapped(path)
    if rec is None or rec.get("version") != CACHE_VERSION or rec.get("config") != fingerprint:
        return None
    return rec


def _stats_path(cache_dir: Path, name: str) -> Path:
    return cache_dir / f"{name}.stats.pt"


def _image_stats(cache_dir: Path, name: str, fingerprint: str, kept: KeptRecords) -> dict[str, torch.Tensor]:
    """One image's PCA statistics: from its record in memory, its statistics file or its record file."""
    rec = kept.records.get(name)
    if rec is None:
        rec = _load_record(_stats_path(cache_dir, name), fingerprint) or _load_record(cache_dir / f"{name}.pt", fingerprint)
    if rec is None:
        raise RuntimeError(f"tiger.extract_features: the statistics of image '{name}' are missing after stage 1")
    return {k: v.clone() for k, v in rec["stats"].items()}


def _current_pca(out: Path, full_fp: str, names: list[str]) -> str | None:
    """The fingerprint of ``out/pca.pt`` when it was fitted with these settings over these images."""
    try:
        meta = json.loads((out / "pca.json").read_text())
    except (OSError, ValueError):
        return None
    if meta.get("config") != full_fp or meta.get("names") != names or not (out / "pca.pt").is_file():
        return None
    return meta.get("pca")


def _finished(target: Path, pca_fingerprint: str) -> bool:
    out = load_mapped(target)
    return out is not None and out.get("pca") == pca_fingerprint


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
    memory_budget: int | None = None,
) -> FeatureSet:
    """Language feature maps for ``images`` (paths or [3, H, W] tensors in [0, 1]) under ``out_dir``.

    Models not passed are loaded through :mod:`tiger.models` (``models``: a config mapping or
    JSON file; else ``$TIGER_MODELS``). Models are loaded onto ``device`` (default: the passed
    ``clip``'s device, else this rank's GPU when there is one, else the CPU) and every image is
    processed there. Returns a :class:`FeatureSet`; ``out_dir/pca.pt`` holds the basis for
    projecting text (``FeatureSet.pca.project(clip.encode_text(...))``).

    ``memory_budget``: bytes of stage-1 records held in memory between the two passes (None: as
    many as fit, see :class:`~tiger.language.extract_io.KeptRecords`; 0: every record is written
    to ``out_dir/cache`` and read back). The outputs are the same bits either way.
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
    # SAM's precision made concrete for the device, so a bf16 and a float32 run never share a cache
    cfg = dataclasses.replace(cfg, sam=sam.config if sam is not None else cfg.sam.resolved(dev))
    fp = cfg.fingerprint(stage1=True)
    full_fp = cfg.fingerprint()
    mine = list(range(rank, len(images), world))
    cache_dir, feat_dir = out / "cache", out / "features"

    pfp = _current_pca(out, full_fp, all_names)
    todo = [i for i in mine if _load_record(cache_dir / f"{all_names[i]}.pt", fp) is None
            and not (pfp is not None and _finished(feat_dir / f"{all_names[i]}.pt", pfp)
                     and _load_record(_stats_path(cache_dir, all_names[i]), fp) is not None)]
    # the projection regenerates JBU / bilinear features of pixels in no mask with CLIP (and JBU)
    unfinished = [i for i in mine if not (pfp is not None and _finished(feat_dir / f"{all_names[i]}.pt", pfp))]
    if todo or (unfinished and cfg.upsampler != "implicit" and cfg.unmasked == "keep"):
        if clip is None:
            clip = MaskCLIP.from_pretrained(device=dev, config=models)
        if cfg.upsampler == "jbu" and jbu is None:
            jbu = JBUStack.from_checkpoint(config=models).to(dev)
    if todo and cfg.use_sam and sam is None:
        sam = SamMaskGenerator.from_pretrained(device=dev, config=models, mask_config=cfg.sam)
    kept = KeptRecords(dev, memory_budget)
    saver = BackgroundSaver(dev, workers=MAP_WRITERS)
    timer = StageTimer(dev)
    recompute: set[str] = set()
    disk = DiskBudget(cache_dir)

    def recomputed(name: str) -> dict[str, Any]:
        img = _as_image(images[all_names.index(name)]).to(dev)
        return compute_image_features(img, clip, sam if cfg.use_sam else None, jbu, cfg)

    def rows(name: str, rec: dict[str, Any]) -> torch.Tensor:
        needs_image = "regen" in rec and rec["regen"]["kind"] != "implicit"
        img = _as_image(images[all_names.index(name)]).to(dev) if needs_image else None
        return unmasked_rows(rec, img, clip, jbu, cfg)

    try:
        bar = progress_lines(len(mine), f"language features (rank {rank})", disable=not progress or rank != 0)
        bar.update(len(mine) - len(todo))
        for k, i in enumerate(todo):
            name = all_names[i]
            img = _as_image(images[i]).to(dev)
            kept.start_image()
            rec = compute_image_features(img, clip, sam if cfg.use_sam else None, jbu, cfg, timer)
            rec["config"] = fp
            # the statistics always reach the disk (rank 0 fits the PCA from every rank's images);
            # the record is written in the background: always when it is not kept in memory,
            # otherwise only while the disk keeps up (a record lost to a kill is recomputed)
            atomic_torch_save({"version": CACHE_VERSION, "config": fp, "stats": rec["stats"]},
                              _stats_path(cache_dir, name), fsync=False)
            in_memory = kept.offer(name, rec)
            # room for the record and for every map this rank still writes (the outputs come first)
            h, w = cfg.out_size(*img.shape[-2:])
            maps_left = (len(mine) - k) * h * w * (2 * cfg.pca_dim + 1)  # an upper bound
            if disk.room(record_bytes(rec), reserve=maps_left):
                disk.add(record_bytes(rec))
                saver.save(rec, cache_dir / f"{name}.pt", fsync=False, optional=in_memory)
            elif not in_memory:  # neither memory nor disk holds it: the projection pass recomputes it
                recompute.add(name)
            del rec, img
            bar.update(1)
        bar.close()
        _barrier(use_dist)
        _fit_pca(out, all_names, cache_dir, fp, full_fp, cfg.pca_dim, kept, rank)
        _barrier(use_dist)
        pca = PCABasis.load(out / "pca.pt")
        with timer("PCA projection, maps written"):
            _project_all(pca, [all_names[i] for i in mine], cache_dir, feat_dir, fp, cfg, kept, saver, dev,
                         {name: recomputed for name in recompute}, rows)
        if recompute:
            logger.info("%d images' stage-1 records fitted neither in memory nor on the disk; recomputed for "
                        "the projection", len(recompute))
        saver.close()
    except BaseException:
        saver.close(raise_errors=False)
        raise
    if saver.dropped:
        logger.info("%d stage-1 records were not written (the disk was behind; the maps are written)",
                    len(saver.dropped))
    _barrier(use_dist)
    timings = {k: v for k, v in timer.summary().items() if v > 0}
    if todo:
        logger.info("language features (rank %d): %s", rank, ", ".join(f"{k} {v:.1f} s" for k, v in timings.items()))
    return FeatureSet(out, all_names, pca, timings)


def _fit_pca(out: Path, all_names: list[str], cache_dir: Path, fp: str, full_fp: str, pca_dim: int,
             kept: KeptRecords, rank: int) -> Path:
    """Rank 0 fits the PCA into ``out/pca.pt`` (unless it was fitted with these settings and images)
    from the per-image statistics summed in image order: the same bits for any number of ranks."""
    pca_path = out / "pca.pt"
    if rank == 0:
        pca_meta = out / "pca.json"
        stale = not pca_path.is_file() or not pca_meta.is_file() or \
            json.loads(pca_meta.read_text()).get("config") != full_fp or \
            json.loads(pca_meta.read_text()).get("names") != all_names
        if stale:
            acc = None
            for name in all_names:
                stats = _image_stats(cache_dir, name, fp, kept)
                if acc is None:
                    acc = StreamingPCA(int(stats["sum"].shape[0]), pca_dim)
                acc.add_statistics(stats)
            basis = acc.fit()
            basis.save(pca_path)
            with open(pca_meta.with_suffix(".json.tmp"), "w") as fh:
                json.dump({"config": full_fp, "names": all_names, "pca": basis.fingerprint()}, fh)
            os.replace(pca_meta.with_suffix(".json.tmp"), pca_meta)
    return pca_path


def _project_all(pca: PCABasis, names: list[str], cache_dir: Path, feat_dir: Path, fp: str, cfg: FeatureConfig,
                 kept: KeptRecords, saver: BackgroundSaver, dev: torch.device,
                 recompute: dict[str, Any], rows: Callable[[str, dict[str, Any]], torch.Tensor]) -> None:
    """Stage 2 for this rank's images: each record (from memory, else from its cache file, else
    recomputed by ``recompute[name](name)`` when neither could hold it) projected on ``dev``; only the
    [h, w, k] float16 map and its validity are copied to the host and written atomically, without
    fsync: the next stage (``tiger embed``) reads them back from the page cache, and a map that a
    crash leaves torn does not load, so a rerun recomputes it (:func:`_finished`). With fsync the
    writes waited for the disk (the fox's 50 maps: 15.0 s at ~0.9 GB/s on the H100 machine).
    ``rows(name, rec)`` gives the features of the record's pixels in no mask (:func:`unmasked_rows`)."""
    pfp = pca.fingerprint()
    saver.drop_optional()  # from here on a written map supersedes its stage-1 record
    saver.max_pending = max(saver.max_pending, MAP_WRITERS)
    for name in names:
        target = feat_dir / f"{name}.pt"
        rec = kept.pop(name)
        if _finished(target, pfp):
            continue
        if rec is None and name in recompute:
            rec = recompute[name](name)
        elif rec is None:
            rec = _load_record(cache_dir / f"{name}.pt", fp)
            if rec is None:
                raise RuntimeError(f"tiger.extract_features: the stage-1 record of image '{name}' is "
                                   "missing; run again to recompute it")
            rec = {k: v.to(dev) if torch.is_tensor(v) else v for k, v in rec.items()}
            if "regen" in rec:
                rec["regen"] = {k: v.to(dev) if torch.is_tensor(v) else v for k, v in rec["regen"].items()}
        if cfg.unmasked == "keep":
            rec = dict(rec, unmasked=rows(name, rec))
        feats, valid = project_record(rec, pca, cfg.unmasked)
        del rec
        saver.save({"features": feats, "valid": valid, "pca": pfp}, target, fsync=False)

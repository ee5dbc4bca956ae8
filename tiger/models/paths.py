"""Where model weights live, and the error when they are missing (SPEC §7).

A model is found, in this order, at: an explicit ``path`` argument; the entry for it in a config
(a mapping or a JSON file of ``{name: path}``, whose keys must be registry names: clip, sam,
featup_jbu, lama, ip2p, mvdream), or inside a config that is a folder (searched like
``$TIGER_MODELS``); ``$TIGER_MODELS/<folder>`` (the folder named in the registry below, or the
public id as a nested folder). Nothing is downloaded unless a Python caller passes
``allow_download=True`` (then ``huggingface_hub`` fetches the public id into ``$TIGER_MODELS`` or
its own cache); the command line never downloads.
"""
from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence, Union

logger = logging.getLogger(__name__)

ENV_VAR = "TIGER_MODELS"
PathLike = Union[str, os.PathLike]
ConfigLike = Union[None, PathLike, Mapping[str, PathLike]]


@dataclass(frozen=True)
class ModelSpec:
    """A model the package can load.

    ``required`` lists groups of file names: a folder is complete when, for every group, one of
    its names exists in it. ``files`` names single-file checkpoints accepted instead of a folder.
    """

    name: str
    public_id: str
    folder: str
    required: tuple[tuple[str, ...], ...]
    files: tuple[str, ...] = ()
    source: str = ""

    def describe(self) -> str:
        groups = [" or ".join(g) for g in self.required]
        text = "a folder with " + ", ".join(groups) if groups else ""
        if self.files:
            text += (" / " if text else "") + "a checkpoint file " + " or ".join(self.files)
        return text


_WEIGHTS = ("model.safetensors", "pytorch_model.bin", "model.safetensors.index.json", "pytorch_model.bin.index.json")

REGISTRY: dict[str, ModelSpec] = {
    "clip": ModelSpec(
        name="clip",
        public_id="openai/clip-vit-base-patch16",
        folder="clip-vit-base-patch16",
        required=(("config.json",), _WEIGHTS, ("vocab.json", "tokenizer.json"), ("merges.txt", "tokenizer.json")),
        source="Hugging Face (CLIPModel.save_pretrained layout)",
    ),
    "sam": ModelSpec(
        name="sam",
        public_id="facebook/sam-vit-huge",
        folder="sam-vit-huge",
        required=(("config.json",), _WEIGHTS),
        files=("sam_vit_h_4b8939.pth",),
        source="Hugging Face (SamModel.save_pretrained layout) or the original segment-anything checkpoint",
    ),
    "featup_jbu": ModelSpec(
        name="featup_jbu",
        public_id="mhamilton723/FeatUp (torch.hub 'maskclip' JBU upsampler)",
        folder="featup",
        required=(),
        files=("maskclip_jbu_stack_cocostuff.ckpt",),
        source="FeatUp's released MaskCLIP JBU checkpoint",
    ),
    "lama": ModelSpec(
        name="lama",
        public_id="advimman/lama big-lama (TorchScript export of lama-cleaner)",
        folder="lama",
        required=(),
        files=("big-lama.pt",),
        source="LaMa's big-lama as a TorchScript file: net(image [B,3,H,W] in [0,1], mask [B,1,H,W]) -> [B,3,H,W]",
    ),
}


def _diffusers_folder(text: str) -> tuple[tuple[str, ...], ...]:
    """The files of a diffusers pipeline folder with a UNet, a VAE and a CLIP text encoder."""
    def weights_of(sub: str, stem: str) -> tuple[str, ...]:
        return (f"{sub}/{stem}.safetensors", f"{sub}/{stem}.bin")

    return (
        ("unet/config.json",), weights_of("unet", "diffusion_pytorch_model"),
        ("vae/config.json",), weights_of("vae", "diffusion_pytorch_model"),
        (f"{text}/config.json",), (f"{text}/model.safetensors", f"{text}/pytorch_model.bin"),
        ("tokenizer/vocab.json", "tokenizer/tokenizer.json"),
        ("scheduler/scheduler_config.json",),
    )


REGISTRY["ip2p"] = ModelSpec(
    name="ip2p",
    public_id="timbrooks/instruct-pix2pix",
    folder="instruct-pix2pix",
    required=_diffusers_folder("text_encoder"),
    source="Hugging Face diffusers folder (unet/ with in_channels 8, vae/, text_encoder/, tokenizer/, scheduler/)",
)
REGISTRY["mvdream"] = ModelSpec(
    name="mvdream",
    public_id="MVDream/MVDream",
    folder="mvdream",
    required=_diffusers_folder("text_encoder"),
    files=("sd-v2.1-base-4view.pt",),
    source="MVDream's original LDM checkpoint, or a diffusers folder of it (unet/ with the camera "
           "embedding as a projection class embedding)",
)


class ModelNotFoundError(FileNotFoundError):
    """A model's files are not where they were looked for."""


def _is_complete(folder: Path, spec: ModelSpec) -> bool:
    if not spec.required or not folder.is_dir():
        return False
    return all(any((folder / name).exists() for name in group) for group in spec.required)


def _config_root(config: ConfigLike) -> Path | None:
    """The folder a config names (searched like ``$TIGER_MODELS``): any path that is neither a
    file nor a ``.json`` name, so a missing folder is reported by the files looked for in it."""
    if config is None or isinstance(config, Mapping):
        return None
    path = Path(config).expanduser()
    return None if path.is_file() or path.suffix == ".json" else path


def _from_config(name: str, config: ConfigLike) -> Path | None:
    if config is None or _config_root(config) is not None:
        return None
    if not isinstance(config, Mapping):
        cfg_path = Path(config)
        try:
            config = json.loads(cfg_path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise ValueError(f"tiger.models: cannot read the model config {cfg_path}: {exc}") from exc
        if not isinstance(config, Mapping):
            raise ValueError(f"tiger.models: the model config {cfg_path} must be a JSON object of name -> path")
    unknown = sorted(k for k in config if k not in REGISTRY)
    if unknown:
        raise ValueError(f"tiger.models: the model config has unknown key(s) {', '.join(map(repr, unknown))}; "
                         f"the keys are {', '.join(REGISTRY)}")
    value = config.get(name)
    return Path(value).expanduser() if value else None


def _candidates(spec: ModelSpec, root: Path) -> list[Path]:
    out = [root / spec.folder, root / spec.public_id.split(" ")[0]]
    out += [root / f for f in spec.files] + [root / spec.folder / f for f in spec.files]
    return out


def _accept(candidate: Path, spec: ModelSpec) -> Path | None:
    if candidate.is_file() and (not spec.files or candidate.suffix in {Path(f).suffix for f in spec.files}):
        return candidate
    if _is_complete(candidate, spec):
        return candidate
    if candidate.is_dir():
        for f in spec.files:
            if (candidate / f).is_file():
                return candidate / f
    return None


def resolve_model_path(
    name: str,
    path: PathLike | None = None,
    *,
    config: ConfigLike = None,
    allow_download: bool = False,
) -> Path:
    """Find the weights of registry model ``name`` ('clip', 'sam', 'featup_jbu', 'ip2p', 'mvdream', 'lama').

    Returns a folder (Hugging Face layout) or a checkpoint file. Raises
    :class:`ModelNotFoundError` naming the expected files, the public id and every place looked at.
    """
    if name not in REGISTRY:
        raise KeyError(f"tiger.models: unknown model {name!r}; known: {sorted(REGISTRY)}")
    spec = REGISTRY[name]
    looked: list[Path] = []
    explicit = Path(path).expanduser() if path is not None else _from_config(name, config)
    if explicit is not None:
        looked.append(explicit)
        found = _accept(explicit, spec)
        if found is not None:
            return found
    else:
        root = _config_root(config) or os.environ.get(ENV_VAR)
        if root:
            for cand in _candidates(spec, Path(root).expanduser()):
                looked.append(cand)
                found = _accept(cand, spec)
                if found is not None:
                    return found
        if allow_download and spec.required:
            return _download(spec, Path(root).expanduser() if root else None)
    where = ", ".join(str(p) for p in looked) if looked else f"nowhere (no path given and ${ENV_VAR} is unset)"
    raise ModelNotFoundError(
        f"tiger: model '{name}' not found. Expected {spec.describe()} "
        f"({spec.source}; public id '{spec.public_id}'). Looked at: {where}. "
        f"Pass its path, add it to a model config (--models), or put it under ${ENV_VAR}/{spec.folder}."
    )


def require_models(names: Sequence[str], *, config: ConfigLike = None, hint: str = "") -> dict[str, Path]:
    """Resolve every model in ``names``; a :class:`ModelNotFoundError` names ALL the missing ones
    (each with what was expected and where it was looked for), then ``hint``."""
    found, missing = {}, []
    for name in names:
        try:
            found[name] = resolve_model_path(name, config=config)
        except ModelNotFoundError as exc:
            missing.append(str(exc).removeprefix("tiger: "))
    if missing:
        head = f"tiger: {len(missing)} of {len(names)} models not found: " if len(names) > 1 else "tiger: "
        raise ModelNotFoundError(head + " | ".join(missing) + (f" {hint}" if hint else ""))
    return found


def _download(spec: ModelSpec, root: Path | None) -> Path:
    from tiger.utils.lazy import require

    hub = require("huggingface_hub", purpose=f"downloading {spec.public_id}")
    local_dir = str(root / spec.folder) if root else None
    logger.info("downloading %s (allow_download=True)", spec.public_id)
    return Path(hub.snapshot_download(spec.public_id, local_dir=local_dir))

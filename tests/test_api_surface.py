"""The public surface of every tiger package, pinned (after kornia's ``test_api_surface``).

A change to a package's ``__all__`` must change SURFACE here too, on purpose. Beyond the pins:
one name per thing (no class or function exported under a second name), one home per thing
(a package exports only what its own modules define, a module only what it defines, and no
two packages export the same object; the top-level ``tiger`` re-exports only ``ALLOWED_TOP``),
and nothing exported is a module.
"""
from __future__ import annotations

import importlib
import inspect
import pkgutil
import types

import pytest

import tiger

SURFACE = {
    "tiger": ["__version__", "rasterize_gaussians"],
    "tiger.cli": [],
    "tiger.delete": ["DeleteConfig", "DeleteResult", "Inpainter", "LamaInpainter", "OpenCVInpainter", "delete",
                     "make_inpainter", "views_around"],
    "tiger.demo": ["DEMO_ORBIT", "tabletop_scene"],
    "tiger.edit": ["CSDGuidance", "CSDSchedule", "DEFAULT_EDIT_LRS", "EditConfig", "EditResult", "EditSession",
                   "EditTarget", "EmptyTargetError", "ObjectViews", "capture_layout", "edit", "resolve_target"],
    "tiger.edit.guidance": ["Guidance", "GuidanceInfo", "IP2PModels", 
                            "InstructPix2PixGuidance", "MVDreamGuidance", "MVDreamModels", "RecolorGuidance",
                            "ViewBatch", "load_ip2p", "load_mvdream", "parse_color"],
    "tiger.eval": [],
    "tiger.language": ["FeatureConfig", "FeatureSet", "FieldConfig", "FieldResult", "ImplicitConfig",
                       "ImplicitUpsampler", "JBUStack", "MaskCLIP", "PCABasis", "SamMaskConfig", "SamMaskGenerator",
                       "SamMasks", "StreamingPCA", "extract_features", "read_rgb_image", "train_field",
                       "upsample_features"],
    "tiger.models": ["ENV_VAR", "ModelNotFoundError", "ModelSpec", "REGISTRY", "load_clip", "load_jbu_checkpoint",
                     "load_sam", "resolve_model_path"],
    "tiger.ops": ["cuda_enabled"],
    "tiger.recon": ["ReconConfig", "SceneOptimizer", "StepOutput", "Trainer", "expon_lr", "load_views",
                    "photometric_loss", "psnr", "ssim", "ssim_map"],
    "tiger.recon.strategy": ["DensifySchedule", "DensifyStats", "InriaStrategy", "RegionTopKStrategy",
                             "clone_and_split", "duplicate", "inria_densify", "prune_transparent",
                             "region_topk_densify", "remove", "reset_opacity", "split"],
    "tiger.render": ["Camera", "Distortion", "RasterSettings", "camera_center", "rasterize_gaussians",
                     "sh_colors"],
    "tiger.retrieval": ["CANONICAL_NEGATIVES", "DEFAULT_TEMPERATURE", "EmbeddingTable", "Retrieval", "SelectionCheck",
                        "TextEncoder", "UnknownTextError", "check_selection", "choose_tau", "embed_negatives", "embed_queries", "min_error_threshold",
                        "otsu_threshold", "pca_of", "project", "relevancy", "relevancy_maps", "render_language",
                        "retrieve", "robust_bounds", "save_heatmap", "save_relevancy_picture", "subset",
                        "valley_threshold", "write_relevancy_pictures"],
    "tiger.scene": ["ColorSpec", "DEFAULT_LRS", "GaussianScene", "LabelledScene", "MissingImagesError",
                    "PARAM_NAMES", "SceneFormatError", "read_ply", "render_rgb", "render_view_chunks", "render_views",
                    "scene_extent",
                    "write_ply"],
    "tiger.testing": [],
    "tiger.train": ["CheckpointError", "CheckpointMismatch", "LoopOutcome", "StageTimer", "ViewSampler", "progress_bar",
                    "read_checkpoint", "restore_rng", "rng_state", "run_loop", "signature_differences",
                    "write_checkpoint"],
    "tiger.utils": [],
    "tiger.viewer": ["Selection", "ViewerError", "ViewerState", "serve"],
}
#: What the top-level package re-exports from its subpackages (the one-line entry point).
ALLOWED_TOP = {"rasterize_gaussians"}
#: Names that were aliases or second homes once: they must not come back anywhere.
RETIRED = {"RasterDefaults", "render_color", "render_rgb_and_footprint", "clear_condition_cache"}
#: Public names every CLI module defines by contract (one per command module).
COMMAND_PROTOCOL = {"add_parser", "run", "main", "build_parser"}
#: Second definitions still to be replaced by the one helper: {name: modules defining it}.
PENDING: dict[str, set[str]] = {}


def _packages() -> list[str]:
    return ["tiger"] + sorted(m.name for m in pkgutil.walk_packages(tiger.__path__, "tiger.") if m.ispkg)


def _modules() -> list[types.ModuleType]:
    names = ["tiger"] + sorted(m.name for m in pkgutil.walk_packages(tiger.__path__, "tiger.")
                               if m.name != "tiger._C")
    return [importlib.import_module(n) for n in names]


def _is_code(obj: object) -> bool:
    return inspect.isclass(obj) or inspect.isfunction(obj)


def test_every_package_is_pinned():
    assert sorted(_packages()) == sorted(SURFACE), "a package was added or removed: pin its __all__ in SURFACE"


@pytest.mark.parametrize("package", sorted(SURFACE))
def test_public_names_are_pinned_and_resolve(package):
    mod = importlib.import_module(package)
    assert hasattr(mod, "__all__"), f"{package} has no __all__"
    assert sorted(mod.__all__) == sorted(SURFACE[package]), f"{package}.__all__ changed"
    assert len(set(mod.__all__)) == len(mod.__all__), f"{package}.__all__ lists a name twice"
    for name in mod.__all__:
        assert hasattr(mod, name), f"{package}.__all__ names {name}, which it does not define"
        assert not isinstance(getattr(mod, name), types.ModuleType), f"{package}.{name} is a module"


def test_one_name_and_one_home_per_thing():
    exported: dict[int, list[str]] = {}
    for mod in _modules():
        is_package = hasattr(mod, "__path__")
        for name in getattr(mod, "__all__", []):
            obj = getattr(mod, name)
            if not _is_code(obj):
                continue
            assert obj.__name__ == name, f"{mod.__name__}.{name} is an alias of {obj.__module__}.{obj.__name__}"
            home = obj.__module__
            if is_package:
                assert home == mod.__name__ or home.startswith(mod.__name__ + "."), (
                    f"package {mod.__name__} exports {name} from {home}, another package's")
                if mod.__name__ != "tiger":
                    exported.setdefault(id(obj), []).append(f"{mod.__name__}.{name}")
                else:
                    assert name in ALLOWED_TOP or name == "__version__", f"tiger re-exports {name}"
            else:
                assert home == mod.__name__, f"module {mod.__name__} re-exports {name} from {home}"
    twice = [homes for homes in exported.values() if len(homes) > 1]
    assert not twice, f"exported by two packages: {twice}"


def test_no_two_public_definitions_share_a_name():
    """A public class or function name is defined in one module only (else one of them is a second
    implementation of one thing, or two things share a name: rename one)."""
    where: dict[str, set[str]] = {}
    for mod in _modules():
        for name, obj in vars(mod).items():
            if not name.startswith("_") and _is_code(obj) and obj.__module__ == mod.__name__:
                where.setdefault(name, set()).add(mod.__name__)
    twice = {n: sorted(m) for n, m in where.items()
             if len(m) > 1 and n not in COMMAND_PROTOCOL and PENDING.get(n) != m}
    assert not twice, f"defined in several modules: {twice}"


def test_retired_names_do_not_come_back():
    for mod in _modules():
        back = RETIRED & set(vars(mod))
        assert not back, f"{mod.__name__} defines {sorted(back)} again"


def test_camera_has_one_home():
    from tiger.render import Camera, Distortion

    assert Camera.__module__ == Distortion.__module__ == "tiger.render.camera"
    holders = [m.__name__ for m in _modules() if "Camera" in getattr(m, "__all__", [])]
    assert holders == ["tiger.render", "tiger.render.camera"]  # the package and its defining module

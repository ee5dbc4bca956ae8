"""Three CSD steps with tiny random InstructPix2Pix + MVDream on CPU: finite gradients, a valid PLY."""
import pytest
import torch

from tiger.edit import CSDGuidance, EditConfig, EditSession, resolve_target
from tiger.edit.build import build_guidance, default_model_dtype
from tiger.scene import GaussianScene

from .scenes import query_a, two_objects


class _Recording:
    """Passes the CSD guidance through and keeps what it returned."""

    def __init__(self, inner):
        self.inner, self.name, self.instruction, self.seen = inner, inner.name, inner.instruction, []
        self.settings, self.generators, self.reset_caches = inner.settings, inner.generators, inner.reset_caches

    def grad(self, renders, views):
        g, info = self.inner.grad(renders, views)
        self.seen.append((g.detach().clone(), info))
        return g, info


@pytest.mark.timeout(300)
def test_three_csd_steps_tiny_models(tiny_models, tmp_path):
    scene = two_objects(n=150)
    csd = build_guidance("ip2p+mvdream", "make it look like a watermelon", models=str(tiny_models), seed=0,
                         ip2p_kwargs={"short_side": 32}, mvdream_kwargs={"image_size": 32})
    assert isinstance(csd, CSDGuidance)
    # on the CPU the defaults are float32 models, no CUDA graphs (bf16 + graphs on a GPU)
    assert csd.ip2p.dtype == torch.float32 and not csd.ip2p.cuda_graph and not csd.mvdream.cuda_graph
    settings = csd.settings()  # what edit.json and the checkpoint signature record
    assert settings["ip2p"]["dtype"] == settings["mvdream"]["dtype"] == "float32"
    assert settings["ip2p"]["cuda_graph"] is False and settings["mvdream"]["cuda_graph"] is False
    assert settings["schedule"] == {"ratio": [2.0, 1.0], "mv_end": 0.75}
    assert csd.instruction == "make it look like a watermelon" and len(csd.generators()) == 2
    assert csd.ip2p.t_range == (0.02, 0.2) and csd.mvdream.t_range == (0.02, 0.2)  # paper: t in [0.02, 0.2]
    rec = _Recording(csd)
    t = resolve_target(scene, query_a(), tau=0.5)
    s = EditSession(scene, t, rec, None,
                    EditConfig(steps=3, width=32, height=32, densify_every=0, progress=False))
    before = s.scene.detach().clone()
    for _ in range(3):
        s.step_once()
    assert len(rec.seen) == 3
    for g, info in rec.seen:
        assert g.shape == (4, 3, 32, 32) and bool(torch.isfinite(g).all()) and float(g.abs().sum()) > 0
        assert info.extra["lambda_ip2p"] > 0 and info.extra["lambda_mvdream"] > 0
    out, w = s.result_scene()
    assert not torch.equal(out.sh_dc[w > 0], before.sh_dc[w > 0])  # the editable Gaussians moved
    assert torch.equal(out.means[w == 0], before.means[w == 0])
    out.save_ply(tmp_path / "edited.ply")
    back = GaussianScene.load_ply(tmp_path / "edited.ply")
    assert len(back) == len(out) and back.lang is not None
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh_dc"):
        assert bool(torch.isfinite(getattr(back, name)).all()), name


def test_model_defaults_follow_the_device(tiny_models):
    assert default_model_dtype("cpu") == torch.float32
    if torch.cuda.is_available():
        want = torch.bfloat16 if torch.cuda.is_bf16_supported() else torch.float16
        assert default_model_dtype("cuda") == want
        ip = build_guidance("ip2p", "make it red", models=str(tiny_models), device="cuda",
                            ip2p_kwargs={"short_side": 32}).ip2p
        assert ip.dtype == want and ip.cuda_graph  # the configuration the GPU benchmarks measure
    with pytest.raises(ValueError, match="cuda_graph=True needs the models on a CUDA device"):
        build_guidance("ip2p", "make it red", models=str(tiny_models), cuda_graph=True,
                       ip2p_kwargs={"short_side": 32})

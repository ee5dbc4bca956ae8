"""The CSD λ schedule, the CSD combination, the analytic guidance's t range, recolor targets."""
import pytest
import torch

from tiger.edit import CSDGuidance, CSDSchedule
from tiger.edit.guidance import GuidanceInfo, RecolorGuidance, ViewBatch, parse_color
from tiger.testing.ideal_denoiser import IdealDenoiserGuidance


@pytest.mark.parametrize("step,lam1,lam2", [
    (0, 2 / 3, 1 / 3),            # 2:1 at the start (paper appendix)
    (300, 2 / 3 + 1 / 9, 1 / 9 * 2),   # p = 0.25: lam2 = 1/3 * (1 - 0.25/0.75) = 2/9
    (450, 5 / 6, 1 / 6),          # p = 0.375: half-way to 0
    (900, 1.0, 0.0),              # 75 %: MVDream's weight reaches 0
    (1199, 1.0, 0.0),
])
def test_schedule_values(step, lam1, lam2):
    l1, l2 = CSDSchedule().weights(step, 1200)
    assert l1 == pytest.approx(lam1, abs=1e-12) and l2 == pytest.approx(lam2, abs=1e-12)
    assert l1 + l2 == pytest.approx(1.0)


def test_schedule_lambda1_grows_monotonically():
    w = [CSDSchedule().weights(s, 100) for s in range(100)]
    assert all(a[0] <= b[0] and a[1] >= b[1] for a, b in zip(w, w[1:]))


class _Const:
    def __init__(self, value, name):
        self.value, self.name, self.calls, self.instruction = value, name, 0, "make it " + name

    def settings(self):
        return {"value": self.value}

    def generators(self):
        return []

    def reset_caches(self):
        pass

    def grad(self, renders, views):
        self.calls += 1
        return torch.full_like(renders, self.value), GuidanceInfo(loss=self.value)


def _batch(step, total, v=4, h=8, w=8):
    return ViewBatch(cameras=[None] * v, originals=torch.zeros(v, 3, h, w), step=step, total_steps=total)


def test_csd_combines_and_skips_mvdream_after_75_percent():
    ip, mv = _Const(1.0, "ip2p"), _Const(10.0, "mvdream")
    csd = CSDGuidance(ip, mv)
    g, info = csd.grad(torch.zeros(4, 3, 8, 8), _batch(0, 100))
    assert torch.allclose(g, torch.full_like(g, 2 / 3 * 1.0 + 1 / 3 * 10.0))
    assert info.extra["lambda_ip2p"] == pytest.approx(2 / 3)
    g, _ = csd.grad(torch.zeros(4, 3, 8, 8), _batch(80, 100))
    assert torch.allclose(g, torch.ones_like(g)) and mv.calls == 1 and ip.calls == 2


def test_analytic_guidance_t_range_and_direction():
    x = torch.rand(2, 3, 8, 8, generator=torch.Generator().manual_seed(0))
    target = torch.rand(2, 3, 8, 8, generator=torch.Generator().manual_seed(1))
    gd = IdealDenoiserGuidance(lambda v: target, t_range=(0.02, 0.2), seed=0)
    for _ in range(20):
        g, info = gd.grad(x, _batch(0, 1, v=2))
        assert bool(((info.t >= 0.02) & (info.t <= 0.2)).all())
        # the ideal denoiser's SDS gradient is a positive multiple of (x - x*) per view
        for k in range(2):
            ratio = g[k] / (x[k] - target[k])
            assert float(ratio.std() / ratio.mean()) < 1e-3 and float(ratio.mean()) > 0


def test_recolor_targets_keep_shading_and_background():
    orig = torch.zeros(1, 3, 4, 4)
    orig[0, 2, :, :2] = 0.8  # a blue object: bright half
    orig[0, 2, :, 2:] = 0.4  # and a shadowed half
    orig[0, :, 0, 3] = 0.5   # a background pixel
    m = torch.zeros(1, 1, 4, 4)
    m[0, 0, :, :] = 1.0
    m[0, 0, 0, 3] = 0.0
    gd = RecolorGuidance("make it red")
    tgt = gd.targets(ViewBatch(cameras=[None], originals=orig, masks=m))
    red = torch.tensor([0.86, 0.08, 0.08])
    lum_b, lum_s = 0.0722 * 0.8, 0.0722 * 0.4
    ref = (8 * lum_b + 7 * lum_s) / 15
    assert torch.allclose(tgt[0, :, 1, 0], (red * lum_b / ref).clamp(0, 1), atol=1e-6)
    assert torch.allclose(tgt[0, :, 1, 3], (red * lum_s / ref).clamp(0, 1), atol=1e-6)
    assert torch.equal(tgt[0, :, 0, 3], orig[0, :, 0, 3])
    g, info = gd.grad(orig, ViewBatch(cameras=[None], originals=orig, masks=m))
    assert torch.allclose(g, orig - tgt)


def test_parse_color():
    assert torch.allclose(parse_color("#ff8000"), torch.tensor([1.0, 128 / 255, 0.0], dtype=torch.float64))
    assert torch.allclose(parse_color("255,0,0"), torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))
    assert torch.allclose(parse_color((0.2, 0.4, 0.6)), torch.tensor([0.2, 0.4, 0.6], dtype=torch.float64))
    with pytest.raises(ValueError, match="no colour"):
        parse_color("make it look like a watermelon")

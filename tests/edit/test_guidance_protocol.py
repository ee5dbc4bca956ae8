"""The Guidance protocol: what the edit loop and ``tiger edit`` need is in it (no probing), a guidance
missing a member fails with one clear line, and the record of an edit is the settings that ran."""
import pytest
import torch

from tiger.edit import CSDGuidance, CSDSchedule, EditConfig, EditSession, edit, resolve_target
from tiger.edit.guidance import GuidanceInfo, RecolorGuidance
from tiger.testing.ideal_denoiser import IdealDenoiserGuidance, render_targets
from tiger.edit.guidance.base import PROTOCOL_MEMBERS, Guidance, check_guidance

from .scenes import query_a, two_objects

SMALL = dict(width=32, height=32, progress=False, densify_every=0)


class _Seeded:
    """A guidance of the full protocol: pulls renders toward grey, plus noise from its generator;
    counts cache resets."""

    def __init__(self, name, seed, scale=1.0):
        self.name, self.instruction, self.scale = name, f"make it grey ({name})", scale
        self.generator = torch.Generator().manual_seed(seed)
        self.resets = 0

    def grad(self, renders, views):
        noise = torch.randn(renders.shape, generator=self.generator, dtype=renders.dtype)
        return self.scale * (renders - 0.5) + 0.01 * noise, GuidanceInfo(loss=0.0)

    def settings(self):
        return {"scale": self.scale}

    def generators(self):
        return [self.generator]

    def reset_caches(self):
        self.resets += 1


def _without(member):
    g = _Seeded("ip2p", 0)
    cls = type("Partial", (), {k: getattr(_Seeded, k) for k in ("__init__", "grad", "settings", "generators",
                                                                "reset_caches") if k != member})
    obj = cls.__new__(cls)
    obj.__dict__.update(g.__dict__)
    if member in ("name", "instruction"):
        del obj.__dict__[member]
    return obj


def test_every_shipped_guidance_implements_the_protocol():
    shipped = [RecolorGuidance("make it red"), IdealDenoiserGuidance(lambda v: v.originals),
               CSDGuidance(_Seeded("ip2p", 0), _Seeded("mvdream", 1))]
    for g in shipped:
        assert check_guidance(g) is g and isinstance(g, Guidance)
        import json

        json.dumps(g.settings())  # the record is JSON
        assert all(isinstance(x, torch.Generator) for x in g.generators())


@pytest.mark.parametrize("member", [m for m, _ in PROTOCOL_MEMBERS])
def test_a_guidance_missing_a_member_fails_clearly(member):
    partial = _without(member)
    with pytest.raises(TypeError, match=rf"guidance Partial lacks {member}"):
        check_guidance(partial)
    scene = two_objects(n=60)
    with pytest.raises(TypeError, match=rf"lacks {member}.*Guidance protocol"):
        edit(scene, query_a(), partial, tau=0.5, steps=1, **SMALL)
    with pytest.raises(TypeError, match=rf"lacks {member}"):
        CSDGuidance(partial, None)


def test_record_is_what_ran_and_instruction_given_once(tmp_path):
    """A non-default CSD schedule: the λ the steps used follow it, and the round's record, the
    checkpoint signature and the guidance's settings all carry that schedule (EditConfig has none)."""
    schedule = CSDSchedule(ratio=(1.0, 3.0), mv_end=0.5)
    csd = CSDGuidance(_Seeded("ip2p", 0, 2.0), _Seeded("mvdream", 1), schedule)
    assert not hasattr(EditConfig(), "schedule") and "schedule" not in EditConfig().to_dict()
    steps = 20
    res = edit(two_objects(), query_a(), csd, tau=0.5, steps=steps, checkpoint=tmp_path / "ck.pt", **SMALL)
    rec = res.rounds[-1]
    assert rec["instruction"] == csd.instruction == "make it grey (ip2p)"  # from the guidance, once
    assert rec["guidance"] == "csd"
    assert rec["guidance_settings"] == {"schedule": {"ratio": [1.0, 3.0], "mv_end": 0.5},
                                        "ip2p": {"name": "ip2p", "instruction": "make it grey (ip2p)", "scale": 2.0},
                                        "mvdream": {"name": "mvdream", "instruction": "make it grey (mvdream)",
                                                    "scale": 1.0}}
    logged = {h["step"]: (h["lambda_ip2p"], h["lambda_mvdream"]) for h in res.history}
    for step, (l1, l2) in logged.items():  # the record's step s logs the λ of step s - 1 (0-based)
        assert (l1, l2) == pytest.approx(schedule.weights(step - 1, steps))
    assert logged[10] == pytest.approx((1.0 - 0.75 * 0.1, 0.75 * 0.1))  # differs from the 2:1 default
    ck = torch.load(tmp_path / "ck.pt", weights_only=True)
    assert ck["signature"]["guidance_settings"] == rec["guidance_settings"]


def test_resume_refuses_other_guidance_settings(tmp_path):
    scene = two_objects(n=60)
    ck = tmp_path / "ck.pt"
    edit(scene, query_a(), CSDGuidance(_Seeded("ip2p", 0), _Seeded("mvdream", 1)), tau=0.5, steps=2,
         checkpoint=ck, **SMALL)
    other = CSDGuidance(_Seeded("ip2p", 0), _Seeded("mvdream", 1), CSDSchedule(mv_end=0.5))
    with pytest.raises(ValueError, match="guidance_settings.schedule.mv_end: 0.75 in the checkpoint, 0.5 now"):
        edit(scene, query_a(), other, tau=0.5, steps=2, checkpoint=ck, resume=True, **SMALL)


def test_loop_resets_caches_and_checkpoints_every_generator(tmp_path):
    ip, mv = _Seeded("ip2p", 0), _Seeded("mvdream", 1)
    csd = CSDGuidance(ip, mv, CSDSchedule(mv_end=1.0))
    assert csd.generators() == [ip.generator, mv.generator]
    assert CSDGuidance(ip, _Shared(ip)).generators() == [ip.generator]  # a shared generator once
    scene = two_objects(n=60)
    s = EditSession(scene, resolve_target(scene, query_a(), tau=0.5), csd, None, EditConfig(steps=3, **SMALL))
    assert ip.resets == mv.resets == 1  # a new round forgets cached per-camera work
    s.step_once()
    s.save(tmp_path / "ck.pt")
    states = [g.get_state().clone() for g in csd.generators()]
    s.step_once()
    s.load(tmp_path / "ck.pt")
    assert all(torch.equal(g.get_state(), st) for g, st in zip(csd.generators(), states))


class _Shared(_Seeded):
    def __init__(self, other):
        super().__init__("mvdream", 0)
        self.generator = other.generator


def test_recolor_instruction_and_colour():
    g = RecolorGuidance("make the ball gold", color="#ff0000")
    assert g.instruction == "make the ball gold" and g.settings()["color"] == [1.0, 0.0, 0.0]
    assert RecolorGuidance("make it blue").settings() == {"color": [0.1, 0.25, 0.9], "strength": 1.0}
    with pytest.raises(ValueError, match="instruction must be a non-empty string"):
        RecolorGuidance("")
    truth = two_objects(n=30)
    assert IdealDenoiserGuidance(render_targets(truth), seed=1).settings() == {"t_range": [0.02, 0.2]}

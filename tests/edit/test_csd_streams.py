"""On a GPU: CSD's MVDream-beside-InstructPix2Pix streams change no value beyond the run-to-run
rounding of the same kernels, graphed and eager; graphs are captured per stream, so the two
guidances' intermediates never share memory while they run at the same time (a shared pool would
differ by O(1), not by rounding)."""
import pytest
import torch

from tiger.edit.csd import CSDGuidance, CSDSchedule
from tiger.edit.guidance import ViewBatch
from tiger.edit.guidance.cuda_graph import GraphedStep
from tiger.edit.guidance.ip2p import InstructPix2PixGuidance, load_ip2p
from tiger.edit.guidance.mvdream import MVDreamGuidance, load_mvdream

pytestmark = [pytest.mark.cuda, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")]


def _csd(ip_models, mv_models, graphed: bool, concurrent: bool) -> CSDGuidance:
    ip = InstructPix2PixGuidance(ip_models, "make it red", short_side=16, cuda_graph=graphed, keep_text_encoder=True,
                                 generator=torch.Generator("cuda").manual_seed(0))
    mv = MVDreamGuidance(mv_models, "a fox", image_size=16, cuda_graph=graphed, keep_text_encoder=True,
                         generator=torch.Generator("cuda").manual_seed(1))
    return CSDGuidance(ip, mv, CSDSchedule(mv_end=1.0), concurrent=concurrent)


@pytest.mark.parametrize("graphed", [False, True])
def test_concurrent_equals_sequential(tiny_models, ring_cameras, graphed):
    ip_models = load_ip2p(tiny_models / "instruct-pix2pix", device="cuda")
    mv_models = load_mvdream(tiny_models / "mvdream", device="cuda")
    originals = torch.rand(4, 3, 16, 16, device="cuda")
    side_by_side = _csd(ip_models, mv_models, graphed, concurrent=True)
    one_stream = _csd(ip_models, mv_models, graphed, concurrent=False)
    again = _csd(ip_models, mv_models, graphed, concurrent=False)  # the kernels' own run-to-run spread
    torch.manual_seed(0)
    for step in range(3):  # the inputs change: captured buffers refilled, caches reused
        renders = torch.rand(4, 3, 16, 16, device="cuda")
        views = ViewBatch(cameras=ring_cameras(size=(16, 16)), originals=originals, view_ids=torch.arange(4),
                          object_center=torch.zeros(3), step=step, total_steps=4)
        a, info_a = side_by_side.grad(renders, views)
        b, _ = one_stream.grad(renders, views)
        c, _ = again.grad(renders, views)
        assert info_a.extra["lambda_mvdream"] > 0  # both guidances ran
        assert torch.isfinite(a).all()
        scale = float(b.abs().max())
        # float32 tiny models: the cuDNN/cuBLAS algorithms of a side stream or a capture may round
        # differently (~1e-6 of the scale); a race or a shared pool would be O(scale).
        msg = (step, float((a - b).abs().max()), float((b - c).abs().max()), scale)
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-4 * scale), msg


def test_graphs_captured_per_stream():
    calls = []

    def fn(x):
        calls.append(1)
        return x * 2

    step = GraphedStep(fn, warmup=1)
    x = torch.ones(8, device="cuda")
    assert torch.equal(step(x), x * 2)
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        y = step(x)
    torch.cuda.current_stream().wait_stream(side)
    assert torch.equal(y, x * 2)
    assert len(step._graphs) == 2  # one graph (and pool) per stream
    assert torch.equal(step(x + 1), (x + 1) * 2)  # replayed with new inputs, no new capture
    assert len(step._graphs) == 2

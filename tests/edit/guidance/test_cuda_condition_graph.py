"""On a GPU: InstructPix2Pix's condition encode of pooled views (camera ids) replays as a CUDA graph
of its own when the guidance is graphed, equal to the eager encode, also when the graph is captured
and replayed in the view pool's worker thread (:func:`tiger.utils.streams.run_beside`) while the
calling thread keeps synchronising on its own stream (captures are "thread_local")."""
import pytest
import torch

from tiger.edit.guidance.ip2p import InstructPix2PixGuidance, load_ip2p
from tiger.utils.streams import run_beside

pytestmark = [pytest.mark.cuda, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")]


@pytest.fixture
def eager_and_graphed(tiny_models):
    """Two InstructPix2Pix guidances on the same tiny models: eager, and graphed."""
    ip = load_ip2p(tiny_models / "instruct-pix2pix", device="cuda")
    return (InstructPix2PixGuidance(ip, "make it red", short_side=16, keep_text_encoder=True),
            InstructPix2PixGuidance(ip, "make it red", short_side=16, cuda_graph=True))


def test_pooled_condition_graph_equals_eager_encode(eager_and_graphed):
    eager, graphed = eager_and_graphed
    torch.manual_seed(0)
    for k in range(3):  # captured once, then the captured input refilled with new originals
        originals = torch.rand(4, 3, 16, 16, device="cuda")
        ids = torch.arange(4 * k, 4 * k + 4)
        want = eager.condition_latents(originals, (16, 16), ids)
        got = graphed.condition_latents(originals, (16, 16), ids)
        assert torch.allclose(got, want, rtol=1e-4, atol=1e-5), (k, float((got - want).abs().max()))
    assert len(graphed._graphed_cond._graphs) == 1 and len(graphed._cond_cache) == 12


def test_condition_graph_captured_in_a_worker_while_the_caller_syncs(eager_and_graphed):
    eager, graphed = eager_and_graphed
    torch.manual_seed(1)
    originals = [torch.rand(4, 3, 16, 16, device="cuda") for _ in range(3)]
    for k, o in enumerate(originals):
        ids = torch.arange(4 * k, 4 * k + 4)
        pending = run_beside(lambda: graphed.condition_latents(o, (16, 16), ids), "cuda", inputs=(o,))
        x = torch.rand(256, 256, device="cuda")
        for _ in range(20):  # the caller's own work and read-backs while the worker captures or replays
            float((x @ x).sum())
        got = pending()
        want = eager.condition_latents(o, (16, 16), ids)
        assert torch.allclose(got, want, rtol=1e-4, atol=1e-5), (k, float((got - want).abs().max()))
    (key,) = graphed._graphed_cond._graphs  # one graph, for the worker's side stream
    assert key[1] != (torch.cuda.current_stream().device_index, torch.cuda.current_stream().stream_id)

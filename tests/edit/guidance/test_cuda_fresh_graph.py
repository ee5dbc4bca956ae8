"""On a GPU: InstructPix2Pix's step for fresh views (no camera ids: the image condition encoded
inside the CUDA graph) equals the eager step on the same noise and t, also after the inputs
change (the captured originals refilled), with the loaders' CUDA defaults (fused norms, folded
adds, channels-last)."""
import pytest
import torch

from tiger.edit.guidance.ip2p import InstructPix2PixGuidance, load_ip2p

pytestmark = [pytest.mark.cuda, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")]


def test_fresh_graph_equals_eager(tiny_models, ip2p_step_inputs):
    ip = load_ip2p(tiny_models / "instruct-pix2pix", device="cuda")
    eager = InstructPix2PixGuidance(ip, "make it red", short_side=16, keep_text_encoder=True)
    graphed = InstructPix2PixGuidance(ip, "make it red", short_side=16, cuda_graph=True)
    for seed in (0, 1):
        torch.manual_seed(seed)
        renders, views, draws = ip2p_step_inputs()
        a, _ = eager.grad(renders, views, **draws)
        b, _ = graphed.grad(renders, views, **draws)
        assert not graphed._cond_cache and len(graphed._graphed_fresh._graphs) == 1
        # other float32 algorithms under capture: ~1e-5 of the gradient's scale; stale buffers O(1)
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-4 * float(a.abs().max())), (seed, float((a - b).abs().max()))

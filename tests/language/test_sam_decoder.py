"""SamGridDecoder (the automatic generator's prompt decoder) against transformers' SamModel, and the
cropped mask upscaling against upsampling SAM's whole input frame."""
import pytest
import torch
import torch.nn.functional as F

from tiger.language.sam_decoder import SamGridDecoder, _conv_t2x2_as_linear
from tiger.language.sam_masks import SamMaskConfig, SamMaskGenerator
from tiger.testing.random_models import random_sam

CUDA = torch.cuda.is_available()


@pytest.fixture(scope="module")
def sam():
    return random_sam("tiny", seed=3)


def _reference(model, emb, points):
    """transformers' SamModel on single positive points: (logits [P, 3, h, w], iou [P, 3])."""
    labels = torch.ones(1, points.shape[0], 1, dtype=torch.int64, device=points.device)
    with torch.no_grad():
        out = model(image_embeddings=emb, input_points=points[None, :, None, :], input_labels=labels,
                    multimask_output=True)
    return out.pred_masks[0], out.iou_scores[0]


def _inputs(model, prompts: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    c = model.config.mask_decoder_config.hidden_size
    e = model.config.prompt_encoder_config.image_embedding_size
    emb = torch.randn(1, c, e, e, generator=g)
    points = torch.rand(prompts, 2, generator=g) * model.config.vision_config.image_size
    return emb, points


@pytest.mark.parametrize("level", [0, 1, 2])
def test_grid_decoder_equals_sam_model(sam, level):
    emb, points = _inputs(sam, 37)
    ref_logits, ref_iou = _reference(sam, emb, points)
    dec = SamGridDecoder(sam, level)
    logits, iou = dec(dec.prepare(emb), points)
    assert logits.shape == ref_logits[:, level].shape and logits.dtype == torch.float32
    scale = ref_logits.abs().max()
    torch.testing.assert_close(logits, ref_logits[:, level], rtol=0, atol=1e-5 * float(scale))
    torch.testing.assert_close(iou, ref_iou[:, level], rtol=1e-5, atol=1e-6)


def test_grid_decoder_batches_are_independent(sam):
    """A prompt's result does not depend on the other prompts of its batch."""
    emb, points = _inputs(sam, 20, seed=1)
    dec = SamGridDecoder(sam)
    tokens = dec.prepare(emb)
    whole, iou = dec(tokens, points)
    parts = [dec(tokens, points[i : i + 7]) for i in range(0, 20, 7)]
    torch.testing.assert_close(torch.cat([p[0] for p in parts]), whole, rtol=0, atol=1e-6 * float(whole.abs().max()))
    torch.testing.assert_close(torch.cat([p[1] for p in parts]), iou)


def test_transposed_conv_as_linear():
    g = torch.Generator().manual_seed(0)
    conv = torch.nn.ConvTranspose2d(6, 5, kernel_size=2, stride=2)
    x = torch.randn(2, 6, 3, 4, generator=g)
    ref = conv(x)  # [2, 5, 6, 8]
    w, b = _conv_t2x2_as_linear(conv)
    y = F.linear(x.permute(0, 2, 3, 1), w, b).view(2, 3, 4, 2, 2, 5)  # (y, x, i, j, c)
    y = y.permute(0, 5, 1, 3, 2, 4).reshape(2, 5, 6, 8)
    torch.testing.assert_close(y, ref.detach())


def test_grid_decoder_bf16_autocast_runs_close(sam):
    emb, points = _inputs(sam, 16, seed=2)
    ref, ref_iou = SamGridDecoder(sam)(SamGridDecoder(sam).prepare(emb), points)
    dec = SamGridDecoder(sam, autocast=True)
    logits, iou = dec(dec.prepare(emb), points)
    assert logits.dtype == torch.float32 and logits.shape == ref.shape
    torch.testing.assert_close(iou, ref_iou, rtol=0, atol=5e-3)


def test_grid_decoder_rejects_bad_input(sam):
    with pytest.raises(ValueError, match="level"):
        SamGridDecoder(sam, level=3)
    with pytest.raises(ValueError, match=r"embedding must be \[1, C, h, w\]"):
        SamGridDecoder(sam).prepare(torch.zeros(2, 32, 4, 4))


@pytest.mark.parametrize("resized,size", [((36, 64), (54, 96)), ((64, 43), (80, 53)), ((64, 64), (64, 64)),
                                          ((1, 64), (3, 100))])
def test_upscale_crops_before_upsampling_bit_identically(sam, resized, size):
    gen = SamMaskGenerator(sam)
    low = torch.randn(5, 16, 16, generator=torch.Generator().manual_seed(4))
    whole = F.interpolate(low[:, None], size=(64, 64), mode="bilinear", align_corners=False)
    ref = F.interpolate(whole[..., : resized[0], : resized[1]], size=size, mode="bilinear", align_corners=False)[:, 0]
    assert torch.equal(gen._upscale(low, resized, size), ref)


def test_generator_decode_batches(sam):
    """The generator's decode equals the transformers model whatever its prompt batch."""
    image = torch.rand(3, 40, 56, generator=torch.Generator().manual_seed(5))
    outs = []
    for batch in (5, 64):
        gen = SamMaskGenerator(sam, SamMaskConfig(points_per_side=4, points_per_batch=batch))
        emb, resized = gen.embed(image)
        outs.append(gen.decode(emb, resized))
    emb, resized = SamMaskGenerator(sam).embed(image)
    from tiger.language.sam_masks import point_grid

    points = (point_grid(4) * torch.tensor([resized[1], resized[0]], dtype=torch.float64)).float()
    ref_logits, ref_iou = _reference(sam, emb, points)
    for low, iou in outs:
        torch.testing.assert_close(low, ref_logits[:, 0], rtol=0, atol=1e-5 * float(ref_logits.abs().max()))
        torch.testing.assert_close(iou, ref_iou[:, 0], rtol=1e-5, atol=1e-6)


@pytest.mark.skipif(not CUDA, reason="needs CUDA")
@pytest.mark.parametrize("autocast", [False, True])
def test_grid_decoder_cuda_equals_cpu(sam, autocast):
    """float32 on CUDA equals the CPU's to rounding; under bf16 autocast the device's error against
    float32 is of the size of the CPU's own bf16-autocast error (random tiny SAM: logits ~1e-5, so
    only errors relative to bf16's own are meaningful)."""
    import copy

    emb, points = _inputs(sam, 40, seed=6)
    ref, ref_iou = SamGridDecoder(sam)(SamGridDecoder(sam).prepare(emb), points)
    model = copy.deepcopy(sam).cuda()
    dec = SamGridDecoder(model, autocast=autocast)
    logits, iou = dec(dec.prepare(emb.cuda()), points.cuda())
    scale = float(ref.abs().max())
    if not autocast:
        torch.testing.assert_close(iou.cpu(), ref_iou, rtol=0, atol=1e-3)
        assert float((logits.cpu() - ref).abs().max()) <= 1e-2 * scale  # TF32 at most
        return
    cpu16 = SamGridDecoder(sam, autocast=True)
    cpu_logits, cpu_iou = cpu16(cpu16.prepare(emb), points)
    cpu_err = float((cpu_logits - ref).abs().max())
    assert float((logits.cpu() - ref).abs().max()) <= 4 * cpu_err + 1e-3 * scale
    assert float((iou.cpu() - ref_iou).abs().max()) <= 4 * float((cpu_iou - ref_iou).abs().max()) + 1e-3

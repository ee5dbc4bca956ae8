"""MaskCLIP dense features equal an independent computation from the CLIP weights."""
import pytest
import torch
import torch.nn.functional as F

from tiger.language.maskclip import IMAGENET_MEAN, IMAGENET_STD, MaskCLIP, resize_for_patches
from tiger.language.templates import MASKCLIP_TEMPLATES


def layer_norm(x, ln):
    mu = x.mean(-1, keepdim=True)
    var = (x - mu).square().mean(-1, keepdim=True)
    return (x - mu) / torch.sqrt(var + ln.eps) * ln.weight + ln.bias


def featup_positions(emb, embeddings, height, width):
    """FeatUp's position interpolation (featup/featurizers/maskclip/interpolate.py): bicubic with
    scale_factor (g + 0.1) / side and recompute_scale_factor=False."""
    table = emb.position_embedding.weight
    side = int(round((table.shape[0] - 1) ** 0.5))
    gh, gw = height // emb.patch_size, width // emb.patch_size
    if (gh, gw) == (side, side):
        return table[None]
    grid = table[1:].reshape(1, side, side, -1).permute(0, 3, 1, 2)
    grid = F.interpolate(grid, scale_factor=((gh + 0.1) / side, (gw + 0.1) / side), mode="bicubic",
                         align_corners=False, recompute_scale_factor=False)
    return torch.cat([table[None, :1], grid.permute(0, 2, 3, 1).reshape(1, gh * gw, -1)], 1)


def reference(clip, images):
    """hidden states from transformers' own forward (with FeatUp's position interpolation), then
    the last block's value path, post-LN and projection written out from the weights."""
    mean = torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
    vm = clip.vision_model
    emb = vm.embeddings
    emb.interpolate_pos_encoding = lambda e, h, w: featup_positions(emb, e, h, w)
    try:
        out = vm(pixel_values=(images - mean) / std, interpolate_pos_encoding=True, output_hidden_states=True)
    finally:
        del emb.interpolate_pos_encoding
    h = out.hidden_states[-2]  # input of the last block
    last = vm.encoder.layers[-1]
    a = last.self_attn
    v = layer_norm(h, last.layer_norm1) @ a.v_proj.weight.T + a.v_proj.bias
    v = v @ a.out_proj.weight.T + a.out_proj.bias
    f = layer_norm(v, vm.post_layernorm) @ clip.visual_projection.weight.T
    b, _, hh, ww = images.shape
    return f[:, 1:].transpose(1, 2).reshape(b, -1, hh // 16, ww // 16)


@pytest.mark.parametrize("size", [(64, 64), (48, 80), (32, 16)])
def test_dense_features_match_reference(maskclip, size):
    images = torch.rand(2, 3, *size, generator=torch.Generator().manual_seed(1))
    got = maskclip(images)
    assert got.shape == (2, maskclip.out_dim, size[0] // 16, size[1] // 16)
    with torch.no_grad():
        ref = reference(maskclip.clip, images)
    torch.testing.assert_close(got, ref, atol=1e-5, rtol=1e-4)
    # batched == one at a time
    torch.testing.assert_close(maskclip(images[1:]), got[1:], atol=1e-5, rtol=1e-4)


def test_value_path_differs_from_full_last_block(maskclip):
    """Guards the test above: the full last block (attention + MLP) gives other features."""
    images = torch.rand(1, 3, 64, 64)
    vm = maskclip.clip.vision_model
    with torch.no_grad():
        full = vm(pixel_values=images, output_hidden_states=True).last_hidden_state
        full = maskclip.clip.visual_projection(vm.post_layernorm(full))[:, 1:]
    assert (full.transpose(1, 2).reshape(1, -1, 4, 4) - maskclip(images)).abs().max() > 1e-3


def test_bad_sizes(maskclip):
    with pytest.raises(ValueError, match="multiple of the patch size 16"):
        maskclip(torch.rand(1, 3, 50, 64))
    with pytest.raises(ValueError, match="\\[B, 3, H, W\\]"):
        maskclip(torch.rand(3, 64, 64))
    with pytest.raises(ValueError, match="normalization"):
        MaskCLIP(maskclip.clip, normalization="nope")


def test_resize_for_patches():
    out = resize_for_patches(torch.rand(1, 3, 1080, 1920), 448)
    assert out.shape == (1, 3, 256, 448)


def test_encode_text_averages_normalised_templates(maskclip):
    texts = ["red cup", "nori"]
    got = maskclip.encode_text(texts)
    assert got.shape == (2, maskclip.out_dim)
    torch.testing.assert_close(got.norm(dim=1), torch.ones(2))
    clip, tok = maskclip.clip, maskclip.tokenizer
    for q, text in enumerate(texts):
        embs = []
        for t in MASKCLIP_TEMPLATES:
            ids = tok([t.format(text)], return_tensors="pt")
            with torch.no_grad():
                e = clip.get_text_features(input_ids=ids["input_ids"], attention_mask=ids["attention_mask"])
            e = e if isinstance(e, torch.Tensor) else e.pooler_output
            embs.append(F.normalize(e[0], dim=0))
        ref = F.normalize(torch.stack(embs).mean(0), dim=0)
        torch.testing.assert_close(got[q], ref, atol=1e-5, rtol=1e-4)
    raw = maskclip.encode_text(texts, templates=None)
    assert (raw - got).abs().max() > 1e-4


def test_vision_in_bf16_is_a_cached_copy_of_the_vision_tower(maskclip):
    img = torch.rand(2, 3, 32, 48, generator=torch.Generator().manual_seed(3))
    ref = maskclip(img)
    twin = maskclip.vision_in(torch.bfloat16)
    assert twin.dtype == torch.bfloat16 and maskclip.dtype == torch.float32  # the original is untouched
    assert twin is maskclip.vision_in(torch.bfloat16)  # cast once
    assert maskclip.vision_in(torch.float32) is maskclip
    assert "_vision_copy" not in dict(maskclip.named_modules()) and not any(
        k.startswith("_vision") for k in maskclip.state_dict())
    out = twin(img)
    cos = torch.nn.functional.cosine_similarity(out, ref, dim=1)
    assert out.dtype == torch.float32 and out.shape == ref.shape and cos.min() > 0.98
    # a changed weight makes a new copy
    with torch.no_grad():
        maskclip.clip.visual_projection.weight.mul_(2.0)
    try:
        again = maskclip.vision_in(torch.bfloat16)
        assert again is not twin
        assert torch.allclose(again.clip.visual_projection.weight.float(),
                              maskclip.clip.visual_projection.weight.bfloat16().float())
    finally:
        with torch.no_grad():
            maskclip.clip.visual_projection.weight.div_(2.0)

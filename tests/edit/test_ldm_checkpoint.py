"""The LDM -> diffusers mapping (diffusers' single_file_utils behind tiger.edit.guidance.ldm_checkpoint)
is pinned: an MVDream checkpoint written by an independent inverse converts back bit-exactly, and
the full-size configuration has MVDream's published facts."""
import pytest
import torch

from tiger.edit.guidance.ldm_checkpoint import convert_ldm_checkpoint, unet_config_from_ldm, vae_config_from_ldm, openclip_text_config
from tiger.testing.random_models import mvdream_ldm_config, random_mvdream_state


def test_round_trip_is_bit_exact_camera_embedding_included():
    state, originals = random_mvdream_state("tiny", seed=3, vocab_size=600)
    assert "model.diffusion_model.camera_embed.0.weight" in state
    comp = convert_ldm_checkpoint(state, mvdream_ldm_config("tiny"))
    for name, converted in (("unet", comp.unet_state), ("vae", comp.vae_state), ("text", comp.text_state)):
        want = {k: v for k, v in originals[name].items() if not k.endswith("position_ids")}
        assert set(converted) == set(want), (name, sorted(set(converted) ^ set(want))[:5])
        for key, value in want.items():
            assert converted[key].shape == value.shape and torch.equal(converted[key], value), (name, key)
    assert torch.equal(comp.unet_state["class_embedding.linear_1.weight"], originals["unet"]["class_embedding.linear_1.weight"])
    assert comp.text_config["num_hidden_layers"] == 2  # 3 blocks stored, the penultimate output used


def test_full_mvdream_configuration_facts():
    cfg = unet_config_from_ldm(None)  # MVDream's sd-v2-base.yaml
    assert list(cfg["attention_head_dim"]) == [5, 10, 20, 20]
    assert cfg["use_linear_projection"] is True and cfg["cross_attention_dim"] == 1024
    assert cfg["sample_size"] == 32 and list(cfg["block_out_channels"]) == [320, 640, 1280, 1280]
    assert cfg["layers_per_block"] == 2 and cfg["in_channels"] == 4 and cfg["out_channels"] == 4
    assert cfg["class_embed_type"] == "projection" and cfg["projection_class_embeddings_input_dim"] == 16
    assert list(cfg["down_block_types"]) == ["CrossAttnDownBlock2D"] * 3 + ["DownBlock2D"]
    vae = vae_config_from_ldm(None)
    assert list(vae["block_out_channels"]) == [128, 256, 512, 512] and vae["scaling_factor"] == 0.18215
    shapes = {"cond_stage_model.model.token_embedding.weight": torch.empty(49408, 1024),
              "cond_stage_model.model.positional_embedding": torch.empty(77, 1024),
              **{f"cond_stage_model.model.transformer.resblocks.{i}.mlp.c_fc.weight": torch.empty(4096, 1024) for i in range(24)}}
    text = openclip_text_config(shapes)  # OpenCLIP ViT-H text tower at its penultimate layer
    assert (text["num_hidden_layers"], text["num_attention_heads"], text["hidden_size"]) == (23, 16, 1024)


def test_schedule_matches_ldm_linear_betas():
    state, _ = random_mvdream_state("tiny", vocab_size=600)
    comp = convert_ldm_checkpoint(state, mvdream_ldm_config("tiny"))
    betas = [(0.00085 ** 0.5 + (0.012 ** 0.5 - 0.00085 ** 0.5) * i / 999) ** 2 for i in range(1000)]
    acp, prod = [], 1.0
    for b in betas:
        prod *= 1.0 - b
        acp.append(prod)
    assert torch.allclose(comp.schedule.alphas_cumprod.double(), torch.tensor(acp, dtype=torch.float64), atol=1e-6)


def test_bad_checkpoints_are_named():
    state, _ = random_mvdream_state("tiny", vocab_size=600)
    with pytest.raises(ValueError, match="not an LDM checkpoint"):
        convert_ldm_checkpoint({"foo": torch.zeros(1)}, mvdream_ldm_config("tiny"))
    no_cam = {k: v for k, v in state.items() if "camera_embed" not in k}
    with pytest.raises(ValueError, match="camera_embed"):
        convert_ldm_checkpoint(no_cam, mvdream_ldm_config("tiny"))
    bad = dict(state, alphas_cumprod=state["alphas_cumprod"] * 0.5)
    with pytest.raises(ValueError, match="alphas_cumprod"):
        convert_ldm_checkpoint(bad, mvdream_ldm_config("tiny"))

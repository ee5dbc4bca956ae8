"""Model loaders: tiny random CLIP and SAM saved in the public formats load through the real code;
missing models give an error naming the expected files and the public id."""
import json
import re

import pytest
import torch

from tiger.models import ENV_VAR, ModelNotFoundError, load_clip, load_sam, resolve_model_path
from tiger.testing.random_models import random_sam, save_random_clip, save_random_sam

# transformers.SamModel key -> original segment-anything key, written independently of the loader.
_TO_ORIGINAL = [
    (r"^vision_encoder\.", "image_encoder."),
    (r"\.layers\.(\d+)\.layer_norm(\d)", r".blocks.\1.norm\2"),
    (r"image_encoder\.layers\.", "image_encoder.blocks."),
    (r"patch_embed\.projection", "patch_embed.proj"),
    (r"neck\.conv1", "neck.0"), (r"neck\.layer_norm1", "neck.1"),
    (r"neck\.conv2", "neck.2"), (r"neck\.layer_norm2", "neck.3"),
    (r"prompt_encoder\.shared_embedding\.positional_embedding", "prompt_encoder.pe_layer.positional_encoding_gaussian_matrix"),
    (r"prompt_encoder\.point_embed\.", "prompt_encoder.point_embeddings."),
    (r"mask_embed\.conv1", "mask_downscaling.0"), (r"mask_embed\.layer_norm1", "mask_downscaling.1"),
    (r"mask_embed\.conv2", "mask_downscaling.3"), (r"mask_embed\.layer_norm2", "mask_downscaling.4"),
    (r"mask_embed\.conv3", "mask_downscaling.6"),
    (r"mask_decoder\.upscale_conv1", "mask_decoder.output_upscaling.0"),
    (r"mask_decoder\.upscale_layer_norm", "mask_decoder.output_upscaling.1"),
    (r"mask_decoder\.upscale_conv2", "mask_decoder.output_upscaling.3"),
    (r"(iou_prediction_head|output_hypernetworks_mlps\.\d+)\.layers\.0", r"\1.layers.1"),
    (r"(iou_prediction_head|output_hypernetworks_mlps\.\d+)\.proj_in", r"\1.layers.0"),
    (r"(iou_prediction_head|output_hypernetworks_mlps\.\d+)\.proj_out", r"\1.layers.2"),
    (r"\.layer_norm(\d)\.", r".norm\1."),
    (r"\.layer_norm_final_attn\.", ".norm_final_attn."),
]


def to_original(state):
    out = {}
    for key, value in state.items():
        if key.startswith("shared_image_embedding."):
            continue
        for pat, rep in _TO_ORIGINAL:
            key = re.sub(pat, rep, key)
        out[key] = value
    out["pixel_mean"] = torch.tensor([123.675, 116.28, 103.53]).view(-1, 1, 1)
    out["pixel_std"] = torch.tensor([58.395, 57.12, 57.375]).view(-1, 1, 1)
    return out


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    root = tmp_path_factory.mktemp("models")
    save_random_clip(root / "clip-vit-base-patch16")
    save_random_sam(root / "sam-vit-huge")
    return root


def test_missing_model_error_names_files_and_public_id(tmp_path, monkeypatch):
    monkeypatch.setenv(ENV_VAR, str(tmp_path))
    with pytest.raises(ModelNotFoundError) as err:
        load_clip()
    msg = str(err.value)
    for part in ("openai/clip-vit-base-patch16", "config.json", "model.safetensors", "vocab.json", str(tmp_path)):
        assert part in msg
    with pytest.raises(ModelNotFoundError, match="facebook/sam-vit-huge.*") as err:
        load_sam(tmp_path / "nope")
    assert "sam_vit_h_4b8939.pth" in str(err.value)
    with pytest.raises(ModelNotFoundError, match="maskclip_jbu_stack_cocostuff.ckpt"):
        resolve_model_path("featup_jbu")
    monkeypatch.delenv(ENV_VAR)
    with pytest.raises(ModelNotFoundError, match=f"\\${ENV_VAR} is unset"):
        resolve_model_path("clip")


def test_incomplete_folder_is_not_accepted(tmp_path):
    (tmp_path / "config.json").write_text("{}")
    with pytest.raises(ModelNotFoundError, match="model.safetensors"):
        resolve_model_path("clip", tmp_path)


def test_resolution_order(tiny, tmp_path, monkeypatch):
    monkeypatch.setenv(ENV_VAR, str(tiny))
    assert resolve_model_path("clip") == tiny / "clip-vit-base-patch16"
    cfg = tmp_path / "models.json"
    cfg.write_text(json.dumps({"sam": str(tiny / "sam-vit-huge")}))
    assert resolve_model_path("sam", config=cfg) == tiny / "sam-vit-huge"
    assert resolve_model_path("sam", config={"sam": tiny / "sam-vit-huge"}) == tiny / "sam-vit-huge"
    with pytest.raises(ModelNotFoundError):
        resolve_model_path("sam", config={"sam": tmp_path / "elsewhere"})


def test_clip_loads_with_tokenizer(tiny):
    bundle = load_clip(tiny / "clip-vit-base-patch16")
    tok = bundle.tokenizer(["a photo of the cup"], return_tensors="pt")
    emb = bundle.model.get_text_features(**tok)
    emb = emb if isinstance(emb, torch.Tensor) else emb.pooler_output
    assert emb.shape == (1, bundle.model.config.projection_dim) and torch.isfinite(emb).all()


def _sam_outputs(model):
    g = torch.Generator().manual_seed(0)
    pixels = torch.randn(1, 3, 64, 64, generator=g)
    pts = torch.rand(1, 5, 1, 2, generator=g) * 64
    with torch.no_grad():
        out = model(pixel_values=pixels, input_points=pts, input_labels=torch.ones(1, 5, 1, dtype=torch.int64))
    return out.pred_masks, out.iou_scores


def test_sam_hf_folder_and_original_checkpoint_agree(tiny, tmp_path):
    reference = random_sam("tiny", seed=0)
    hf = load_sam(tiny / "sam-vit-huge")
    torch.save(to_original(reference.state_dict()), tmp_path / "sam_vit_h_4b8939.pth")
    original = load_sam(tmp_path / "sam_vit_h_4b8939.pth", vision_overrides={"num_attention_heads": 2})
    assert original.config.vision_config.global_attn_indexes == [1]
    assert original.config.vision_config.window_size == 2
    ref_masks, ref_iou = _sam_outputs(reference)
    for model in (hf, original):
        masks, iou = _sam_outputs(model)
        torch.testing.assert_close(masks, ref_masks)
        torch.testing.assert_close(iou, ref_iou)


def test_sam_checkpoint_in_models_dir(tiny, tmp_path, monkeypatch):
    torch.save(to_original(random_sam("tiny").state_dict()), tmp_path / "sam_vit_h_4b8939.pth")
    monkeypatch.setenv(ENV_VAR, str(tmp_path))
    assert resolve_model_path("sam") == tmp_path / "sam_vit_h_4b8939.pth"


def test_wrong_checkpoint_is_named(tmp_path):
    torch.save({"something": torch.zeros(1)}, tmp_path / "sam_vit_h_4b8939.pth")
    with pytest.raises(ValueError, match="image_encoder.patch_embed.proj.weight"):
        load_sam(tmp_path / "sam_vit_h_4b8939.pth")


def test_download_only_when_allowed(tmp_path, monkeypatch):
    import sys
    import types

    calls = []
    fake = types.ModuleType("huggingface_hub")
    fake.snapshot_download = lambda repo, local_dir=None: calls.append((repo, local_dir)) or str(tmp_path)
    monkeypatch.setitem(sys.modules, "huggingface_hub", fake)
    monkeypatch.setenv(ENV_VAR, str(tmp_path))
    with pytest.raises(ModelNotFoundError):
        resolve_model_path("clip")
    assert calls == []
    assert resolve_model_path("clip", allow_download=True) == tmp_path
    assert calls == [("openai/clip-vit-base-patch16", str(tmp_path / "clip-vit-base-patch16"))]

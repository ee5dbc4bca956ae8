"""The defaults chosen by measurement or fixed by a specification, each pinned against its source,
so that changing one is a deliberate act (the source named beside it must change too)."""
from __future__ import annotations

import inspect

from tiger.cli.main import build_parser
from tiger.language.featup import ImplicitConfig
from tiger.recon.config import ReconConfig
from tiger.retrieval import guard
from tiger.retrieval.select import top_cluster_threshold


def _defaults(command: str) -> dict:
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")  # the sub-command table
    return {a.dest: a.default for a in sub.choices[command]._actions}


def test_selection_guard_limits_are_those_the_help_states():
    # docs/RETRIEVAL.md and `tiger query --help`: more than half of the scene, or several groups
    # (linked within 5 % of the scene's diagonal, counting groups of >= 10 % of the selection)
    assert (guard.MAX_SHARE, guard.LINK, guard.MIN_GROUP) == (0.5, 0.05, 0.1)


def test_auto_threshold_split_rule():
    # docs/RETRIEVAL.md: a split counts when the density at the cut is <= 0.35 of the lower mode and
    # each side keeps >= 0.2 % of the scores and >= 32 of them (chosen on the demo tabletop)
    sig = inspect.signature(top_cluster_threshold).parameters
    assert {k: sig[k].default for k in ("max_depth", "min_fraction", "min_count")} == \
        {"max_depth": 0.35, "min_fraction": 0.002, "min_count": 32}


def test_implicit_featup_defaults():
    # FeatUp's implicit upsampler drops out at 0.2; the fast fit in bf16 is the default (within
    # tolerance of the reference loop: tests/language/test_featup_implicit.py, docs/LANGUAGE_FEATURES.md)
    cfg = ImplicitConfig()
    assert (cfg.dropout, cfg.method, cfg.precision) == (0.2, "fast", "bf16")


def test_reconstruction_colours_random_points_from_the_views():
    # docs/BENCHMARKS.md, fox reconstruction: colours from the views (with the border masks) gave the
    # fox its held-out PSNR; INRIA's random colours are the alternative
    assert ReconConfig().init_colors == "views"


def test_cli_defaults_of_the_new_commands():
    assert _defaults("embed")["init"] == "lift"  # lifting starts the field (tests/language/test_lift.py)
    view = _defaults("view")
    assert (view["host"], view["port"]) == ("127.0.0.1", 8080)  # loopback unless told otherwise
    for command in ("query", "edit", "delete"):
        assert _defaults(command)["tau"] == "auto", command


def test_reconstruct_background_follows_the_images_and_appearance_stays_opt_in():
    # random backgrounds for opaque photographs (tiger.recon.data.training_background; the fox's
    # held-out PSNR in benchmarks/recon_fox_study.py, docs/BENCHMARKS.md); per-image appearance is a
    # measured candidate, not yet a default: a change here needs its GPU figures
    from tiger.recon.data import training_background

    d = _defaults("reconstruct")
    assert (d["appearance"], d["random_background"]) == (False, None)  # None: decided by the images
    assert training_background([], None)[0] and not training_background(["a.png"], None)[0]
    # the library's trainer (also used to refit edited renders) keeps a fixed background unless told
    assert (ReconConfig().appearance, ReconConfig().random_background) == (False, False)


def test_implicit_featup_stopping_and_fusion_defaults():
    # the fit stops once 100 more steps change its map by less than two seeds' stopped fits differ
    # (1 - cosine 1e-2), not before 400 steps (cosine 0.993-0.994 from the 1200-step reference there;
    # calibrated on the H100: docs/LANGUAGE_FEATURES.md, benchmarks/gpu/results/featup_implicit_steps_h100.txt
    # and featup_implicit_stopping_h100.txt); the fused network ops are on; the
    # backbone featurises 256 views a batch (0.69 s against 0.77 s at 64 for 2048 views on the H100)
    from tiger.language.featup import STOP_CHANGE, STOP_MIN_STEPS

    cfg = ImplicitConfig()
    assert (STOP_CHANGE, STOP_MIN_STEPS) == (1e-2, 400)
    assert (cfg.stop_change, cfg.min_steps) == (STOP_CHANGE, STOP_MIN_STEPS)
    assert (cfg.steps, cfg.check_every) == (1200, 100)
    assert (cfg.fused_network, cfg.featurize_batch) == (True, 256)
    # the step channels last (tiger::magnitude_blur, tiger::masked_logit): 3.13 / 3.05 s per 1080p
    # image against 3.33 / 3.23 s channels first, same H100 call
    # (benchmarks/gpu/results/featup_implicit_h100.txt)
    assert cfg.step_layout == "channels_last"
    # the attention op's pixel-major backward dots: 2.66 / 2.65 s per 1080p image against
    # 3.11 / 2.92 s with the baseline kernels, staged_tiles 2.91 / 2.93 s, same H100 call
    # (benchmarks/gpu/results/featup_implicit_attention_variants_h100.txt; A/B in one call: 2.61 / 2.62
    # against 2.75 / 2.75 s, featup_implicit_attention_ab_h100.txt)
    assert cfg.attention_variant == "pixel_dots"


def test_guidance_model_kernels_defaults():
    # GEGLU fusion, 4x4 VAE downsampling and the GroupNorm bias fold follow the device (on with
    # tiger's CUDA kernels); FP8 stays opt-in: no faster and 4x bf16's SDS error on the H100
    # (benchmarks/gpu/results/guidance_floor_model_kernels_h100.txt)
    from tiger.edit.guidance.model_kernels import ModelKernels

    k = ModelKernels()
    assert (k.matmul_precision, k.fp8_fast_accum) == ("model", False)
    assert (k.fused_geglu, k.vae_downsample_4x4, k.fold_norm_bias) == (None, None, None)
    # the row LayerNorm and the sub-pixel upsampling also follow the device: the pooled CSD step
    # 61.2 / 61.0 ms without either, 60.3 ms with both, SDS error vs float32 unchanged (H100, one
    # call; benchmarks/gpu/results/guidance_floor_layer_norm_upsample_h100.txt)
    assert (k.row_layer_norm, k.subpixel_upsample) == (None, None)
    # the lean attention is on everywhere (same values bit for bit): CSD pooled step 61.2 -> 60.3 ms
    # (H100, one call; guidance_floor_lean_attention_h100.txt)
    assert k.lean_attention is None
    # the VAE ResNet blocks' own backward follows the device too: CSD pooled step 60.8 -> 59.8 ms, the
    # 1200-step edit 83.5 -> 82.0 s (H100; guidance_floor_block_backward_h100.txt, edit_1200_steps_h100.txt)
    assert k.block_backward is None
    # zero-padded first convolutions follow the device: CSD pooled step 59.6-59.7 -> 59.0-59.1 ms, the
    # 1200-step edit 81.4 s (H100; guidance_floor_pad_conv_in_h100.txt, edit_1200_steps_h100.txt)
    assert k.pad_conv_in is None
    # the fused transformer blocks follow the device: CSD step fresh 70.0-70.1 -> 69.4-69.5 ms, pooled
    # 58.7-58.9 -> 58.4-58.8 ms, SDS error vs float32 unchanged (H100, one call;
    # guidance_floor_fused_transformer_h100.txt)
    assert k.fused_transformer is None
    # the VAE encoder's conv_in / downsampler biases carried into the next ResNet block: CSD step
    # pooled 58.8 / 59.3 -> 58.5 / 58.9 ms, fresh 70.0 / 70.7 -> 69.4 / 69.9 ms (H100, one call;
    # guidance_floor_carry_conv_bias_h100.txt)
    assert k.carry_conv_bias is None
    # InstructPix2Pix's instruction and image-only branches once up to the first cross-attention, on
    # every device ("auto" resolves to on): CSD step pooled 58.3 -> 57.9 ms, fresh 69.7 -> 68.9-69.4 ms
    # (H100, one call; guidance_floor_branch_prefix_h100.txt); the 1200-step edit 80.6 -> 79.0 s with
    # MVDream's cached camera conditions (edit_1200_steps_h100.txt)
    assert k.branch_prefix is None
    # the up blocks' skip concatenations written in place and the VAE attention's row softmax follow
    # the device (on with tiger's CUDA kernels): CSD step pooled -0.3 to -0.7 ms and -0.1 to -0.3 ms,
    # the 1200-step edit 74.31 -> 73.33-73.54 s with the one-pass sub-pixel interleave (H100;
    # guidance_floor_softmax_skip_concat_h100.txt, edit_1200_steps_h100.txt)
    assert (k.skip_concat, k.row_softmax) == (None, None)


def test_csd_runs_mvdream_beside_instructpix2pix_and_records_no_stream_choice():
    # MVDream on a side stream beside InstructPix2Pix: the CSD step 68.5 -> 64.7 ms, the 1200-step
    # edit 88.4 -> 84.3 s (H100; benchmarks/gpu/results/guidance_streams_h100.txt,
    # edit_1200_steps_h100.txt). The values do not depend on it, so the record does not either.
    from tiger.edit.csd import CSDGuidance
    from tiger.edit.guidance.recolor import RecolorGuidance

    ip, mv = RecolorGuidance("make it red"), RecolorGuidance("make it blue")
    default = CSDGuidance(ip, mv)
    assert default.concurrent is True
    assert default.settings() == CSDGuidance(ip, mv, concurrent=False).settings()


def test_prepare_runs_features_alongside_by_device_and_sam_precision_follows_it():
    # None: alongside the reconstruction on one GPU, one after the other on the CPU (tiger/cli/prepare.py)
    assert _defaults("prepare")["alongside"] is None
    # SAM: bf16 on CUDA, float32 on the CPU (SamMaskConfig.precision "auto"); prepare passes it on
    assert _defaults("features")["sam_precision"] == "auto" and _defaults("prepare")["sam_precision"] is None


def test_feature_stage_memory_and_disk_shares(monkeypatch, tmp_path):
    # stage-1 records: at most a quarter of the host memory (CPU) kept between the passes, at most
    # a tenth of the disk written by a run, 1 GiB and 5 % of the disk kept free (extract_io)
    import os
    import shutil
    from collections import namedtuple

    import torch

    from tiger.language import extract_io

    kept = extract_io.KeptRecords(torch.device("cpu"))
    assert kept.budget == os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 4
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(1000 << 30, 0, 1000 << 30))
    budget = extract_io.DiskBudget(tmp_path)
    assert budget.room(100 << 30) and not budget.room((100 << 30) + 1)  # a tenth of the disk
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(1000 << 30, 0, (50 << 30) + (1 << 20)))
    assert budget.room(1 << 20) and not budget.room((1 << 20) + 1)  # 5 % kept free


def test_edit_renders_with_one_pixel_per_backward_thread():
    # docs/BENCHMARKS.md (edit render stage, H100): the edit's backward on few tiles with long lists
    # is faster with one pixel per backward thread (its own cameras: 1.94 against 2.38 ms), the
    # library default stays 2 (real captures' full backward: fox 1.24 against 1.56 ms); tiles are
    # drawn longest list first by default (the edit's forward 1.15 -> 1.02 ms)
    from tiger.edit.loop import EDIT_RASTER_KERNELS
    from tiger.ops.raster import RasterKernelSettings

    assert EDIT_RASTER_KERNELS == RasterKernelSettings(backward_pixels_per_thread=1)
    assert RasterKernelSettings().backward_pixels_per_thread == 2
    assert RasterKernelSettings().tile_order == "heavy_first"
    assert RasterKernelSettings().warp_cull is True


def test_edit_prepares_the_next_pool_set_beside_the_step_and_records_no_such_choice():
    # a new pool set's originals and condition encode prepared beside the step before it: view-pool
    # wait 3.64 -> 0.19 ms/step, the 1200-step edit 79.7 -> 78.4 s by default, 75.8 -> 75.4 s with a
    # pool of 64 (H100, one call each; benchmarks/gpu/results/edit_1200_steps_h100.txt). The values
    # do not depend on it, so neither the record nor the checkpoint signature does.
    from tiger.edit import EditConfig

    assert EditConfig().prefetch_views is True
    assert EditConfig().to_dict() == EditConfig(prefetch_views=False).to_dict()


def test_edit_densifies_every_100_steps_from_step_100():
    # tiger edit's schedule (docs/EDITING.md, "densification": every 100 steps from step 100, steps/12);
    # benchmarks/edit.py takes its --densify-every default from here, so the 1200-step figures in
    # docs/BENCHMARKS.md (edit_1200_steps_h100.txt) time this schedule, not the former 25.
    from tiger.edit import EditConfig

    assert (EditConfig().densify_every, EditConfig().densify_from) == (100, 100)
    assert EditConfig().steps // 12 == EditConfig().densify_every

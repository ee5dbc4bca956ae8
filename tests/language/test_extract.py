"""extract_features: outputs, caching, resume after an interruption, and rank sharding."""
import dataclasses
import os

import pytest
import torch
import torch.multiprocessing as mp

from tiger.language import extract as extract_mod
from tiger.language.extract import FeatureConfig, FeatureSet, extract_features, read_rgb_image
from tiger.language.featup import ImplicitConfig
from tiger.language.maskclip import MaskCLIP
from tiger.language.sam_masks import SamMaskConfig, SamMaskGenerator

LENIENT = SamMaskConfig(points_per_side=4, pred_iou_thresh=-1e9, stability_score_thresh=0.0, mask_nms_score=-1e9,
                        min_mask_region_area=10)


class SimulatedCrash(Exception):
    pass


def images(n=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    return [torch.rand(3, 40 + 8 * k, 56, generator=g) for k in range(n)]


def config(**kw):
    base = dict(upsampler="bilinear", clip_long_side=64, output_long_side=32, pca_dim=4, sam=LENIENT)
    base.update(kw)
    return FeatureConfig(**base)


@pytest.fixture(scope="module")
def models(tiny_models):
    clip = MaskCLIP.from_pretrained(tiny_models / "clip-vit-base-patch16")
    sam = SamMaskGenerator.from_pretrained(tiny_models / "sam-vit-huge", mask_config=LENIENT)
    return clip, sam


def test_outputs_and_masked_average(models, tmp_path):
    clip, sam = models
    imgs = images()
    # memory_budget=0: every stage-1 record goes through the cache files
    fs = extract_features(imgs, tmp_path, clip=clip, sam=sam, config=config(), progress=False, memory_budget=0)
    assert fs.names == ["00000", "00001", "00002"]
    for k, name in enumerate(fs.names):
        feats, valid = fs.load(name)
        h = round(32 * (40 + 8 * k) / 56) if 40 + 8 * k < 56 else 32
        assert feats.dtype == torch.float16 and feats.shape == (h, 32, 4) and valid.all()
        rec = torch.load(tmp_path / "cache" / f"{name}.pt", weights_only=True)
        ids = rec["ids"].long()
        # every pixel of a mask carries that mask's projected mean
        for m in ids.unique().tolist():
            if m >= 0:
                vals = feats[ids == m].float()
                assert (vals - vals[0]).abs().max() < 1e-6
    # the text projection uses the saved basis
    q = clip.encode_text(["red cup"])
    assert fs.pca.project(q).shape == (1, 4)
    assert (tmp_path / "pca.pt").is_file()
    # records kept in memory between the passes give the same bits as records read back from the disk
    mem = extract_features(imgs, tmp_path / "in_memory", clip=clip, sam=sam, config=config(), progress=False)
    assert torch.equal(mem.pca.components, fs.pca.components) and torch.equal(mem.pca.mean, fs.pca.mean)
    for name in fs.names:
        for x, y in zip(fs.load(name), mem.load(name)):
            assert torch.equal(x, y), name
        stats = torch.load(tmp_path / "cache" / f"{name}.stats.pt", weights_only=True)["stats"]
        assert torch.equal(stats["outer"], torch.load(tmp_path / "in_memory" / "cache" / f"{name}.stats.pt",
                                                      weights_only=True)["stats"]["outer"])


def test_image_statistics_match_a_batch_pca_of_the_pixels(models):
    """The per-image statistics (mask means weighted by their pixel counts, unmasked rows once, in
    chunks) equal the moments of the per-pixel feature rows they stand for."""
    from tiger.utils.pca import moments

    g = torch.Generator().manual_seed(3)
    means = torch.nn.functional.normalize(torch.randn(5, 16, generator=g), dim=1).half()
    counts = torch.tensor([3, 0, 7, 1, 2])
    unmasked = torch.randn(11, 16, generator=g).half()
    stats = extract_mod.image_statistics(means, counts, unmasked, chunk_rows=4)
    rows = torch.cat([means.repeat_interleave(counts, 0), unmasked]).double()
    ref = moments(rows)
    for key in ("count", "sum", "outer"):
        assert torch.allclose(stats[key], ref[key], rtol=1e-12, atol=1e-12), key


def test_resume_after_interruption(models, tmp_path, monkeypatch):
    clip, sam = models
    imgs = images()
    calls = []
    crash = [True]
    real = extract_mod.compute_image_features

    def flaky(image, *a, **kw):
        calls.append(tuple(image.shape))
        if len(calls) == 2 and crash[0]:
            crash[0] = False
            raise SimulatedCrash("simulated interruption")
        return real(image, *a, **kw)

    monkeypatch.setattr(extract_mod, "compute_image_features", flaky)
    with pytest.raises(SimulatedCrash):
        extract_features(imgs, tmp_path, clip=clip, sam=sam, config=config(), progress=False)
    done = sorted(p.name for p in (tmp_path / "cache").iterdir())
    assert done == ["00000.pt", "00000.stats.pt"]  # the finished image's record survives; nothing torn
    first_mtime = os.stat(tmp_path / "cache" / "00000.pt").st_mtime_ns
    calls.clear()
    # memory_budget=0 from here: every record reaches the cache (the PCA refit below reads them)
    fs = extract_features(imgs, tmp_path, clip=clip, sam=sam, config=config(), progress=False, memory_budget=0)
    assert len(calls) == 2  # the finished image was skipped
    assert os.stat(tmp_path / "cache" / "00000.pt").st_mtime_ns == first_mtime
    # identical to an uninterrupted run
    monkeypatch.setattr(extract_mod, "compute_image_features", real)
    ref = extract_features(imgs, tmp_path / "ref", clip=clip, sam=sam, config=config(), progress=False)
    for name in fs.names:
        assert torch.equal(fs.load(name)[0], ref.load(name)[0])
    calls.clear()
    monkeypatch.setattr(extract_mod, "compute_image_features", flaky)
    extract_features(imgs, tmp_path, clip=clip, sam=sam, config=config(), progress=False)
    assert calls == []  # a finished run does nothing again
    # a new PCA size refits the PCA from the cache without recomputing any image
    fs3 = extract_features(imgs, tmp_path, clip=clip, sam=sam, config=config(pca_dim=3), progress=False)
    assert calls == [] and fs3.load(fs3.names[0])[0].shape[-1] == 3
    # another stage-1 setting is recomputed, not mixed with the old cache
    extract_features(imgs, tmp_path, clip=clip, sam=sam, config=config(unmasked="ignore"), progress=False)
    assert len(calls) == 3
    monkeypatch.setattr(extract_mod, "compute_image_features", real)


def test_resume_when_records_stayed_in_memory(models, tmp_path, monkeypatch):
    """A record kept in memory whose background write was dropped (the disk was behind): its map,
    once written, makes it finished; only a new PCA basis needs the image computed again."""
    clip, sam = models
    imgs = images()
    ref = extract_features(imgs, tmp_path / "ref", clip=clip, sam=sam, config=config(pca_dim=3), progress=False)
    extract_features(imgs, tmp_path / "run", clip=clip, sam=sam, config=config(), progress=False)
    for name in ("00000", "00002"):  # as if these writes had been dropped
        (tmp_path / "run" / "cache" / f"{name}.pt").unlink(missing_ok=True)  # (or really dropped)
    calls = []
    real = extract_mod.compute_image_features

    def spy(image, *a, **kw):
        calls.append(tuple(image.shape))
        return real(image, *a, **kw)

    monkeypatch.setattr(extract_mod, "compute_image_features", spy)
    extract_features(imgs, tmp_path / "run", clip=clip, sam=sam, config=config(), progress=False)
    assert calls == []  # their maps are written with the current basis
    fs = extract_features(imgs, tmp_path / "run", clip=clip, sam=sam, config=config(pca_dim=3), progress=False)
    assert len(calls) == 2  # a new basis needs the two missing records
    for name in fs.names:
        assert torch.equal(fs.load(name)[0], ref.load(name)[0])


def test_background_saver_and_kept_records(tmp_path):
    from tiger.language.extract_io import BackgroundSaver, KeptRecords, record_bytes

    saver = BackgroundSaver(torch.device("cpu"), max_pending=1, workers=1)
    gate = __import__("threading").Event()
    real = saver._write
    saver._write = lambda *a: (gate.wait(5), real(*a))
    saver.save({"x": torch.ones(3)}, tmp_path / "a.pt", fsync=False)
    saver.save({"x": torch.ones(3)}, tmp_path / "b.pt", fsync=False, optional=True)  # queued behind a.pt
    saver.drop_optional()
    gate.set()
    saver.close()
    assert saver.dropped == [tmp_path / "b.pt"] and (tmp_path / "a.pt").is_file()
    assert not (tmp_path / "b.pt").exists()
    bad = BackgroundSaver(torch.device("cpu"))
    bad.save({"x": torch.ones(1)}, tmp_path / "a.pt" / "inside_a_file.pt", fsync=False)
    with pytest.raises(OSError):
        bad.close()
    rec = {"ids": torch.zeros(4, 4, dtype=torch.int32), "stats": {"outer": torch.zeros(2, 2, dtype=torch.float64)}}
    assert record_bytes(rec) == 64 + 32
    kept = KeptRecords(torch.device("cpu"), budget=150)
    assert kept.offer("a", rec) and not kept.offer("b", rec)
    assert kept.pop("a") is rec and kept.kept_bytes == 0 and kept.pop("b") is None
    assert not KeptRecords(torch.device("cpu"), budget=0).offer("a", rec)


def test_paths_implicit_and_no_sam(models, tmp_path):
    from PIL import Image

    clip, _ = models
    paths = []
    for k, img in enumerate(images(2)):
        p = tmp_path / f"view_{k}.png"
        Image.fromarray((img.permute(1, 2, 0) * 255).round().byte().numpy()).save(p)
        paths.append(p)
    assert torch.allclose(read_rgb_image(paths[0]), images(1)[0], atol=1 / 255)
    cfg = config(upsampler="implicit", use_sam=False,
                 implicit=ImplicitConfig(steps=3, n_views=4, pca_batch=4, kernel_size=3, jitters_per_step=2))
    fs = extract_features(paths, tmp_path / "out", clip=clip, config=cfg, progress=False)
    assert fs.names == ["view_0", "view_1"]
    assert fs.load("view_1")[0].shape == (27, 32, 4)  # 48x56 at long side 32


def test_bad_arguments(models, tmp_path):
    clip, sam = models
    with pytest.raises(ValueError, match="upsampler must be one of"):
        extract_features(images(1), tmp_path, clip=clip, sam=sam, config=config(upsampler="nearest"))
    with pytest.raises(ValueError, match="names must be unique"):
        extract_features(images(2), tmp_path, names=["a", "a"], clip=clip, sam=sam, config=config())
    with pytest.raises(ValueError, match=r"\[3, H, W\]"):
        extract_features([torch.rand(1, 8, 8)], tmp_path, clip=clip, sam=sam, config=config())


def _rank_main(rank, world, init_file, out_dir, model_dir, result_dir):
    import torch.distributed as dist

    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=world)
    try:
        clip = MaskCLIP.from_pretrained(os.path.join(model_dir, "clip-vit-base-patch16"))
        sam = SamMaskGenerator.from_pretrained(os.path.join(model_dir, "sam-vit-huge"), mask_config=LENIENT)
        seen = []
        real = extract_mod.compute_image_features

        def spy(image, *a, **kw):
            seen.append(int(image.shape[1]))
            return real(image, *a, **kw)

        extract_mod.compute_image_features = spy
        extract_features(images(3), out_dir, clip=clip, sam=sam, config=config(), progress=False)
        torch.save(seen, os.path.join(result_dir, f"rank{rank}.pt"))
    finally:
        dist.destroy_process_group()


def test_two_ranks_share_the_images(tiny_models, tmp_path):
    out = tmp_path / "out"
    mp.spawn(_rank_main, args=(2, str(tmp_path / "init"), str(out), str(tiny_models), str(tmp_path)), nprocs=2)
    seen0 = torch.load(tmp_path / "rank0.pt")
    seen1 = torch.load(tmp_path / "rank1.pt")
    assert seen0 == [40, 56] and seen1 == [48]  # rank r takes images r, r + 2, ...
    fs = FeatureSet(out, ["00000", "00001", "00002"], extract_mod.PCABasis.load(out / "pca.pt"))
    for name in fs.names:
        assert fs.load(name)[0].shape[-1] == 4
    # Sharding changes nothing: one process (same thread count as each rank) writes the same files.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        clip = MaskCLIP.from_pretrained(tiny_models / "clip-vit-base-patch16")
        sam = SamMaskGenerator.from_pretrained(tiny_models / "sam-vit-huge", mask_config=LENIENT)
        # through the disk here (memory_budget=0), in memory on the two ranks: the same bits either way
        one = extract_features(images(3), tmp_path / "one", clip=clip, sam=sam, config=config(), progress=False,
                               memory_budget=0)
    finally:
        torch.set_num_threads(threads)
    for name in one.names:
        for rel in (f"features/{name}.pt", f"cache/{name}.stats.pt", f"cache/{name}.pt"):
            if rel.startswith("cache/") and not rel.endswith("stats.pt") and not (out / rel).is_file():
                continue  # a record kept in memory may not have been written (the disk was behind)
            a = torch.load(tmp_path / "one" / rel, weights_only=True)
            b = torch.load(out / rel, weights_only=True)
            for key, value in a.items():
                if torch.is_tensor(value):
                    assert torch.equal(value, b[key]), (rel, key)
    assert torch.equal(one.pca.components, fs.pca.components)


def _pixel_features(record, image, clip, cfg):
    """Per-pixel 512-d features [h*w, D] rebuilt from a stage-1 cache record (the pixels in no
    mask regenerated from the record's ``regen``, as the projection does)."""
    ids = record["ids"].reshape(-1).long()
    out = torch.zeros(ids.numel(), record["means"].shape[1])
    valid = ids >= 0
    out[valid] = record["means"].float().cpu()[ids[valid].cpu()]
    out[~valid] = extract_mod.unmasked_rows(record, image, clip, None, cfg).float().cpu()
    return out


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_pipeline_on_cuda_matches_cpu(tiny_models, tmp_path):
    import tiger

    if not tiger.ops.cuda_enabled():
        pytest.skip("tiger built without CUDA kernels")
    outs = {}
    fp32 = dataclasses.replace(LENIENT, precision="fp32")  # SAM in float32 on both devices
    for dev in ("cpu", "cuda"):
        clip = MaskCLIP.from_pretrained(tiny_models / "clip-vit-base-patch16", device=dev)
        sam = SamMaskGenerator.from_pretrained(tiny_models / "sam-vit-huge", device=dev, mask_config=fp32)
        fs = extract_features(images(2), tmp_path / dev, clip=clip, sam=sam, config=config(sam=fp32), device=dev,
                              progress=False, memory_budget=0)
        cfg = config(sam=fp32)
        outs[dev] = [_pixel_features(torch.load(tmp_path / dev / "cache" / f"{n}.pt", weights_only=True,
                                                map_location=dev), img, clip, cfg)
                     for n, img in zip(fs.names, images(2))]
        assert fs.load(fs.names[0])[0].shape[-1] == 4
    for a, b in zip(outs["cpu"], outs["cuda"]):
        # masks may differ at a few boundary pixels (float32 upsampling on two devices)
        cos = torch.nn.functional.cosine_similarity(a, b, dim=1)
        assert (cos > 0.999).float().mean() > 0.97


def test_models_loaded_from_a_config_with_jbu(tiny_models, tmp_path):
    """No model objects passed: CLIP, SAM and the JBU checkpoint come from a models config."""
    from tiger.language.featup import JBUStack

    torch.manual_seed(0)
    state = {f"upsampler.{k}": v for k, v in JBUStack(24).state_dict().items()}
    torch.save({"state_dict": state}, tmp_path / "maskclip_jbu_stack_cocostuff.ckpt")
    models = {"clip": tiny_models / "clip-vit-base-patch16", "sam": tiny_models / "sam-vit-huge",
              "featup_jbu": tmp_path / "maskclip_jbu_stack_cocostuff.ckpt"}
    fs = extract_features(images(1), tmp_path / "out", config=config(upsampler="jbu"), models=models,
                          device="cpu", progress=False)
    feats, valid = fs.load(fs.names[0])
    assert feats.shape == (23, 32, 4) and torch.isfinite(feats.float()).all() and valid.all()


def test_records_that_fit_neither_memory_nor_disk_are_recomputed(models, tmp_path, monkeypatch):
    """With no memory budget and a disk too full for a stage-1 record, the projection pass
    recomputes each image's record: the same maps and basis as records read back from the disk,
    and no record file written (the per-image statistics still are)."""
    clip, sam = models
    imgs = images()
    ref = extract_features(imgs, tmp_path / "disk", clip=clip, sam=sam, config=config(), progress=False,
                           memory_budget=0)
    monkeypatch.setattr(extract_mod.DiskBudget, "room", lambda self, nbytes, reserve=0: False)
    full = extract_features(imgs, tmp_path / "full", clip=clip, sam=sam, config=config(), progress=False,
                            memory_budget=0)
    assert torch.equal(full.pca.components, ref.pca.components)
    for name in ref.names:
        assert not (tmp_path / "full" / "cache" / f"{name}.pt").exists()
        assert (tmp_path / "full" / "cache" / f"{name}.stats.pt").is_file()
        for x, y in zip(full.load(name), ref.load(name)):
            assert torch.equal(x, y), name


def test_disk_budget_rule(tmp_path):
    from tiger.language.extract_io import DiskBudget

    budget = DiskBudget(tmp_path / "not" / "made" / "yet")
    assert budget.room(1)
    assert not budget.room(1 << 62) and not budget.room(1, reserve=1 << 62)
    budget.add(1 << 62)  # this run's records are capped at a tenth of the disk
    assert not budget.room(1)


@pytest.mark.parametrize("upsampler", ["bilinear", "jbu", "implicit"])
def test_unmasked_rows_regenerate_the_upsampled_features(models, upsampler):
    """A stage-1 record keeps, instead of the 512-d features of its pixels in no mask, what
    regenerates them (the fitted implicit network, or the low-res CLIP map for JBU / bilinear):
    regenerated, they equal the rows of the upsampled map computed directly by
    ``upsample_features`` (the path before records were compact), bit for bit on the CPU."""
    import torch.nn.functional as F

    from tiger.language.featup import JBUStack, upsample_features
    from tiger.language.maskclip import normalize_images, resize_for_patches

    clip, sam = models
    torch.manual_seed(0)
    jbu = JBUStack(24).eval() if upsampler == "jbu" else None  # as from_checkpoint loads it
    cfg = config(upsampler=upsampler,
                 implicit=ImplicitConfig(steps=3, n_views=4, pca_batch=4, kernel_size=3, jitters_per_step=2))
    img = images(1)[0]
    rec = extract_mod.compute_image_features(img, clip, sam, jbu, cfg)
    ids = rec["ids"].reshape(-1)
    assert (ids < 0).any() and "regen" in rec
    if upsampler != "implicit":  # (the fitted network outweighs a map this small; not a 1080p one)
        assert extract_mod.record_bytes(rec) < 2 * int((ids < 0).sum()) * 24  # less than the rows it replaces
    clip_in = resize_for_patches(img[None], cfg.clip_long_side, clip.patch_size)[0]
    with torch.enable_grad():
        hr = upsample_features(clip_in, clip, tuple(rec["size"]), upsampler, jbu=jbu, implicit=cfg.implicit,
                               guidance_normalizer=lambda x: normalize_images(x, "imagenet"))
    direct = F.normalize(hr.detach().float(), dim=0).permute(1, 2, 0).reshape(-1, hr.shape[0])[ids < 0].half()
    rows = extract_mod.unmasked_rows(rec, img, clip, jbu, cfg)
    assert rows.shape == direct.shape and torch.equal(rows, direct)


def test_feature_set_load_is_memory_mapped_and_survives_a_rewrite(tmp_path):
    """Maps come back memory-mapped (read when touched) with the written bits; replacing a file
    atomically (a rerun with --force) leaves maps already loaded as they were."""
    from tiger.language.pca import PCABasis
    from tiger.utils.io import atomic_torch_save

    g = torch.Generator().manual_seed(0)
    feats, valid = torch.randn(6, 9, 4, generator=g).half(), torch.rand(6, 9, generator=g) > 0.5
    (tmp_path / "features").mkdir()
    atomic_torch_save({"features": feats, "valid": valid, "pca": "x"}, tmp_path / "features" / "a.pt", fsync=False)
    fs = FeatureSet(tmp_path, ["a"], PCABasis(torch.zeros(4), torch.eye(4), torch.ones(4)))
    f, v = fs.load("a")
    assert torch.equal(f, feats) and torch.equal(v, valid)
    atomic_torch_save({"features": feats + 1, "valid": ~valid, "pca": "y"}, tmp_path / "features" / "a.pt",
                      fsync=False)
    assert torch.equal(f, feats) and torch.equal(v, valid)
    assert torch.equal(fs.load("a")[0], feats + 1)

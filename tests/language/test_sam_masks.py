"""SAM finest-level automatic masks: prompting, filters and clean-up against references."""
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from tiger.language.sam_masks import (
    SamMaskConfig,
    SamMaskGenerator,
    SamMasks,
    masks_to_boxes,
    point_grid,
    remove_small_regions_of_mask as remove_small_regions,
    stability_score,
)


def test_point_grid_is_sams():
    n = 5
    offset = 1 / (2 * n)
    side = np.linspace(offset, 1 - offset, n)
    ref = np.stack([np.tile(side[None, :], (n, 1)).ravel(), np.tile(side[:, None], (1, n)).ravel()], axis=1)
    np.testing.assert_allclose(point_grid(n).numpy(), ref, atol=1e-12)


def test_stability_score():
    logits = torch.tensor([[[2.0, 0.5, -0.5, -2.0]]])
    # > +1: one pixel; > -1: three pixels
    torch.testing.assert_close(stability_score(logits, 0.0, 1.0), torch.tensor([1 / 3]))


def test_masks_to_boxes_matches_nonzero():
    masks = torch.rand(6, 9, 11) > 0.8
    masks[2] = False
    boxes = masks_to_boxes(masks)
    for k in range(6):
        ys, xs = torch.nonzero(masks[k], as_tuple=True)
        ref = [0, 0, 0, 0] if len(ys) == 0 else [xs.min(), ys.min(), xs.max(), ys.max()]
        assert boxes[k].tolist() == [float(v) for v in ref]


def test_remove_small_regions():
    m = np.zeros((20, 20), dtype=bool)
    m[2:15, 2:15] = True
    m[5, 5] = False  # a 1-px hole
    m[18:20, 18:20] = True  # a 4-px island
    filled, changed = remove_small_regions(m, 10, "holes")
    assert changed and filled[5, 5] and filled[18, 18]
    cleaned, changed = remove_small_regions(filled, 10, "islands")
    assert changed and not cleaned[18:, 18:].any() and cleaned[2:15, 2:15].all()
    same, changed = remove_small_regions(cleaned, 10, "islands")
    assert not changed and np.array_equal(same, cleaned)
    tiny = np.zeros((10, 10), dtype=bool)
    tiny[0, 0] = True
    tiny[5:7, 5:7] = True
    kept, _ = remove_small_regions(tiny, 10, "islands")  # all small: the largest stays
    assert kept[5:7, 5:7].all() and not kept[0, 0]
    with pytest.raises(ValueError, match="holes"):
        remove_small_regions(m, 10, "both")


def test_id_map_smallest_mask_wins():
    masks = torch.zeros(3, 6, 6, dtype=torch.bool)
    masks[0, :, :] = True
    masks[1, 1:4, 1:4] = True
    masks[2, 2:3, 2:3] = True
    ids = SamMasks(masks, torch.ones(3), torch.ones(3)).id_map()
    assert ids[0, 0] == 0 and ids[1, 1] == 1 and ids[2, 2] == 2
    assert SamMasks(masks[:0], torch.ones(0), torch.ones(0)).id_map().eq(-1).all()


@pytest.fixture(scope="module")
def generator(tiny_models):
    cfg = SamMaskConfig(points_per_side=4, points_per_batch=7, pred_iou_thresh=-1e9, stability_score_thresh=0.0)
    return SamMaskGenerator.from_pretrained(tiny_models / "sam-vit-huge", mask_config=cfg)


def test_predict_matches_single_point_prompts(generator):
    image = torch.rand(3, 40, 56, generator=torch.Generator().manual_seed(3))
    size = (30, 42)
    masks, iou, stab = generator.predict(image, size)
    assert masks.shape == (16, *size) and masks.dtype == torch.bool
    model = generator.model
    pixels, (rh, rw) = generator.preprocess(image)
    assert (rh, rw) == (46, 64)  # long side -> 64, short side 40 * 64 / 56 rounded
    assert pixels.shape == (1, 3, 64, 64) and pixels[..., rh:, :].abs().sum() == 0
    emb = model.get_image_embeddings(pixels)
    n = 4
    for k in (0, 3, 6, 9, 12, 15):  # corners and inner points of the 4x4 grid
        x = (k % n + 0.5) / n * rw
        y = (k // n + 0.5) / n * rh
        with torch.no_grad():
            out = model(image_embeddings=emb, input_points=torch.tensor([[[[x, y]]]]), multimask_output=True)
        low = out.pred_masks[0, 0, 0][None, None]
        up = F.interpolate(low, size=(64, 64), mode="bilinear", align_corners=False)[..., :rh, :rw]
        up = F.interpolate(up, size=size, mode="bilinear", align_corners=False)[0, 0]
        assert torch.equal(masks[k], up > 0)
        torch.testing.assert_close(iou[k], out.iou_scores[0, 0, 0])
        torch.testing.assert_close(stab[k], ((up > 1).sum() / (up > -1).sum().clamp_min(1)).float())


def test_full_generator_output_obeys_its_filters(generator):
    cfg = SamMaskConfig(points_per_side=6, pred_iou_thresh=-1e9, stability_score_thresh=0.0, mask_nms_score=-1e9,
                        min_mask_region_area=20)
    gen = SamMaskGenerator(generator.model, cfg)
    out = gen(torch.rand(3, 48, 64, generator=torch.Generator().manual_seed(5)))
    m = out.masks
    assert m.shape[1:] == (48, 64) and m.shape[0] >= 1
    assert (m.flatten(1).sum(1) >= 20).all()
    inter = (m.flatten(1).double() @ m.flatten(1).double().T)
    area = inter.diagonal()
    iou = inter / (area[:, None] + area[None, :] - inter)
    iou.fill_diagonal_(0)
    assert (iou <= 0.8 + 1e-9).all()
    ids = out.id_map()
    assert ids.min() >= -1 and ids.max() < m.shape[0]
    for k in ids.unique().tolist():
        if k >= 0:
            assert m[k][ids == k].all()


CUDA = torch.cuda.is_available() and __import__("tiger").ops.cuda_enabled()


def _id_map_loop(masks):
    """The id map painted mask by mask, largest first (the definition)."""
    m, h, w = masks.shape
    ids = torch.full((h, w), -1, dtype=torch.int64)
    for k in torch.argsort(masks.flatten(1).sum(1), descending=True, stable=True).tolist():
        ids[masks[k]] = k
    return ids


def test_id_map_matches_painting_loop():
    g = torch.Generator().manual_seed(0)
    masks = torch.rand(70, 23, 31, generator=g) < 0.3
    masks[5] = masks[9]  # equal areas: the later index wins
    masks[11] = False
    torch.testing.assert_close(SamMasks(masks, torch.ones(70), torch.ones(70)).id_map(), _id_map_loop(masks),
                               rtol=0, atol=0)


def test_clean_matches_sams_per_mask_reference(generator):
    from benchmarks.masks import realistic_masks

    masks, _ = realistic_masks(40, 60, 90, seed=2)
    holes = torch.rand(40, 60, 90, generator=torch.Generator().manual_seed(1)) < 0.01
    masks = masks ^ holes  # pinholes inside and specks outside every mask
    gen = SamMaskGenerator(generator.model, SamMaskConfig(min_mask_region_area=30))
    cleaned, changed = gen._clean(masks)
    for k in range(40):
        m, c1 = remove_small_regions(masks[k].numpy(), 30, "holes")
        m, c2 = remove_small_regions(m, 30, "islands")
        assert np.array_equal(cleaned[k].numpy(), m) and bool(changed[k]) == (c1 or c2)
    assert changed.all()


@pytest.mark.skipif(not CUDA, reason="needs CUDA and tiger's CUDA kernels")
def test_cuda_mask_path_equals_cpu(generator):
    """One whole image: SAM's predictions on CUDA agree with the CPU's, and every later stage
    (NMS, clean-up, id map) gives exactly the CPU result on the same predictions."""
    cfg = SamMaskConfig(points_per_side=8, pred_iou_thresh=-1e9, stability_score_thresh=0.0, mask_nms_score=-1e9,
                        min_mask_region_area=20, precision="fp32")
    cpu = SamMaskGenerator(generator.model, cfg)
    image = torch.rand(3, 96, 128, generator=torch.Generator().manual_seed(4))
    masks, iou, stab = cpu.predict(image)
    gpu = SamMaskGenerator(__import__("copy").deepcopy(generator.model).cuda(), cfg)
    g_masks, g_iou, g_stab = gpu.predict(image.cuda())
    assert g_masks.shape == masks.shape
    assert (g_masks.cpu() != masks).float().mean() < 1e-3  # only logits within rounding of 0 differ
    torch.testing.assert_close(g_iou.cpu(), iou, atol=1e-4, rtol=1e-4)
    from benchmarks.masks import _grow, realistic_masks

    many, scores = realistic_masks(150, 96, 128, seed=1)  # a SAM-like set: every stage has work to do
    many ^= _grow(many, 3) & (torch.rand(many.shape, generator=torch.Generator().manual_seed(2)) < 0.01)
    for m, i, s in [(masks, iou, stab), (many, scores, torch.full_like(scores, 0.9))]:
        ref = cpu.postprocess(m, i, s)
        out = gpu.postprocess(m.cuda(), i.cuda(), s.cuda())
        assert ref.masks.shape[0] >= 1
        assert torch.equal(out.masks.cpu(), ref.masks) and torch.equal(out.iou.cpu(), ref.iou)
        assert torch.equal(out.id_map().cpu(), ref.id_map())
    assert ref.masks.shape[0] > 10
    whole = gpu(image.cuda())  # the whole path on the device runs and obeys its filters
    assert whole.masks.device.type == "cuda" and (whole.masks.flatten(1).sum(1) >= 20).all()


def test_precision_resolves_per_device_and_bf16_runs_the_encoder_in_bfloat16(tiny_models):
    assert SamMaskConfig().resolved("cpu").precision == "fp32"
    assert SamMaskConfig().resolved("cuda").precision == "bf16"
    assert SamMaskConfig(precision="fp32").resolved("cuda").precision == "fp32"
    with pytest.raises(ValueError, match="precision must be one of"):
        SamMaskConfig(precision="fp16").resolved("cpu")
    cfg = SamMaskConfig(points_per_side=4, pred_iou_thresh=-1e9, stability_score_thresh=0.0)
    ref = SamMaskGenerator.from_pretrained(tiny_models / "sam-vit-huge", mask_config=cfg)
    assert ref.config.precision == "fp32" and ref.encoder_dtype == torch.float32
    bf = SamMaskGenerator.from_pretrained(tiny_models / "sam-vit-huge",
                                          mask_config=SamMaskConfig(**{**cfg.__dict__, "precision": "bf16"}))
    assert bf.encoder_dtype == torch.bfloat16 and bf.dtype == torch.float32 and bf.decoder.autocast
    image = torch.rand(3, 40, 56, generator=torch.Generator().manual_seed(3))
    emb, _ = bf.embed(image)
    emb_ref, _ = ref.embed(image)
    assert emb.dtype == torch.float32
    # bfloat16 keeps about 3 significant digits: the embeddings agree to that, not bit for bit
    assert (emb - emb_ref).norm() / emb_ref.norm() < 3e-2
    masks, iou, _ = bf.predict(image, (30, 42))
    assert masks.shape[1:] == (30, 42) and iou.dtype == torch.float32


@pytest.mark.skipif(not CUDA, reason="needs CUDA and tiger's CUDA kernels")
def test_cuda_default_precision_is_bf16(tiny_models):
    gen = SamMaskGenerator.from_pretrained(tiny_models / "sam-vit-huge", device="cuda")
    assert gen.config.precision == "bf16" and gen.encoder_dtype == torch.bfloat16 and gen.decoder.autocast
    out = gen(torch.rand(3, 96, 128, device="cuda", generator=None))
    assert out.masks.device.type == "cuda"

"""The RES models' numpy pre- and post-processing equals the transformers processors' own output
(their Pillow backends, transformers' reference implementations)."""

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from stages.models import res_processing as rp

PIL = pytest.importorskip("PIL.Image")
transformers = pytest.importorskip("transformers")

SHAPES = [(300, 400), (400, 300), (37, 61), (480, 640), (123, 1000), (720, 1280)]


def _img(h, w, seed=0):
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


@pytest.mark.parametrize("h,w", SHAPES + [(352, 352), (90, 90)])
@pytest.mark.parametrize("kind", ["bilinear", "bicubic"])
@pytest.mark.parametrize("target", [(352, 352), (600, 800), (57, 33)])
def test_pil_resize_is_bit_exact(h, w, kind, target):
    img = _img(h, w, h * w)
    res = {"bilinear": PIL.BILINEAR, "bicubic": PIL.BICUBIC}[kind]
    want = np.asarray(PIL.fromarray(img).resize((target[1], target[0]), res))
    assert np.array_equal(rp.pil_resize(img, target, kind), want)


@pytest.mark.parametrize("h,w", SHAPES)
@pytest.mark.parametrize("canvas", [(600, 800), (96, 128), (800, 600)])
def test_detector_inputs_equal_the_processor(h, w, canvas):
    """Fit into the fixed canvas and pad: size {"max_height", "max_width"} and pad_size."""
    proc = transformers.GroundingDinoImageProcessorPil(
        size={"max_height": canvas[0], "max_width": canvas[1]},
        pad_size={"height": canvas[0], "width": canvas[1]},
    )
    img = _img(h, w)
    want = proc(images=img, return_tensors="np")
    pixels, mask = rp.detector_inputs(img, canvas)
    assert pixels.shape == want["pixel_values"].shape == (1, 3, *canvas)
    assert np.abs(pixels - want["pixel_values"]).max() <= 1e-6
    assert np.array_equal(mask, want["pixel_mask"])


@pytest.mark.parametrize("threshold,k", [(0.3, 100), (0.5, 3), (0.1, 1)])
def test_detections_equal_the_processor(threshold, k):
    from transformers.models.grounding_dino.processing_grounding_dino import (
        GroundingDinoProcessor,
    )

    g = torch.Generator().manual_seed(0)
    q, n = 40, 9
    logits = torch.randn(1, q, n, generator=g) * 2
    padded = torch.full((1, q, 256), float("-inf"))
    padded[..., :n] = logits
    boxes = torch.rand(1, q, 4, generator=g) * 0.5 + 0.1
    ids = torch.tensor([[101, 1037, 2417, 3242, 1012, 1037, 2665, 1012, 102]])

    class Proc:  # the post-processing needs only batch_decode from the processor
        batch_decode = staticmethod(lambda label_ids: [list(map(int, x)) for x in label_ids])

    want = GroundingDinoProcessor.post_process_grounded_object_detection(
        Proc(),
        SimpleNamespace(logits=padded, pred_boxes=boxes, input_ids=ids),
        threshold=threshold,
        target_sizes=[(300, 400)],
    )[0]
    order = torch.argsort(want["scores"], descending=True, stable=True)[:k]
    b, s = rp.detections(logits[0].numpy(), boxes[0].numpy(), (300, 400), threshold, k)
    assert len(s) == len(order) > 0
    assert np.abs(s - want["scores"][order].numpy()).max() <= 1e-6
    assert np.abs(b - want["boxes"][order].numpy()).max() <= 1e-4
    assert np.all(np.diff(s) <= 0)


def test_detector_caption():
    assert rp.detector_caption(" The Red Chair ") == "the red chair."
    assert rp.detector_caption("a cat.") == "a cat."


@pytest.mark.parametrize("h,w", SHAPES)
@pytest.mark.parametrize("size", [1024, 512])
def test_sam_inputs_equal_the_processor(h, w, size):
    proc = transformers.SamImageProcessorPil(
        size={"longest_edge": size}, pad_size={"height": size, "width": size}
    )
    img = _img(h, w, 1)
    want = proc(images=img, return_tensors="np")
    assert tuple(want["reshaped_input_sizes"][0]) == rp.sam_shape(h, w, size)
    assert np.abs(rp.sam_inputs(img, size) - want["pixel_values"]).max() <= 1e-6


def test_sam_boxes_equal_the_processor():
    proc = transformers.SamProcessor(image_processor=transformers.SamImageProcessorPil())
    img = _img(300, 400)
    boxes = [[10.0, 20.0, 200.0, 250.0], [0.0, 0.0, 400.0, 300.0]]
    want = proc(images=img, input_boxes=[boxes], return_tensors="np")["input_boxes"]
    assert np.abs(rp.sam_boxes(np.asarray(boxes), (300, 400), 1024) - want).max() <= 1e-4


@pytest.mark.parametrize("h,w", [(300, 400), (400, 300), (37, 61), (720, 1280)])
def test_sam_masks_equal_the_processor(h, w):
    proc = transformers.SamImageProcessorPil()
    low = torch.randn(1, 2, 1, 256, 256, generator=torch.Generator().manual_seed(h)) * 4
    hw = rp.sam_shape(h, w, 1024)
    want = proc.post_process_masks([low[0]], [(h, w)], [hw], binarize=False)[0].numpy()
    got = rp.sam_mask_logits(low[0].numpy(), (h, w), 1024)
    assert np.abs(got - want).max() <= 1e-5  # measured 2.9e-6
    masks = proc.post_process_masks([low[0]], [(h, w)], [hw])[0].numpy()
    differ = (got > 0) != masks  # only where the logit is within float error of 0
    assert np.all(np.abs(want[differ]) < 1e-5)


@pytest.mark.parametrize("h,w", SHAPES)
def test_clipseg_inputs_equal_the_processor(h, w):
    """ViTImageProcessor as CIDAS/clipseg-rd64-refined's preprocessor_config.json sets it."""
    proc = transformers.ViTImageProcessorPil(
        size={"height": 352, "width": 352},
        resample=2,
        image_mean=list(rp.IMAGENET_MEAN),
        image_std=list(rp.IMAGENET_STD),
    )
    img = _img(h, w, 2)
    want = proc(images=img, return_tensors="np")["pixel_values"]
    got = rp.square_inputs(img, (352, 352), rp.IMAGENET_MEAN, rp.IMAGENET_STD)
    assert np.abs(got - want).max() <= 1e-6


def test_scores_to_mask_equals_torch_interpolation():
    probs = torch.randn(64, 64, generator=torch.Generator().manual_seed(0)).sigmoid()
    want = torch.nn.functional.interpolate(probs[None, None], (300, 400), mode="bilinear")[0, 0]
    got = rp.scores_to_mask(probs.numpy(), (300, 400), 0.4)
    differ = got != (want > 0.4).numpy()
    assert np.all(np.abs(want.numpy()[differ] - 0.4) < 1e-6)


@pytest.mark.parametrize("h,w", [(300, 400), (400, 300), (37, 61), (480, 640), (720, 1280)])
def test_sam_mask_logits_equal_the_plain_two_step_reference(h, w):
    """The composed per-axis matrices against the two resizes and the crop between them."""
    low = np.random.default_rng(h).standard_normal((3, 256, 256)).astype(np.float32) * 10
    want = rp.sam_mask_logits_reference(low, (h, w), 1024)
    got = rp.sam_mask_logits(low, (h, w), 1024)
    assert got.shape == want.shape == (3, h, w) and got.dtype == np.float32
    assert np.abs(got - want).max() <= 1e-5  # measured 2.9e-6 at magnitude 4


@pytest.mark.parametrize("h,w", [(48, 64), (70, 40), (300, 400), (1200, 900), (961, 1000)])
def test_owl_inputs_equal_the_processor(h, w):
    """Owlv2ImageProcessor's own resize (scipy: Gaussian anti-alias when shrinking, linear
    zoom) on the image padded with grey 0.5, as the original OWLv2 and transformers 4.x pad
    (transformers 5 pads with 0; goi keeps the original's grey)."""
    pytest.importorskip("scipy")
    proc = transformers.Owlv2ImageProcessorPil()
    rgb = np.random.default_rng(h + w).integers(0, 256, (h, w, 3), dtype=np.uint8)
    x = proc.rescale(rgb.transpose(2, 0, 1), 1 / 255)
    x = proc.pad(x, constant_value=0.5)
    x = proc.resize(x, {"height": 96, "width": 96})
    want = proc.normalize(x, rp.IMAGENET_MEAN, rp.IMAGENET_STD)
    got = rp.owl_inputs(rgb, 96, rp.IMAGENET_MEAN, rp.IMAGENET_STD)
    assert got.shape == (1, 3, 96, 96) and got.dtype == np.float32
    assert np.abs(got[0] - want).max() <= 1e-5
    ref = rp.owl_inputs_reference(rgb, 96, rp.IMAGENET_MEAN, rp.IMAGENET_STD)
    assert np.abs(got - ref).max() <= 5e-6

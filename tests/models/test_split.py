"""The RES split (docs/models.md): the image side computed once per image, then the prompt
side on it, gives what `Bundle.ground` gives on the image."""

import json
import shutil

import numpy as np
import pytest

from stages.core.errors import GoiError
from stages.models.bundle import load_bundle

pytest.importorskip("transformers")

PROMPTS = ["a red chair", "the green sofa"]


def _images():
    rng = np.random.default_rng(7)
    return [rng.integers(0, 256, s, dtype=np.uint8) for s in ((96, 128, 3), (130, 90, 3))]


def test_grounded_split_equals_ground(res_bundles):
    bundle = load_bundle(res_bundles["grounded"])
    assert bundle.res_indexable
    spec = bundle.res_image_side_spec()
    assert spec == {"sam_embedding": ((32, 8, 8), "float16")}
    for rgb in _images():
        side = bundle.res_image_side(rgb)
        assert {k: (v.shape, v.dtype.name) for k, v in side.items()} == spec
        exact = {k: v[0] for k, v in bundle._grounded.sam.embed(rgb).items()}  # float32
        for text in PROMPTS:
            prompt = bundle.res_prompt(text)
            want = bundle.ground(rgb, text)
            assert len(want.boxes) > 0 and 0 < want.mask.mean() < 1
            got = bundle.res_from_image_side(exact, rgb.shape[:2], prompt, rgb)
            assert np.array_equal(got.mask, want.mask)
            assert np.array_equal(got.boxes, want.boxes)
            assert np.array_equal(got.scores, want.scores)
            half = bundle.res_from_image_side(side, rgb.shape[:2], prompt, rgb)
            assert np.array_equal(half.boxes, want.boxes)
            assert (half.mask != want.mask).mean() < 2e-3  # float16: threshold pixels only


def test_grounded_split_refuses_a_foreign_image_side(res_bundles):
    bundle = load_bundle(res_bundles["grounded"])
    rgb = _images()[0]
    prompt = bundle.res_prompt("a red chair")
    with pytest.raises(GoiError, match="'sam_embedding' is missing"):
        bundle.res_from_image_side({}, rgb.shape[:2], prompt, rgb)
    bad = {"sam_embedding": np.zeros((32, 4, 4), np.float16)}
    with pytest.raises(GoiError, match=r"'sam_embedding' is \[32, 4, 4\], expected \[32, 8, 8\]"):
        bundle.res_from_image_side(bad, rgb.shape[:2], prompt, rgb)
    side = bundle.res_image_side(rgb)
    with pytest.raises(GoiError, match="rgb is needed"):
        bundle.res_from_image_side(side, rgb.shape[:2], prompt)


def test_no_box_gives_an_empty_mask_from_the_image_side(res_bundles, tmp_path):
    root = tmp_path / "b"
    shutil.copytree(res_bundles["grounded"], root)
    m = json.loads((root / "manifest.json").read_text())
    m["grounded"]["box_threshold"] = 0.99999
    (root / "manifest.json").write_text(json.dumps(m))
    bundle = load_bundle(root)
    rgb = _images()[0]
    got = bundle.res_from_image_side(
        bundle.res_image_side(rgb), rgb.shape[:2], bundle.res_prompt("a red chair"), rgb
    )
    assert len(got.boxes) == 0 and not got.mask.any() and got.mask.shape == rgb.shape[:2]


def test_a_whole_single_model_res_has_no_image_side(res_bundles):
    """CLIPSeg exported as one graph: nothing to cache; the prompt side runs it on the image."""
    bundle = load_bundle(res_bundles["clipseg"])
    assert not bundle.res_indexable and bundle.res_image_side_spec() == {}
    rgb = _images()[1]
    assert bundle.res_image_side(rgb) == {}
    got = bundle.res_from_image_side({}, rgb.shape[:2], bundle.res_prompt("the red sofa"), rgb)
    assert np.array_equal(got.mask, bundle.ground(rgb, "the red sofa").mask)

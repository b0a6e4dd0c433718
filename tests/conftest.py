"""Shared fixtures: the synthetic semantic scene taken through extract, init-codebook and
fit-field once per test session (the field and query tests both use it)."""

import pytest

from goi_cli.main import main
from stages.testing.models import GROUNDED  # the tiny Grounded-SAM bundle's settings
from tests.helpers import semantic_scene


@pytest.fixture(scope="session")
def fitted(tmp_path_factory):
    root = tmp_path_factory.mktemp("sem")
    s = semantic_scene(root)
    run = root / "run"
    run.mkdir()
    assert (
        main(
            [
                "extract",
                "--scene",
                str(s["scene"]),
                "--from",
                str(s["features"]),
                "--out",
                str(run / "features.h5"),
            ]
        )
        == 0
    )
    assert (
        main(
            [
                "init-codebook",
                "--features",
                str(run / "features.h5"),
                "--entries",
                "16",
                "--out",
                str(run / "codebook.h5"),
            ]
        )
        == 0
    )
    assert (
        main(
            [
                "fit-field",
                "--scene",
                str(s["scene"]),
                "--features",
                str(run / "features.h5"),
                "--codebook",
                str(run / "codebook.h5"),
                "--out",
                str(run / "field.h5"),
                "--iterations",
                "400",
                "--checkpoint-every",
                "0",
            ]
        )
        == 0
    )
    return s, run


@pytest.fixture(scope="session")
def res_checkpoints(tmp_path_factory):
    """Tiny random Grounding DINO, SAM (128 px) and CLIPSeg (64 px) checkpoints."""
    pytest.importorskip("transformers")
    from stages.testing.models import checkpoints

    return checkpoints(tmp_path_factory.mktemp("res_ckpt"))


@pytest.fixture(scope="session")
def res_bundles(res_checkpoints, tmp_path_factory):
    """The tiny checkpoints through `goi export-model`: {"grounded": dir, "clipseg": dir} (CLIPSeg
    as one graph; tests/models/test_clipseg_split.py exports the split)."""
    root = tmp_path_factory.mktemp("res_bundles")
    ck, g = res_checkpoints, GROUNDED
    argv = ["export-model", str(ck["detector"]), str(ck["sam"]), "--out", str(root / "grounded"),
            "--detector-height", str(g["canvas"][0]), "--detector-width", str(g["canvas"][1]),
            "--box-threshold", str(g["box_threshold"]),
            "--max-boxes", str(g["max_boxes"])]  # fmt: skip
    assert main(argv) == 0
    argv = ["export-model", str(ck["clipseg"]), "--out", str(root / "clipseg"), "--clipseg-whole"]
    assert main(argv) == 0
    return {"grounded": root / "grounded", "clipseg": root / "clipseg"}

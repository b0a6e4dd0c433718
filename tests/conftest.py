"""Shared fixtures: the synthetic semantic scene taken through extract, init-codebook and
fit-field once per test session (the field and query tests both use it)."""

import pytest

from goi_cli.main import main
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

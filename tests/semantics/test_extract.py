import os
import pickle

import numpy as np
import pytest
import torch

from goi_cli.main import main
from stages.scene.formats.inria import write_inria
from stages.semantics.features import load_features
from tests.helpers import front_camera, random_vertex, write_ply


@pytest.fixture
def scene(tmp_path):
    d = tmp_path / "scene"
    d.mkdir()
    write_ply(d / "point_cloud.ply", random_vertex(50))
    cams = [front_camera(40, 32, f"v{i}") for i in range(3)]
    write_inria(d / "cameras.json", cams)
    feats = tmp_path / "feats"
    feats.mkdir()
    rng = np.random.default_rng(0)
    for c in cams:
        np.save(feats / f"{c.name}.npy", rng.normal(size=(8, 10, 20)).astype(np.float16))
    return d, feats


def _run(capsys, *args):
    code = main([str(a) for a in args])
    err = capsys.readouterr().err
    return code, err


def _codebook(capsys, features, out, *options) -> bool:
    """goi init-codebook succeeded."""
    return _run(capsys, "init-codebook", "--features", features, *options, "--out", out)[0] == 0


def test_npy_and_pt_import_the_same_maps(scene, tmp_path, capsys):
    d, feats = scene
    pt = tmp_path / "pt"
    pt.mkdir()
    for f in feats.iterdir():
        torch.save(torch.from_numpy(np.load(f)), pt / f"{f.stem}.pt")
    assert (
        _run(capsys, "extract", "--scene", d, "--from", feats, "--out", tmp_path / "a.h5")[0] == 0
    )
    assert _run(capsys, "extract", "--scene", d, "--from", pt, "--out", tmp_path / "b.h5")[0] == 0
    a, b = load_features(tmp_path / "a.h5"), load_features(tmp_path / "b.h5")
    assert a.views == ["v0", "v1", "v2"] and a.dim == 8
    np.testing.assert_array_equal(a.maps["v1"], b.maps["v1"])
    assert a.maps["v1"].shape == (10, 20, 8)


def test_large_maps_are_area_downsampled(scene, tmp_path, capsys):
    d, feats = scene
    code, _ = _run(
        capsys,
        "extract",
        "--scene",
        d,
        "--from",
        feats,
        "--out",
        tmp_path / "a.h5",
        "--max-side",
        "10",
    )
    assert code == 0
    assert load_features(tmp_path / "a.h5").maps["v0"].shape == (5, 10, 8)


def _expect_refused(capsys, tmp_path, args, *words):
    out = tmp_path / "out.h5"
    code, err = _run(capsys, *args, "--out", out)
    assert code == 2, err
    assert err.count("\n") == 1 and "Traceback" not in err
    for w in words:
        assert w in err, err
    assert not out.exists()


def test_missing_and_foreign_feature_files(scene, tmp_path, capsys):
    d, feats = scene
    os.remove(feats / "v1.npy")
    _expect_refused(capsys, tmp_path, ["extract", "--scene", d, "--from", feats], "v1")
    for f in feats.iterdir():
        f.rename(feats / f"other_{f.name}")
    _expect_refused(
        capsys, tmp_path, ["extract", "--scene", d, "--from", feats], "belong to this scene"
    )


def test_wrong_dimension_rank_and_nan(scene, tmp_path, capsys):
    d, feats = scene
    np.save(feats / "v2.npy", np.zeros((9, 10, 20), np.float16))
    _expect_refused(
        capsys, tmp_path, ["extract", "--scene", d, "--from", feats], "dimension 9", "v2"
    )
    np.save(feats / "v2.npy", np.zeros((10, 20), np.float16))
    _expect_refused(
        capsys, tmp_path, ["extract", "--scene", d, "--from", feats], "v2.npy", "expected [D, h, w]"
    )
    bad = np.zeros((8, 10, 20), np.float32)
    bad[0, 1, 2] = np.nan
    np.save(feats / "v2.npy", bad)
    _expect_refused(capsys, tmp_path, ["extract", "--scene", d, "--from", feats], "v2.npy", "NaN")


class _Exploit:
    def __reduce__(self):
        return (os.system, ("touch PWNED",))


def test_a_pickled_object_is_refused_and_never_runs(scene, tmp_path, capsys, monkeypatch):
    d, feats = scene
    monkeypatch.chdir(tmp_path)
    for f in feats.iterdir():
        torch.save(torch.from_numpy(np.load(f)), feats / f"{f.stem}.pt")
        f.unlink()
    with open(feats / "v1.pt", "wb") as fh:
        pickle.dump(_Exploit(), fh)
    _expect_refused(
        capsys, tmp_path, ["extract", "--scene", d, "--from", feats], "v1.pt", "refused"
    )
    assert not (tmp_path / "PWNED").exists()


def test_codebook_of_another_dimension_is_refused(scene, tmp_path, capsys):
    d, feats = scene
    assert (
        _run(capsys, "extract", "--scene", d, "--from", feats, "--out", tmp_path / "f.h5")[0] == 0
    )
    assert _codebook(capsys, tmp_path / "f.h5", tmp_path / "c.h5", "--entries", 4, "--samples", 500)
    for f in feats.iterdir():
        np.save(f, np.ones((6, 10, 20), np.float16))
    assert (
        _run(capsys, "extract", "--scene", d, "--from", feats, "--out", tmp_path / "g.h5")[0] == 0
    )
    _expect_refused(
        capsys,
        tmp_path,
        [
            "fit-field",
            "--scene",
            d,
            "--features",
            tmp_path / "g.h5",
            "--codebook",
            tmp_path / "c.h5",
        ],
        "c.h5",
        "dimension 8",
        "have 6",
    )


def test_codebook_is_deterministic_and_spherical(scene, tmp_path, capsys):
    d, feats = scene
    _run(capsys, "extract", "--scene", d, "--from", feats, "--out", tmp_path / "f.h5")
    for name in ("a", "b"):
        assert _codebook(
            capsys, tmp_path / "f.h5", tmp_path / f"{name}.h5", "--entries", 5, "--seed", 3
        )
    from stages.semantics.codebook import load_codebook

    a, b = load_codebook(tmp_path / "a.h5"), load_codebook(tmp_path / "b.h5")
    np.testing.assert_array_equal(a, b)
    np.testing.assert_allclose(np.linalg.norm(a, axis=1), 1, atol=1e-5)

"""The fit's memory budget: the blend cache streamed from disk when it does not fit, a budget
too small refused before any work, and a cut-off cache build resumed."""

import h5py
import numpy as np
import pytest

import stages.semantics.blend_cache as bc
from stages.core.errors import GoiError
from stages.core.report import Lines
from stages.scene.scene import load_scene
from stages.semantics.codebook import CodebookParams, CodebookRun, init_codebook
from stages.semantics.extract import ExtractParams, ExtractRun, import_features
from stages.semantics.features import feature_grid, feature_views
from stages.semantics.field import load_field
from stages.semantics.field_params import FieldParams, FieldRun
from stages.semantics.fit_field import fit_field
from stages.semantics.memory import GIB, working_set
from tests.helpers import semantic_scene


class Log(Lines):
    def __init__(self) -> None:
        self.lines: list[str] = []
        super().__init__(write=self.lines.append)


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("mem")
    s = semantic_scene(tmp, n=3000, n_views=6, size=(48, 36))
    scene = load_scene(s["scene"])
    feats = import_features(scene, s["features"], ExtractParams(), ExtractRun(tmp / "f.h5"))
    cb = init_codebook(feats, CodebookParams(entries=8), CodebookRun(tmp / "c.h5"))
    return tmp, scene, feats, cb, s["scene"]


P = FieldParams(iterations=30, cells_per_view=64, views_per_step=2)


def test_a_streamed_cache_gives_the_same_field_bit_for_bit(world, tmp_path):
    _, scene, feats, cb, _ = world
    fit_field(scene, feats, cb, P, FieldRun(tmp_path / "mem.h5", cache=tmp_path / "c.h5"))
    train = scene.views("train")
    views = [c.name for c in train]
    dim, _ = feature_views(feats)
    need = working_set(scene.gaussians.count, scene, train, feature_grid(feats, views), dim, 8, P)
    cache = sum(bc.cache_nbytes(tmp_path / "c.h5", views).values())
    log = Log()
    budget = (need + cache * 0.8) / GIB  # the rest and a step's views fit, not all
    run = FieldRun(tmp_path / "stream.h5", cache=tmp_path / "c.h5", max_memory_gib=budget)
    fit_field(scene, feats, cb, P, run, log)
    assert any("streaming the blend cache" in line for line in log.lines)
    a, b = load_field(tmp_path / "mem.h5"), load_field(tmp_path / "stream.h5")
    assert np.array_equal(a.features, b.features) and np.array_equal(a.codebook, b.codebook)


def test_a_budget_below_the_working_set_is_refused_before_any_work(world, tmp_path):
    _, scene, feats, cb, _ = world
    run = FieldRun(tmp_path / "f.h5", cache=tmp_path / "c.h5", max_memory_gib=1e-4)
    with pytest.raises(GoiError, match=r"--max-memory-gib: the fit needs at least"):
        fit_field(scene, feats, cb, P, run)
    assert list(tmp_path.iterdir()) == []


def test_a_cut_off_cache_build_resumes_with_the_views_it_finished(world, tmp_path, monkeypatch):
    _, scene, feats, _, _ = world
    train = scene.views("train")
    sizes = feature_grid(feats, [c.name for c in train])
    real = bc.view_weights
    calls = {"n": 0}

    def cut(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == len(train):  # the last view
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(bc, "view_weights", cut)
    with pytest.raises(KeyboardInterrupt):
        bc.ensure_cache(tmp_path / "c.h5", scene, train, 0, sizes)
    partial = tmp_path / "c.h5.partial"
    assert not (tmp_path / "c.h5").exists() and partial.is_file()
    with h5py.File(partial) as f:
        assert len(f["views"]) == len(train) - 1 >= 2
    monkeypatch.setattr(bc, "view_weights", real)
    log = Log()
    bc.ensure_cache(tmp_path / "c.h5", scene, train, 0, sizes, log)
    assert any("resuming" in line and f"{len(train) - 1} views done" in line for line in log.lines)
    assert not partial.exists()
    whole = bc.ensure_cache(tmp_path / "whole.h5", scene, train, 0, sizes)
    resumed, fresh = bc.BlendCache.load(tmp_path / "c.h5"), bc.BlendCache.load(whole)
    assert list(resumed.views) == list(fresh.views) == [c.name for c in train]
    for v in fresh.views:
        for arr in ("indptr", "indices", "weights"):
            assert np.array_equal(getattr(resumed.views[v], arr), getattr(fresh.views[v], arr))


def test_the_cli_names_the_option_and_the_size_needed(world, tmp_path, capsys):
    from goi_cli.main import main

    _, _, feats, cb, root = world
    args = ["fit-field", "--scene", str(root), "--features", str(feats)]
    args += ["--codebook", str(cb), "--out", str(tmp_path / "f.h5"), "--max-memory-gib", "0.001"]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("goi: error: --max-memory-gib: the fit needs")
    assert "MiB" in err[0] and "0.00 GiB" not in err[0]  # a small fit's sizes, readable
    assert list(tmp_path.iterdir()) == []


def test_float16_targets_divided_by_their_norms_are_the_unit_features(world):
    import torch

    from stages.core.arrays import unit_norms
    from stages.semantics.features import load_features

    _, _, feats, _, _ = world
    unit, raw = load_features(feats), load_features(feats, unit=False)
    for v, m in raw.maps.items():
        assert m.dtype == np.float16
        cells = m.reshape(-1, raw.dim)
        v_gt = (
            torch.from_numpy(cells)
            .float()
            .div_(torch.from_numpy(unit_norms(cells.astype(np.float32)))[:, None])
        )
        assert np.array_equal(v_gt.numpy(), unit.maps[v].reshape(-1, raw.dim))

import h5py
import numpy as np
import pytest

from goi_cli.main import main
from stages.render.rasterizer import Rasterizer
from stages.scene.gaussians import load_ply
from stages.semantics.field import load_field
from tests.helpers import semantic_scene


@pytest.mark.slow
def test_held_out_views_decode_to_each_objects_feature(fitted):
    s, run = fitted
    field = load_field(run / "field.h5")
    rast = Rasterizer.from_gaussians(load_ply(s["scene"] / "point_cloud.ply"))
    table = field.unit_codebook()
    good = total = 0
    for name in s["test"]:
        cam = s["cameras"][name]
        f_hat = rast.render_features(cam, field.features).image.reshape(-1, field.features.shape[1])
        share = rast.render_features(cam, s["onehot"]).image.reshape(-1, s["onehot"].shape[1])
        covered = share.sum(1) > 0.5
        truth = s["objects"][share.argmax(1)]
        cos = (table[field.decode_index(f_hat)] * truth).sum(1)
        good += int((cos[covered] >= 0.9).sum())
        total += int(covered.sum())
    assert total > 0.8 * len(s["test"]) * 128 * 96
    assert good / total >= 0.95, good / total


@pytest.mark.slow
def test_the_loss_decreases_and_the_field_describes_itself(fitted):
    _, run = fitted
    with h5py.File(run / "field.h5") as f:
        curve = f["loss_curve"][()]
        assert f.attrs["schema"] == "goi.field" and f.attrs["iterations"] == 400
        assert f["features"].shape[1] == 10 and f["codebook"].shape == (16, 32)
    assert curve.shape == (400, 5)
    assert curve[-50:, 0].mean() < 0.8 * curve[:10, 0].mean()
    assert (
        main(
            [
                "inspect",
                str(run / "field.h5"),
                str(run / "codebook.h5"),
                str(run / "features.h5"),
                str(run / "blend_cache.h5"),
            ]
        )
        == 0
    )


@pytest.mark.parametrize("reference_losses", [False, True])
def test_resume_after_an_interruption_gives_the_uninterrupted_result(
    tmp_path, monkeypatch, reference_losses
):
    """Both paths (the fused default and the paper's formulation) resume bit for bit; the
    checkpoint holds the features and their Adam moments in PLY order, whatever order the fit
    keeps them in."""
    import stages.semantics.fit_field as field_mod
    from stages.scene.scene import load_scene
    from stages.semantics.codebook import CodebookParams, CodebookRun, init_codebook
    from stages.semantics.extract import ExtractParams, ExtractRun, import_features
    from stages.semantics.field_params import FieldParams, FieldRun
    from stages.semantics.fit_field import fit_field

    s = semantic_scene(tmp_path, n=3000, n_views=6, size=(48, 36))
    scene = load_scene(s["scene"])
    feats = import_features(scene, s["features"], ExtractParams(), ExtractRun(tmp_path / "f.h5"))
    cb = init_codebook(feats, CodebookParams(entries=8), CodebookRun(tmp_path / "c.h5"))

    def fit(out, resume=False, seed=0):
        p = FieldParams(
            iterations=60, cells_per_view=64, seed=seed, reference_losses=reference_losses
        )
        run = FieldRun(tmp_path / out, checkpoint_every=20, resume=resume)
        return fit_field(scene, feats, cb, p, run)

    fit("a.h5")
    real = field_mod.field_losses
    calls = {"n": 0}

    def interrupted(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 47:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(field_mod, "field_losses", interrupted)
    with pytest.raises(KeyboardInterrupt):
        fit("b.h5")
    monkeypatch.setattr(field_mod, "field_losses", real)
    assert not (tmp_path / "b.h5").exists() and (tmp_path / "b.h5.ckpt").exists()
    with h5py.File(tmp_path / "b.h5.ckpt") as f:
        assert f.attrs["iteration"] == 40
    fit("b.h5", resume=True)
    assert not (tmp_path / "b.h5.ckpt").exists()
    a, b = load_field(tmp_path / "a.h5"), load_field(tmp_path / "b.h5")
    np.testing.assert_array_equal(a.features, b.features)
    np.testing.assert_array_equal(a.codebook, b.codebook)
    # Resuming with other options is refused, naming the checkpoint.
    from stages.core.errors import GoiError

    calls["n"] = 0
    monkeypatch.setattr(field_mod, "field_losses", interrupted)
    with pytest.raises(KeyboardInterrupt):
        fit("d.h5")
    monkeypatch.setattr(field_mod, "field_losses", real)
    with pytest.raises(GoiError, match=r"d.h5.ckpt: checkpoint was made with other fit-field"):
        fit("d.h5", resume=True, seed=5)

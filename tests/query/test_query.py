"""The query half on the synthetic scene: hyperplane, masks, 3D selection, PLY export."""

import json

import cv2
import h5py
import numpy as np
import pytest

from goi_cli.main import main
from stages.query.selection import load_selection
from stages.render.rasterizer import Rasterizer
from stages.scene.gaussians import load_ply
from stages.semantics.field import load_field
from tests.helpers import write_true_res

OBJ = 2  # a box standing on the floor


@pytest.fixture(scope="module")
def queried(fitted, tmp_path_factory):
    """Text embeddings = the objects' features; RES masks = each object's true train masks."""
    s, run = fitted
    root = tmp_path_factory.mktemp("query")
    write_true_res(s, root, range(len(s["objects"])))
    return s, run, root


def _query(s, run, root, k, *extra):
    return main(
        [
            "query", "--scene", str(s["scene"]), "--field", str(run / "field.h5"),
            "--prompt", f"object {k}", "--text-embeddings", str(root / "text.json"),
            "--res-masks", str(root / "res"), "--prompt-id", f"o{k}",
            "--out", str(root / "out"), *extra,
        ]
    )  # fmt: skip


def _selection(root, k):
    from stages.query.prompts import safe_name

    return load_selection(root / "out" / safe_name(f"object {k}") / "selection.h5")


@pytest.mark.slow
def test_selected_gaussians_match_the_object(queried):
    """3D IoU weighted by how much each Gaussian makes of the training images: a Gaussian
    hidden behind others (a box's underside) is neither rewarded nor punished."""
    s, run, root = queried
    rast = Rasterizer.from_gaussians(load_ply(s["scene"] / "point_cloud.ply"))
    w = sum(rast.contribution(s["cameras"][n]) for n in s["train"])
    ids = s["onehot"].argmax(1)
    for k in (1, 2, 3, 4):
        assert _query(s, run, root, k) == 0
        sel = _selection(root, k).selected
        truth = ids == k
        iou = w[sel & truth].sum() / w[sel | truth].sum()
        assert iou >= 0.9, (k, iou)


@pytest.mark.slow
def test_a_cached_prompt_is_not_refitted(queried, capsys):
    s, run, root = queried
    assert _query(s, run, root, OBJ) == 0
    capsys.readouterr()
    with h5py.File(root / "out" / "hyperplanes.h5") as f:
        before = {k: f["prompts"][k]["W"][()].copy() for k in f["prompts"]}
    assert _query(s, run, root, OBJ) == 0
    assert "(cached)" in capsys.readouterr().out
    with h5py.File(root / "out" / "hyperplanes.h5") as f:
        assert set(f["prompts"]) == set(before)
        for k, w in before.items():
            np.testing.assert_array_equal(f["prompts"][k]["W"][()], w)


@pytest.mark.slow
def test_the_hyperplane_beats_a_wrong_threshold(queried):
    """With the threshold set far too low, the fixed cut selects much of the scene; fitting the
    plane from there against the RES masks recovers the object."""
    s, run, root = queried
    rast = Rasterizer.from_gaussians(load_ply(s["scene"] / "point_cloud.ply"))
    w = sum(rast.contribution(s["cameras"][n]) for n in s["train"])
    truth = s["onehot"].argmax(1) == OBJ

    def iou(sel):
        return w[sel & truth].sum() / w[sel | truth].sum()

    args = ["--threshold", "-0.2", "--out", str(root / "wrong")]
    assert _query(s, run, root, OBJ, "--mode", "threshold", *args) == 0
    fixed = iou(_selection_in(root / "wrong", OBJ, "threshold"))
    assert _query(s, run, root, OBJ, "--mode", "hyperplane", *args) == 0
    fitted = iou(_selection_in(root / "wrong", OBJ, "hyperplane"))
    assert fixed < 0.5 and fitted >= 0.9, (fixed, fitted)


def _selection_in(out, k, mode):
    from stages.query.prompts import safe_name

    sel = load_selection(out / safe_name(f"object {k}") / "selection.h5")
    assert sel.mode == mode
    return sel.selected


@pytest.mark.slow
def test_exported_plys_load_back_with_identical_values(queried, tmp_path):
    s, run, root = queried
    assert _query(s, run, root, OBJ) == 0
    from stages.query.prompts import safe_name

    sel_path = root / "out" / safe_name(f"object {OBJ}") / "selection.h5"
    sel = load_selection(sel_path).selected
    src = load_ply(s["scene"] / "point_cloud.ply").vertex
    base = ["export-ply", "--scene", str(s["scene"]), "--selection", str(sel_path)]

    def export(name, *extra):
        assert main([*base, "--out", str(tmp_path / name), *extra]) == 0
        return load_ply(tmp_path / name).vertex

    sub = export("subset.ply")
    assert len(sub) == sel.sum() and sub.tobytes() == src[sel].tobytes()
    inv = export("invert.ply", "--invert")
    assert inv.tobytes() == src[~sel].tobytes()
    hi = export("hi.ply", "--highlight", "#00ff00")
    assert hi[~sel].tobytes() == src[~sel].tobytes()
    np.testing.assert_allclose(0.5 + 0.28209479177387814 * hi["f_dc_1"][sel], 1.0, atol=1e-6)
    mv = export("mv.ply", "--translate", "0.5,0,-1")
    np.testing.assert_allclose(mv["x"][sel], src["x"][sel] + 0.5, atol=1e-6)
    np.testing.assert_array_equal(mv["y"], src["y"])
    sem = export("sem.ply", "--semantics", "--field", str(run / "field.h5"))
    field = load_field(run / "field.h5")
    np.testing.assert_array_equal(sem["sem_3"], field.features[sel, 3])
    assert main([*base, "--out", str(tmp_path / "x.ply"), "--translate", "1,2"]) == 2
    assert main([*base, "--out", str(tmp_path / "x.ply"), "--invert", "--highlight", "red"]) == 2
    assert not (tmp_path / "x.ply").exists()


@pytest.mark.slow
def test_lifted_query_select_render_mask_and_fit_hyperplane(queried, tmp_path):
    """--lift on query, select, render-mask and fit-hyperplane: the selection records the views
    and evidence, its masks are the selection seen from the view, and it finds the object."""
    s, run, root = queried
    rast = Rasterizer.from_gaussians(load_ply(s["scene"] / "point_cloud.ply"))
    w = sum(rast.contribution(s["cameras"][n]) for n in s["train"])
    truth = s["onehot"].argmax(1) == OBJ
    out = tmp_path / "lifted"
    assert _query(s, run, root, OBJ, "--lift", "--out", str(out)) == 0
    sel = _selection_in(out, OBJ, "lifted")
    assert w[sel & truth].sum() / w[sel | truth].sum() >= 0.9
    from stages.query.prompts import safe_name

    art = load_selection(out / safe_name(f"object {OBJ}") / "selection.h5")
    assert art.lifted is not None and art.lifted["views"] == s["train"]
    assert art.lifted["chosen_by"] == "all mask files"
    assert "guard" in art.lifted["fusion"]  # what the guard weighed (null: it did not look)
    assert isinstance(art.lifted["fusion"]["core_kin_gaussians"], int)  # goi.selection 1.5
    assert art.lifted["clean"]["rule"] == "far_piece"  # goi.selection 1.6
    with h5py.File(out / safe_name(f"object {OBJ}") / "selection.h5") as f:
        assert f.attrs["schema_version"] == "1.8"
        assert f["lifted/S1"].shape == sel.shape
    common = [
        "--scene", str(s["scene"]), "--field", str(run / "field.h5"), "--prompt", f"object {OBJ}",
        "--text-embeddings", str(root / "text.json"), "--res-masks", str(root / "res"),
        "--prompt-id", f"o{OBJ}", "--lift",
    ]  # fmt: skip
    assert main(["select", *common, "--res-views", "2", "--out", str(tmp_path / "s.h5")]) == 0
    two = load_selection(tmp_path / "s.h5")
    assert len(two.lifted["views"]) == 2 and two.mode == "lifted"
    assert main(["render-mask", *common, "--out", str(tmp_path / "m"), "--no-overlay"]) == 0
    test_view = s["test"][0]
    m = cv2.imread(str(tmp_path / "m" / f"{test_view}.png"), cv2.IMREAD_GRAYSCALE) > 0
    proj, bins = rast.prepare(s["cameras"][test_view])
    from stages.render.lift import selection_mask

    cam = s["cameras"][test_view]
    assert np.array_equal(m, selection_mask(proj, bins, sel, cam.width, cam.height))
    hp = tmp_path / "hp.h5"
    assert main(["fit-hyperplane", *common, "--out", str(hp)]) == 0
    with h5py.File(hp) as f:
        assert json.loads(f["prompts"][safe_name(f"object {OBJ}")].attrs["views"]) == s["train"]
    # bad inputs: K beyond the training views; masks for none of the views; nothing written
    assert main(["select", *common, "--res-views", "99", "--out", str(tmp_path / "x.h5")]) == 2
    empty = tmp_path / "res_none" / f"o{OBJ}"
    empty.mkdir(parents=True)
    cv2.imwrite(str(empty / "not_a_view.png"), np.zeros((8, 8), np.uint8))
    bad = [a if a != str(root / "res") else str(empty.parent) for a in common]
    assert main(["select", *bad, "--out", str(tmp_path / "x.h5")]) == 2
    assert not (tmp_path / "x.h5").exists()
    assert main(["select", *common[:-1], "--out", str(tmp_path / "x.h5")]) == 2  # no plane


@pytest.fixture(scope="module")
def unfitted(tmp_path_factory):
    """A scene and each object's true RES masks on the training views, and no field."""
    from tests.helpers import semantic_scene

    root = tmp_path_factory.mktemp("fieldfree")
    s = semantic_scene(root, n=6000, n_views=8, size=(64, 48), dim=8)
    rast = Rasterizer.from_gaussians(load_ply(s["scene"] / "point_cloud.ply"))
    d = root / "res" / f"o{OBJ}"
    d.mkdir(parents=True)
    for name in s["train"]:
        share = rast.render_features(s["cameras"][name], s["onehot"]).image
        m = (share.argmax(2) == OBJ) & (share.sum(2) > 0.5)
        cv2.imwrite(str(d / f"{name}.png"), m.astype(np.uint8) * 255)
    return s, root, rast


def test_field_free_lifted_query_select_and_render_mask(unfitted, tmp_path):
    """--lift with RES masks and no --field: no feature model, codebook, field or text
    embedding; the selection records that no field took part and finds the object as the
    views see it. Without --lift (or without a RES source) --field is asked for."""
    s, root, rast = unfitted
    from stages.query.prompts import safe_name
    from stages.render.lift import selection_mask

    common = [
        "--scene", str(s["scene"]), "--prompt", f"object {OBJ}",
        "--res-masks", str(root / "res"), "--prompt-id", f"o{OBJ}",
    ]  # fmt: skip
    out = tmp_path / "q"
    assert main(["query", *common, "--lift", "--out", str(out)]) == 0
    art = load_selection(out / safe_name(f"object {OBJ}") / "selection.h5")
    assert art.mode == "lifted" and art.lifted["semantics"] == "none (field-free)"
    assert art.lifted["views"] == s["train"]
    with h5py.File(out / safe_name(f"object {OBJ}") / "selection.h5") as f:
        assert "field" not in json.loads(f.attrs["inputs"])
    truth = s["onehot"].argmax(1) == OBJ
    w = sum(rast.contribution(s["cameras"][n]) for n in s["train"])
    sel = art.selected
    assert w[sel & truth].sum() / w[sel | truth].sum() >= 0.9
    assert main(["select", *common, "--lift", "--out", str(tmp_path / "s.h5")]) == 0
    assert np.array_equal(load_selection(tmp_path / "s.h5").selected, sel)
    m_dir = tmp_path / "m"
    assert main(["render-mask", *common, "--lift", "--out", str(m_dir), "--no-overlay"]) == 0
    cam = s["cameras"][s["test"][0]]
    m = cv2.imread(str(m_dir / f"{cam.name}.png"), cv2.IMREAD_GRAYSCALE) > 0
    proj, bins = rast.prepare(cam)
    assert np.array_equal(m, selection_mask(proj, bins, sel, cam.width, cam.height))
    # without --lift, or without RES masks, there is nothing to answer from
    assert main(["select", *common, "--out", str(tmp_path / "x.h5")]) == 2
    no_res = [a for a in common[:4]]
    assert main(["query", *no_res, "--lift", "--out", str(tmp_path / "x")]) == 2
    assert main(["fit-hyperplane", *common, "--lift", "--out", str(tmp_path / "x.h5")]) == 2
    assert not (tmp_path / "x.h5").exists() and not (tmp_path / "x").exists()


@pytest.mark.slow
def test_a_res_that_finds_nothing_gives_an_empty_answer(queried, tmp_path, capsys):
    """Every RES mask empty: goi query answers with empty masks and selection and a warning
    (the paper's mode and --lift), not an error."""
    s, run, root = queried
    empty = tmp_path / "res" / "o9"
    empty.mkdir(parents=True)
    for name in s["train"]:
        cv2.imwrite(str(empty / f"{name}.png"), np.zeros((96, 128), np.uint8))
    for extra in ([], ["--lift"]):
        out = tmp_path / f"q{len(extra)}"
        capsys.readouterr()
        argv = ["query", "--scene", str(s["scene"]), "--field", str(run / "field.h5"),
                "--prompt", f"object {OBJ}", "--text-embeddings", str(root / "text.json"),
                "--res-masks", str(tmp_path / "res"), "--prompt-id", "o9", "--out", str(out),
                *extra]  # fmt: skip
        assert main(argv) == 0
        assert "the answer is empty" in capsys.readouterr().err
        from stages.query.prompts import safe_name

        pdir = out / safe_name(f"object {OBJ}")
        assert not load_selection(pdir / "selection.h5").selected.any()
        m = cv2.imread(str(pdir / "masks" / f"{s['test'][0]}.png"), cv2.IMREAD_GRAYSCALE)
        assert m is not None and not m.any()

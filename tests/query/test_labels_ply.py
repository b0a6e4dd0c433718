"""Named selections as labels in the scene's PLY (goi export-ply --labels, schema
goi.labels_ply): round trip, the overlap rule, refusals, and the readers that must still read
the file (goi's own as a scene, INRIA's property rules, PlayCanvas's splat-transform)."""

import json
import subprocess

import cv2
import h5py
import numpy as np
import plyfile
import pytest

from goi_cli.main import main
from stages.core.artifacts import sha256_file
from stages.core.errors import GoiError
from stages.query.ply_labels import (
    LabelLayer,
    assign,
    read_labels,
    write_labels_ply,
)
from stages.query.selection import load_selection, write_selection
from stages.render.rasterizer import Rasterizer
from stages.scene.formats.inria import write_inria
from stages.scene.gaussians import REQUIRED, load_ply, save_ply
from stages.testing.synthetic import ring_cameras, room_vertex
from tests.helpers import write_ply

N_OBJ = 4


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    """A small room (4 boxes) as a scene directory, with each box's true mask on the
    training views as RES mask files (res/o<k>/<view>.png)."""
    root = tmp_path_factory.mktemp("labels")
    scene = root / "scene"
    scene.mkdir()
    v, ids = room_vertex(6000, seed=3, n_objects=N_OBJ)
    write_ply(scene / "point_cloud.ply", v)
    cams = ring_cameras(8, 64, 48, radius=1.9, height_m=1.5)
    write_inria(scene / "cameras.json", cams)
    train = [c.name for c in cams[0::2]]
    (scene / "split.json").write_text(
        json.dumps({"train": train, "test": [c.name for c in cams[1::2]]})
    )
    g = load_ply(scene / "point_cloud.ply")
    rast = Rasterizer.from_gaussians(g)
    onehot = np.eye(N_OBJ + 1, dtype=np.float32)[ids]
    for k in (1, 2):
        d = root / "res" / f"o{k}"
        d.mkdir(parents=True)
        for c in cams[0::2]:
            share = rast.render_features(c, onehot).image
            m = (share.argmax(2) == k) & (share.sum(2) > 0.5)
            cv2.imwrite(str(d / f"{c.name}.png"), m.astype(np.uint8) * 255)
    return {"root": root, "scene": scene, "ids": ids, "g": g, "sha": sha256_file(g.path)}


def _selection(room, path, selected, evidence=None, min_evidence=1.0, ply_sha=None):
    lifted = None if evidence is None else {"params": {"min_evidence": min_evidence}}
    return write_selection(
        path, selected, path.stem, "lifted" if lifted else "threshold",
        ply_sha or room["sha"], {"ply": room["sha"]}, force=True, lifted=lifted,
        evidence=evidence,
    )  # fmt: skip


def _export(room, out, *labels, extra=()):
    args = ["export-ply", "--scene", str(room["scene"]), "--out", str(out)]
    for spec in labels:
        args += ["--labels", spec]
    return main([*args, *extra])


def test_three_selections_round_trip(room, tmp_path, capsys):
    """Two hand selections (score 1) and a lifted one (score = its vote share where its
    evidence reaches min_evidence, else 1) come back as written, names and all; the scene's
    Gaussians are written unchanged, its properties first."""
    ids = room["ids"]
    a = _selection(room, tmp_path / "a.h5", ids == 1)
    b = _selection(room, tmp_path / "b.h5", ids == 2)
    S1 = np.where(ids == 3, 3.0, 0.0)
    S0 = np.where(ids == 3, 2.0, 0.5)
    S1[ids == 3] *= np.linspace(0, 1, int((ids == 3).sum()))  # shares 0 .. 0.6
    S0[np.flatnonzero(ids == 3)[:10]] = 0.0  # some with little evidence: E < 1.5
    c = _selection(room, tmp_path / "c.h5", ids == 3, (S1, S0), min_evidence=1.5)
    out = tmp_path / "scene.labels.ply"
    names = ["box", "teddy bear on the sofa", 'caf\u00e9 "x"']
    assert _export(room, out, f"{names[0]}={a}", f"{names[1]}={b}", f"{names[2]}={c}") == 0
    printed = capsys.readouterr().out
    assert "labels 1 'box' 300, 2 'teddy bear on the sofa' 300" in printed
    assert f"; {((ids == 0) | (ids == 4)).sum()} in none" in printed
    lab = read_labels(out)
    assert lab.names == names and lab.version == "1.0"
    assert lab.overlap == "higher-score-then-first"
    np.testing.assert_array_equal(lab.label, np.where(ids <= 3, ids, 0))  # label i: box i
    E = S1 + S0
    want = np.where(ids == 3, np.where(E >= 1.5, S1 / np.maximum(E, 1e-12), 1.0), 0.0)
    want[(ids == 1) | (ids == 2)] = 1.0
    np.testing.assert_allclose(lab.score, want, atol=1e-6)
    assert lab.score[ids == 3].min() < 0.1 and lab.score[ids == 3].max() == 1.0
    assert lab.provenance["inputs"] == {
        "ply": room["sha"],
        "label 1": sha256_file(a),
        "label 2": sha256_file(b),
        "label 3": sha256_file(c),
    }
    # every property of the scene, unchanged and first, then label and score
    src = room["g"].vertex
    got = plyfile.PlyData.read(str(out))["vertex"].data
    assert got.dtype.names == (*src.dtype.names, "label", "score")
    assert got.dtype["label"] == np.dtype("<i4") and got.dtype["score"] == np.dtype("<f4")
    for name in src.dtype.names:
        assert got[name].tobytes() == src[name].tobytes()
    # the header is ASCII: the name's non-ASCII character is escaped
    head = out.read_bytes()[:4096]
    assert b'comment goi label 3 "caf\\u00e9 \\"x\\""' in head


def test_overlap_takes_the_higher_score_then_the_first():
    sel = np.array([[1, 1, 1, 0, 1], [1, 1, 0, 1, 1], [0, 1, 0, 0, 1]], bool)
    s1 = np.array([0.2, 0.9, 0.5, 0.0, 0.7], np.float32)
    s2 = np.array([0.6, 0.9, 0.0, 0.4, 0.3], np.float32)
    layers = [LabelLayer("a", sel[0], s1), LabelLayer("b", sel[1], s2), LabelLayer("c", sel[2])]
    lab, overlapping = assign(layers, 5)
    # 0: b's 0.6 beats a's 0.2; 1: c's 1.0 beats a and b; 2, 3: alone; 4: c's 1.0
    np.testing.assert_array_equal(lab.label, [2, 3, 1, 2, 3])
    np.testing.assert_allclose(lab.score, [0.6, 1.0, 0.5, 0.4, 1.0])
    assert overlapping == 3
    # equal scores: the one given first
    tie, _ = assign([LabelLayer("a", sel[0], s1), LabelLayer("b", sel[1], s1)], 5)
    np.testing.assert_array_equal(tie.label, [1, 1, 1, 2, 1])
    none, _ = assign([LabelLayer("a", np.zeros(5, bool))], 5)
    assert not none.label.any() and not none.score.any()  # label 0 scores 0
    with pytest.raises(GoiError, match="not a number in"):
        assign([LabelLayer("a", sel[0], np.array([0.5, np.nan, 0, 0, 0]))], 5)
    with pytest.raises(GoiError, match="not a number in"):
        assign([LabelLayer("a", sel[0], np.array([0.5, 1.5, 0, 0, 0]))], 5)
    with pytest.raises(GoiError, match="given twice"):
        assign([LabelLayer("a", sel[0]), LabelLayer("a", sel[1])], 5)
    with pytest.raises(GoiError, match="no named selection"):
        assign([], 5)


@pytest.mark.slow
def test_real_lifted_selections_and_their_overlap(room, tmp_path):
    """Two lifted selections made by `goi select --lift` from the boxes' masks, and a hand
    selection of box 1 and the floor given between them: each Gaussian takes the selection
    with the higher score, each label's score is its selection's, ties go to the first."""
    common = ["--scene", str(room["scene"]), "--res-masks", str(room["root"] / "res"), "--lift"]
    for k in (1, 2):
        args = ["select", *common, "--prompt", f"box {k}", "--prompt-id", f"o{k}"]
        assert main([*args, "--out", str(tmp_path / f"o{k}.h5")]) == 0
    ids = room["ids"]
    hand = (ids == 1) | ((ids == 0) & (room["g"].means[:, 2] < 0.01))
    _selection(room, tmp_path / "hand.h5", hand)
    out = tmp_path / "l.ply"
    specs = [f"box 1={tmp_path / 'o1.h5'}", f"hand={tmp_path / 'hand.h5'}"]
    assert _export(room, out, *specs, f"box 2={tmp_path / 'o2.h5'}") == 0
    lab = read_labels(out)
    sels = [load_selection(tmp_path / f).selected for f in ("o1.h5", "hand.h5", "o2.h5")]
    assert sels[0].sum() > 100 and sels[2].sum() > 100
    assert np.array_equal(lab.label > 0, sels[0] | sels[1] | sels[2])
    for i, s in enumerate(sels, start=1):
        assert s[lab.label == i].all()
    both = sels[0] & sels[1]
    assert both.sum() > 100  # box 1 is in the hand selection too
    share = lab.score[both]  # box 1's vote share where it kept them, 1.0 where hand took them
    kept = lab.label[both] == 1
    assert kept.any() and (share[kept] == 1.0).all()  # a tie with hand's 1.0: the first wins
    assert (~kept).any() and (share[~kept] == 1.0).all()
    # box 2's scores are its artifact's vote shares S1 / E where E >= min_evidence, else 1
    with h5py.File(tmp_path / "o2.h5") as f:
        S1, S0 = f["lifted/S1"][()].astype(np.float64), f["lifted/S0"][()].astype(np.float64)
        tau = json.loads(f["lifted"].attrs["record"])["params"]["min_evidence"]
    E = S1 + S0
    share = np.where(E >= tau, S1 / np.maximum(E, 1e-300), 1.0)
    mine = lab.label == 3
    np.testing.assert_allclose(lab.score[mine], share[mine], atol=1e-6)
    assert lab.score[mine].min() < 0.9  # not all 1: the vote share, not a flag


def test_refusals_exit_2_and_write_nothing(room, tmp_path, capsys):
    ids = room["ids"]
    a = _selection(room, tmp_path / "a.h5", ids == 1)
    other = _selection(room, tmp_path / "other.h5", ids == 2, ply_sha="0" * 64)
    out = tmp_path / "x.ply"
    cases = [
        ([f"a={a}", f"b={other}"], [], "made for another PLY"),
        ([f"={a}"], [], "empty"),
        ([f"a={a}", f"a={a}"], [], "given twice"),
        ([f"a\tb={a}"], [], "not printable"),
        ([f" a={a}"], [], "starts or ends with a space"),
        ([str(a)], [], "not NAME=SELECTION.h5"),
        ([f"a={tmp_path / 'missing.h5'}"], [], "no such file"),
        ([f"a={a}"], ["--invert"], "--invert: not with --labels"),
        ([f"a={a}"], ["--selection", str(a)], "--selection: not with --labels"),
        ([f"a={a}"], ["--highlight", "red"], "--highlight: not with --labels"),
    ]
    for specs, extra, message in cases:
        assert _export(room, out, *specs, extra=extra) == 2, specs
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1 and "Traceback" not in err, err
    # --out is one of the selections (even with --force); nothing at all asked for
    assert _export(room, a, f"a={a}", extra=["--force"]) == 2
    assert "inputs" in capsys.readouterr().err
    assert main(["export-ply", "--scene", str(room["scene"]), "--out", str(out)]) == 2
    assert "--selection" in capsys.readouterr().err
    assert not out.exists() and load_selection(a).selected.sum() == (ids == 1).sum()


def _labelled(tmp_path, v, comments, name="bad.ply"):
    p = tmp_path / name
    save_ply(p, v, force=True, comments=comments)
    return p


def test_the_reader_refuses_malformed_labels(room, tmp_path):
    ids = room["ids"]
    out = tmp_path / "good.ply"
    assert _export(room, out, f"a={_selection(room, tmp_path / 'a.h5', ids == 1)}") == 0
    g = load_ply(out)
    head = [c for c in g.comments if not c.startswith("goi label ")]
    v = g.vertex.copy()
    bad_label = v.copy()
    bad_label["label"][7] = 2
    nan_score = v.copy()
    nan_score["score"][3] = np.nan
    big_score = v.copy()
    big_score["score"][3] = 1.5
    from numpy.lib import recfunctions as rfn

    cases = [
        (bad_label, g.comments, "label 2 at vertex 7 is not one of the ids 0..1"),
        (nan_score, g.comments, "score nan at vertex 3"),
        (big_score, g.comments, "score 1.5 at vertex 3"),
        (v, [c.replace("labels_ply 1.0", "labels_ply 2.0") for c in g.comments], "upgrade goi"),
        (v, head, "names no label"),
        (v, [*head, 'goi label 2 "a"'], "ids run 1, 2"),
        (v, [*head, "goi label 1 a"], "is not 'goi label 1"),
        (v, [*head, 'goi label 1 ""'], "empty"),
        (rfn.drop_fields(v, ["score"], usemask=False), g.comments, "'score' is missing"),
    ]
    for i, (table, comments, message) in enumerate(cases):
        p = _labelled(tmp_path, table, comments, f"bad{i}.ply")
        with pytest.raises(GoiError, match="^" + str(p)) as e:
            read_labels(p)
        assert message in str(e.value), (message, str(e.value))
    plain = tmp_path / "plain.ply"
    save_ply(plain, v, force=True)  # the properties, without goi's comments
    with pytest.raises(GoiError, match="dropped goi's header comments"):
        read_labels(plain)
    with pytest.raises(GoiError, match="not a goi labels PLY"):
        read_labels(room["scene"] / "point_cloud.ply")


def test_a_labels_ply_is_a_scene_and_inspect_shows_its_labels(room, tmp_path, capsys):
    """goi loads the labels PLY as a scene (label and score are extra properties), INRIA's
    loader rules find the scene's arrays unchanged, an export of it keeps the labels named,
    and `goi inspect` lists names and counts (and a malformed one's problem)."""
    ids = room["ids"]
    a = _selection(room, tmp_path / "a.h5", ids == 1)
    b = _selection(room, tmp_path / "b.h5", ids == 2)
    out = tmp_path / "scene.labels.ply"
    assert _export(room, out, f"sofa={a}", f"teddy bear={b}") == 0
    src, g = room["g"], load_ply(out)
    assert g.extra_fields == ["label", "score"]
    np.testing.assert_array_equal(g.means, src.means)
    np.testing.assert_array_equal(g.sh, src.sh)
    np.testing.assert_array_equal(g.opacities, src.opacities)
    # INRIA's GaussianModel.load_ply: properties by name and by prefix ("scale_", "rot")
    el = plyfile.PlyData.read(str(out)).elements[0]
    names = [p.name for p in el.properties]
    assert names[: len(src.vertex.dtype.names)] == list(src.vertex.dtype.names)
    assert set(REQUIRED) <= set(names)
    scale = sorted((n for n in names if n.startswith("scale_")), key=lambda n: int(n[6:]))
    rot = sorted((n for n in names if n.startswith("rot")), key=lambda n: int(n.split("_")[-1]))
    assert scale == ["scale_0", "scale_1", "scale_2"] and rot == [f"rot_{i}" for i in range(4)]
    # an export of the labelled scene keeps the labels and their names
    sub = tmp_path / "sub.ply"
    base = ["export-ply", "--ply", str(out), "--cameras", str(room["scene"] / "cameras.json")]
    sel_on_labelled = write_selection(
        tmp_path / "s.h5", ids > 0, "objects", "threshold", sha256_file(out), {}, force=True
    )
    assert main([*base, "--selection", str(sel_on_labelled), "--out", str(sub)]) == 0
    lab = read_labels(sub)
    assert lab.names == ["sofa", "teddy bear"]
    np.testing.assert_array_equal(lab.label, read_labels(out).label[ids > 0])
    capsys.readouterr()
    assert main(["inspect", str(out)]) == 0
    shown = capsys.readouterr().out
    assert "labels        2 named selections (goi.labels_ply 1.0" in shown
    assert f'label 1       "sofa": {(ids == 1).sum()} Gaussians' in shown
    assert f'label 2       "teddy bear": {(ids == 2).sum()} Gaussians' in shown
    assert f"label 0       (none): {(ids == 0).sum() + (ids > 2).sum()} Gaussians" in shown
    bad = g.vertex.copy()
    bad["label"][0] = 9
    p = _labelled(tmp_path, bad, g.comments)
    assert main(["inspect", str(p)]) != 0
    assert "label 9 at vertex 0" in capsys.readouterr().out


def test_the_viewer_entry_writes_arrays(room, tmp_path):
    """write_labels_ply: (name, selected, score | None) arrays in, the PLY out."""
    ids = room["ids"]
    score = np.where(ids == 2, 0.25, 0.0)
    layers = [("chair", ids == 1, None), ("table", ids == 2, score)]
    out, lab, overlapping = write_labels_ply(room["g"], layers, tmp_path / "v.ply", {"ply": "x"})
    back = read_labels(out)
    assert back.names == ["chair", "table"] and overlapping == 0
    np.testing.assert_array_equal(back.label, np.where(ids <= 2, ids, 0))
    np.testing.assert_allclose(back.score, np.where(ids == 1, 1.0, np.where(ids == 2, 0.25, 0)))
    with pytest.raises(GoiError, match="one of this command's inputs|already exists"):
        write_labels_ply(room["g"], [LabelLayer("a", ids == 1)], room["g"].path, {}, force=True)
    # names that would push the header past what PLY readers read of it
    many = [(f"{i:03d} " + "x" * 190, ids == 1, None) for i in range(200)]
    with pytest.raises(GoiError, match="bytes of the PLY header"):
        write_labels_ply(room["g"], many, tmp_path / "many.ply", {})
    assert not (tmp_path / "many.ply").exists()


@pytest.mark.slow
def test_splat_transform_reads_the_labelled_ply(room, tmp_path):
    """PlayCanvas's splat-transform (npm, the reader of SuperSplat) reads every Gaussian with
    positions intact and keeps label and score as extra columns; a PLY it writes back loads
    in goi, whose label reader then says the names are gone (splat-transform drops comments)."""
    from stages.testing import splat_transform

    try:
        splat_transform.fetch()
    except (RuntimeError, OSError, subprocess.TimeoutExpired) as e:
        pytest.skip(f"splat-transform not available: {e}")
    ids = room["ids"]
    a = _selection(room, tmp_path / "a.h5", ids == 1)
    b = _selection(room, tmp_path / "b.h5", ids == 2)
    out = tmp_path / "scene.labels.ply"
    assert _export(room, out, f"sofa={a}", f"teddy bear={b}") == 0
    info = splat_transform.run(["-q", str(out), "--info", "json", "null"])
    assert info.returncode == 0, info.stderr
    meta = json.loads(info.stdout[info.stdout.index("{") : info.stdout.rindex("}") + 1])
    assert meta["numGaussians"] == len(ids) and meta["gaussian"] is True
    extra = {c["name"] for c in meta["extraColumns"]}
    assert {"label", "score"} <= extra
    back = tmp_path / "back.ply"
    conv = splat_transform.run(["-q", str(out), "-w", str(back)])
    assert conv.returncode == 0, conv.stderr
    src = plyfile.PlyData.read(str(out))["vertex"].data
    got = plyfile.PlyData.read(str(back))["vertex"].data
    assert len(got) == len(src)
    for name in src.dtype.names:  # positions and every other property, bit for bit
        np.testing.assert_array_equal(got[name], src[name], err_msg=name)
    g = load_ply(back)
    np.testing.assert_array_equal(g.means, room["g"].means)
    with pytest.raises(GoiError, match="dropped goi's header comments"):
        read_labels(back)

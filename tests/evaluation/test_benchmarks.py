"""goi eval --benchmark end to end on small synthetic scenes written in each benchmark's exact
layout (stages/testing/public_layouts.py), and the readers' refusals and warnings."""

import json

import numpy as np
import pytest

from goi_cli.main import main
from schemas import validate_json
from stages.core.errors import GoiError, GoiWarning
from stages.evaluation.benchmarks.goi_m360 import read_goi_m360
from stages.evaluation.benchmarks.lerf_ovs import read_lerf_ovs
from stages.evaluation.benchmarks.run import BENCHMARKS
from stages.evaluation.benchmarks.three_d_ovs import read_three_d_ovs
from stages.scene.formats import load_cameras
from stages.testing.public_layouts import synthetic_benchmark

SIZE = {"3d-ovs": (160, 120)}  # 3D-OVS scores at 1/8 of the image


def _make(tmp_path, benchmark):
    return synthetic_benchmark(tmp_path, benchmark, n=3000, size=SIZE.get(benchmark, (64, 48)))


def _argv(s, benchmark, out, *extra):
    return ["eval", "--benchmark", benchmark, str(s["bench"]), "--scene", f"toy={s['trained']}",
            "--features", str(s["features"]), "--res-masks", str(s["res"]),
            "--text-embeddings", str(s["embeddings"]), "--out", str(out),
            "--iterations", "40", "--entries", "16", *extra]  # fmt: skip


@pytest.mark.slow
@pytest.mark.parametrize("benchmark", BENCHMARKS)
def test_benchmark_scored_end_to_end(tmp_path, benchmark, capsys):
    s = _make(tmp_path, benchmark)
    out, html = tmp_path / "r.json", tmp_path / "r.html"
    variants = "full,lifted,lifted_fieldless" if benchmark == "goi-m360" else "full"
    assert main(_argv(s, benchmark, out, "--html", str(html), "--variants", variants)) == 0
    r = json.loads(out.read_text())
    validate_json(r, "goi.eval", str(out))
    assert r["schema_version"] == "1.5" and r["benchmark"]["name"] == benchmark
    scene = r["benchmark"]["scenes"]["toy"]
    assert scene["n_frames"] == 2 and not scene["skipped"]
    for v in variants.split(","):
        figs = scene["variants"][v]
        assert set(figs["queries"]) == set(s["queries"].values())
        for value in figs["protocol"].values():
            assert 0.5 <= value <= 1  # the boxes are found (by the mask and the score map)
        if benchmark in ("lerf-ovs", "3d-ovs"):
            assert "miou_score_map" in figs["protocol"]
            assert f"score_map_{v}" in r["timings_s"]
        assert r["variants"][v]["protocol"] == figs["protocol"]  # one scene: the mean is it
        assert 0.5 <= figs["goi"]["miou"] <= 1
    assert r["timings_s"]["read_annotations"] >= 0 and r["timings_s"]["metrics"] >= 0
    page = html.read_text()
    assert r["benchmark"]["protocol"] in page and "toy" in page
    assert f"<title>goi eval --benchmark {benchmark}</title>" in page
    figs = sorted((tmp_path / "r_files").glob("*.png"))
    assert len(figs) == len(s["queries"]) * len(variants.split(","))
    assert all(f"r_files/{f.name}" in page for f in figs)
    if benchmark in ("goi-m360", "replica-goi"):
        want = "0.8646" if benchmark == "goi-m360" else "0.6169"  # GOI's own mean mIoU
        assert "GOI paper" in page and want in page
    else:  # LangSplat / LangSplatV2 / Gaussian Grouping, with protocol and source
        want = {"lerf-ovs": "0.5990", "lerf-mask": "0.7280", "3d-ovs": "0.9340"}[benchmark]
        assert "(published)" in page and "read in:" in page and want in page
    printed = capsys.readouterr().out
    assert "protocol" in printed and "goi mIoU" in printed


def _refused(argv, capsys, words):
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err.splitlines()[-1]
    assert err.startswith("goi: error:") and words in err, err


def test_lerf_ovs_refusals(tmp_path, capsys):
    s = _make(tmp_path, "lerf-ovs")
    out = tmp_path / "r.json"
    labels = s["bench"] / "label" / "toy"
    first = sorted(labels.glob("*.json"))[0]
    doc = json.loads(first.read_text())
    first.write_text(json.dumps({"info": doc["info"]}))
    _refused(_argv(s, "lerf-ovs", out), capsys, f"{first}: no 'objects' list")
    first.write_text(json.dumps({**doc, "info": {**doc["info"], "name": "frame_00099.jpg"}}))
    _refused(_argv(s, "lerf-ovs", out), capsys, "this frame has no camera")
    first.write_text(json.dumps(doc))
    _refused([*_argv(s, "lerf-ovs", out), "--entries", "50000"], capsys, "--entries: 50000")
    emb = json.loads(s["embeddings"].read_text())
    emb.pop("red box")
    s["embeddings"].write_text(json.dumps(emb))
    _refused(_argv(s, "lerf-ovs", out), capsys, "no text embedding for 'red box'")
    _refused(_argv(s, "lerf-ovs", out)[:4] + _argv(s, "lerf-ovs", out)[6:], capsys, "--scene")
    assert not out.exists() and not (tmp_path / "r.work").exists()


def test_lerf_ovs_polygon_outside_the_image_warns_and_is_clipped(tmp_path):
    s = _make(tmp_path, "lerf-ovs")
    labels = s["bench"] / "label" / "toy"
    first = sorted(labels.glob("*.json"))[0]
    doc = json.loads(first.read_text())
    doc["objects"][0]["segmentation"] = [[-10, -10], [30, -5], [30, 30], [-10, 30]]
    doc["objects"].append({**doc["objects"][1], "bbox": [0, 0, 2, 2]})  # a repeated category
    first.write_text(json.dumps(doc))
    cams = load_cameras(s["bench"] / "toy" / "sparse" / "0")
    with pytest.warns(GoiWarning, match="reaches outside the 64x48 image"):
        bench = read_lerf_ovs(s["bench"], "toy", cams)
    f = bench.frames[0]
    q0, q1 = (doc["objects"][k]["category"] for k in (0, 1))
    assert f.gts[q0][:31, :31].all() and f.gts[q0].sum() == 31 * 31  # clipped; edges filled
    assert f.boxes[q1].shape == (2, 4)  # boxes concatenated, masks OR'd
    assert f.camera.name == cams[1].name == "frame_00002"  # idx 2 - 1 into the sorted cameras
    assert bench.frames[0].key == "frame_00002"


def test_three_d_ovs_class_list_must_match_the_masks(tmp_path, capsys):
    s = _make(tmp_path, "3d-ovs")
    seg = s["bench"] / "toy" / "segmentations"
    (seg / "classes.txt").write_text("wall\nred box\ngreen box\nblue box\ntall box\nsofa\n")
    _refused(_argv(s, "3d-ovs", tmp_path / "r.json"), capsys, "sofa.png: missing; classes.txt")
    (seg / "classes.txt").write_text("wall\nred box\n")
    cams = load_cameras(s["bench"] / "toy" / "sparse" / "0")
    with pytest.warns(GoiWarning, match="blue box, green box, tall box of no class"):
        bench = read_three_d_ovs(s["bench"], "toy", cams)
    assert [q.text for q in bench.queries] == ["red box", "wall"]  # sorted, as the reference
    assert bench.frames[0].camera.width == 20 and bench.frames[0].key == "01"
    (seg / "99").mkdir()
    _refused(_argv(s, "3d-ovs", tmp_path / "r2.json"), capsys, "the frame has no camera")


def test_goi_m360_skips_a_mask_without_camera_and_replica_needs_its_list(tmp_path, capsys):
    s = _make(tmp_path / "m", "goi-m360")
    stray = s["bench"] / "toy" / "red_box" / "masks" / "DSCF9999.png"
    stray.write_bytes(
        (s["bench"] / "toy" / "red_box" / "masks").glob("*.png").__next__().read_bytes()
    )
    cams = load_cameras(s["trained"] / "cameras.json")
    with pytest.warns(GoiWarning, match="DSCF9999.png: no camera named 'DSCF9999'"):
        bench = read_goi_m360(s["bench"], "toy", cams)
    assert len(bench.frames) == 2 and bench.skipped
    assert {q.text for q in bench.queries} == {"red box", "green box", "blue box"}
    r = synthetic_benchmark(tmp_path / "r", "replica-goi", n=2000)
    top = r["bench"] / "toy" / "test" / "top_list.json"
    top.write_text(json.dumps({"sem_1.png": []}))
    _refused(_argv(r, "replica-goi", tmp_path / "r.json"), capsys, "'sem_4.png': missing")


def test_reader_errors_are_goi_errors(tmp_path):
    with pytest.raises(GoiError, match="label"):
        read_lerf_ovs(tmp_path, "figurines", [])
    assert np.isfinite(0.0)


@pytest.mark.slow
def test_two_scenes_give_a_table_each_and_their_mean(tmp_path):
    """--features and --res-masks hold one folder per scene; the mean is over scenes."""
    import shutil

    bench, feats, res = tmp_path / "bench", tmp_path / "feats", tmp_path / "res"
    scenes = []
    for name in ("room", "bonsai"):  # one seed: the texts' embeddings are the same
        s = synthetic_benchmark(tmp_path / name, "goi-m360", scene=name, n=2500)
        shutil.move(s["bench"] / name, bench / name)
        shutil.move(s["features"], feats / name)
        shutil.move(s["res"], res / name)
        scenes.append(f"{name}={s['trained']}")
    emb = s["embeddings"]
    out = tmp_path / "r.json"
    argv = ["eval", "--benchmark", "goi-m360", str(bench), "--scene", scenes[0], "--scene",
            scenes[1], "--features", str(feats), "--res-masks", str(res), "--text-embeddings",
            str(emb), "--out", str(out), "--html", str(tmp_path / "r.html"),
            "--iterations", "30", "--entries", "16", "--variants", "full"]  # fmt: skip
    assert main(argv) == 0
    r = json.loads(out.read_text())
    per = [r["benchmark"]["scenes"][n]["variants"]["full"]["protocol"] for n in ("room", "bonsai")]
    for k in ("miou", "mpa", "mp"):
        assert r["variants"]["full"]["protocol"][k] == pytest.approx((per[0][k] + per[1][k]) / 2)
    page = (tmp_path / "r.html").read_text()
    assert "Mean over 2 scene(s)" in page and "0.8504" in page and "0.9147" in page  # per scene

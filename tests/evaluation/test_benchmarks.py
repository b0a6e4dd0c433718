"""goi eval --benchmark end to end on small synthetic scenes written in each benchmark's exact
layout (stages/testing/public_layouts.py), and the readers' refusals and warnings."""

import json
import re
import shutil
import warnings

import numpy as np
import pytest

from goi_cli.main import main
from schemas import validate_json
from stages.core.errors import GoiError, GoiWarning
from stages.evaluation.benchmarks.common import pil_nearest
from stages.evaluation.benchmarks.goi_m360 import read_goi_m360
from stages.evaluation.benchmarks.lerf_mask import NAMED, NUMBERED, read_lerf_mask
from stages.evaluation.benchmarks.lerf_ovs import read_lerf_ovs
from stages.evaluation.benchmarks.run import BENCHMARKS, READERS
from stages.evaluation.benchmarks.scoring import gt_bool
from stages.evaluation.benchmarks.three_d_ovs import read_three_d_ovs
from stages.scene.formats import load_cameras
from stages.testing.public_layouts import synthetic_benchmark

SIZE = {"3d-ovs": (160, 120)}  # 3D-OVS scores at 1/8 of the image
#: a released scene of each benchmark, for the published figures set beside goi's
RELEASED = {"lerf-ovs": "figurines", "lerf-mask": "figurines", "3d-ovs": "bed",
            "goi-m360": "room", "replica-goi": "room0"}  # fmt: skip


def _make(tmp_path, benchmark, scene="toy"):
    size = SIZE.get(benchmark, (64, 48))
    return synthetic_benchmark(tmp_path, benchmark, scene=scene, n=3000, size=size)


def _argv(s, benchmark, out, *extra):
    return ["eval", "--benchmark", benchmark, str(s["bench"]), "--scene",
            f"{s['scene']}={s['trained']}", "--features", str(s["features"]), "--res-masks",
            str(s["res"]), "--text-embeddings", str(s["embeddings"]), "--out", str(out),
            "--iterations", "40", "--entries", "16", *extra]  # fmt: skip


@pytest.mark.slow
@pytest.mark.parametrize("benchmark", BENCHMARKS)
def test_benchmark_scored_end_to_end(tmp_path, benchmark, capsys):
    name = RELEASED[benchmark]
    s = _make(tmp_path, benchmark, name)
    out, html = tmp_path / "r.json", tmp_path / "r.html"
    variants = "full,lifted,lifted_fieldless" if benchmark == "goi-m360" else "full"
    assert main(_argv(s, benchmark, out, "--html", str(html), "--variants", variants)) == 0
    r = json.loads(out.read_text())
    validate_json(r, "goi.eval", str(out))
    assert r["schema_version"] == "1.8" and r["benchmark"]["name"] == benchmark
    scene = r["benchmark"]["scenes"][name]
    assert scene["n_frames"] == 2 and not scene["skipped"]
    cams = scene["frames"]  # frame -> camera (at the ground truth's size: name_WxH)
    assert sorted(re.sub(r"_\d+x\d+$", "", c) for c in cams.values()) == sorted(
        s["cameras"][i].name for i in (1, 4)
    )  # each frame matched to the camera whose view its ground truth was rendered from
    if benchmark == "lerf-mask":
        assert scene["layout"].startswith("numbered folders") and set(cams) == {"0", "1"}
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
    assert r["benchmark"]["protocol"] in page and name in page
    assert f"<title>goi eval --benchmark {benchmark}</title>" in page
    figs = sorted((tmp_path / "r_files").glob("*.png"))
    assert len(figs) == len(s["queries"]) * len(variants.split(","))
    assert all(f"r_files/{f.name}" in page for f in figs)
    # one released scene: its published figures, and as the mean only the mean of the same
    # scene's figures, never the paper's mean over its whole scene set
    mean_table = page.split("<h2>Mean over 1 scene(s)</h2>")[1].split("<h2>")[0]
    one, whole = {
        "goi-m360": ("0.8504", "0.8646"),  # GOI (paper), room / mean of four
        "replica-goi": ("0.6589", "0.6169"),  # GOI (paper), room0 / mean of four
        "lerf-ovs": ("0.5640", "0.5990"),  # LangSplatV2, figurines / mean of four
        "lerf-mask": ("0.6970", "0.7280"),  # Gaussian Grouping, figurines / mean of three
        "3d-ovs": ("0.9250", "0.9340"),  # LangSplat, bed / its printed mean
    }[benchmark]
    assert one in mean_table and whole not in page
    assert "mean of its 1 per-scene figure(s)" in mean_table
    if benchmark in ("goi-m360", "replica-goi"):
        assert "GOI paper" in page
    else:  # LangSplat / LangSplatV2 / Gaussian Grouping, with protocol and source
        assert "(published)" in page and "read in:" in page
    if benchmark == "lerf-mask":  # the intro names only the rows shown
        intro = page.split("Published figures shown: ")[1].split(",")[:2]
        assert intro == ["Gaussian Grouping", " LangSplat"]
    printed = capsys.readouterr()
    assert "protocol" in printed.out and "goi mIoU" in printed.out
    assert "not one of" not in printed.err  # a released scene name: no warning


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
    _refused(_argv(s, "3d-ovs", tmp_path / "r.json"), capsys, "01: no sofa.png; classes.txt")
    (seg / "classes.txt").write_text("wall\nred box\n")
    cams = load_cameras(s["bench"] / "toy" / "sparse" / "0")
    with pytest.warns(GoiWarning, match="blue box, green box, tall box of no class"):
        bench = read_three_d_ovs(s["bench"], "toy", cams)
    assert [q.text for q in bench.queries] == ["red box", "wall"]  # sorted, as the reference
    assert bench.frames[0].camera.width == 20 and bench.frames[0].key == "01"
    assert bench.frames[0].camera.name.startswith("IMG_0102")  # sorted(images)[int("01")]
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


def _cams(s, benchmark):
    bench_dir = s["bench"] / s["scene"]
    if benchmark in ("lerf-ovs", "lerf-mask", "3d-ovs"):
        return load_cameras(bench_dir / "sparse" / "0")
    return load_cameras(s["trained"] / "cameras.json")


def _iou(a, b):
    return (a & b).sum() / max(1, (a | b).sum())


@pytest.mark.parametrize("benchmark", BENCHMARKS)
def test_every_reader_pairs_a_frame_with_the_camera_its_reference_pairs(tmp_path, benchmark):
    """The fixture writes each release's layout as its reference code reads or writes it
    (stages/testing/public_layouts.py quotes the code), with image names under which a wrong
    reading finds a camera: every frame's ground truth must be the rendering of the camera
    the reader matched it to, and not the other annotated view's."""
    s = _make(tmp_path, benchmark)
    bench = READERS[benchmark](s["bench"], "toy", _cams(s, benchmark))
    assert len(bench.frames) == 2
    names = [re.sub(r"_\d+x\d+$", "", f.camera.name) for f in bench.frames]
    assert sorted(names) == sorted(s["cameras"][i].name for i in (1, 4))
    for f, name in zip(bench.frames, names, strict=True):
        other = next(n for n in names if n != name)
        for k, qid in s["queries"].items():
            if qid not in f.gts:
                continue
            gt = gt_bool(f.gts[qid])

            def truth(view, gt=gt, k=k):  # at the ground truth's size, as 3D-OVS resizes
                return pil_nearest(s["labels"][view] == k, gt.shape[1], gt.shape[0])

            if not (gt.any() or truth(name).any()):
                continue
            assert _iou(gt, truth(name)) >= 0.8, (f.key, name, qid)
            assert _iou(gt, truth(name)) > _iou(gt, truth(other)), (f.key, name, qid)


def test_lerf_mask_numbered_folders_as_released_and_named_ones(tmp_path):
    s = _make(tmp_path, "lerf-mask")
    cams = _cams(s, "lerf-mask")
    masks = s["bench"] / "toy" / "test_mask"
    bench = read_lerf_mask(s["bench"], "toy", cams)
    assert bench.layout == NUMBERED and [f.key for f in bench.frames] == ["0", "1"]
    assert [f.camera.name for f in bench.frames] == ["frame_00002", "frame_00005"]
    assert bench.held_out == {"frame_00002", "frame_00005"}  # the images not in images_train
    for k, name in enumerate(["frame_00002", "frame_00005"]):  # goi's earlier reading
        (masks / str(k)).rename(masks / name)
    named = read_lerf_mask(s["bench"], "toy", cams)
    assert named.layout == NAMED and [f.key for f in named.frames] == ["frame_00002", "frame_00005"]
    assert all(
        (a.gts[q] == b.gts[q]).all() for a, b in zip(bench.frames, named.frames, strict=True)
        for q in a.gts
    )  # fmt: skip
    (masks / "frame_00002").rename(masks / "frame_00001")  # a training view
    with pytest.raises(GoiError, match="'frame_00001' is in images_train"):
        read_lerf_mask(s["bench"], "toy", cams)
    for d in masks.iterdir():
        d.rename(masks / {"frame_00001": "0", "frame_00005": "1"}[d.name])
    shutil.copytree(masks / "1", masks / "2")
    with pytest.raises(GoiError, match="3 numbered folders, but the scene has 2 test cameras"):
        read_lerf_mask(s["bench"], "toy", cams)
    shutil.rmtree(masks / "1")
    with pytest.raises(GoiError, match="folder 2, but the 2 test cameras are numbered 0-1"):
        read_lerf_mask(s["bench"], "toy", cams)


def test_lerf_ovs_frame_number_is_an_index_into_the_sorted_cameras(tmp_path):
    """idx = int(name.split('_')[-1].split('.jpg')[0]) - 1 indexes the cameras sorted by
    image name, whatever their names: without frame_00001, frame_00002 is the third camera."""
    s = _make(tmp_path, "lerf-ovs")
    cams = [c for c in _cams(s, "lerf-ovs") if c.name != "frame_00001"]
    bench = read_lerf_ovs(s["bench"], "toy", cams)
    assert [(f.key, f.camera.name) for f in bench.frames] == [
        ("frame_00002", "frame_00003"),
        ("frame_00005", "frame_00006"),
    ]


def test_an_unknown_scene_name_is_warned_about(tmp_path, capsys):
    s = _make(tmp_path, "lerf-ovs")
    emb = json.loads(s["embeddings"].read_text())
    emb.pop("red box")
    s["embeddings"].write_text(json.dumps(emb))
    capsys.readouterr()
    with warnings.catch_warnings():
        warnings.simplefilter("always")  # the CLI prints a warning once per process
        assert main(_argv(s, "lerf-ovs", tmp_path / "r.json")) == 2
    err = capsys.readouterr().err
    assert "--scene toy: not one of lerf-ovs's released scenes (figurines, ramen" in err
    assert err.splitlines()[-1].startswith("goi: error:") and "no text embedding" in err


@pytest.mark.slow
def test_seeds_report_the_spread_of_full(tmp_path, capsys):
    s = _make(tmp_path, "lerf-mask", "figurines")
    out, html = tmp_path / "r.json", tmp_path / "r.html"
    argv = _argv(s, "lerf-mask", out, "--html", str(html), "--variants", "full,lifted",
                 "--seeds", "0,1,2")  # fmt: skip
    assert main(argv) == 0
    r = json.loads(out.read_text())
    validate_json(r, "goi.eval", str(out))
    sd = r["benchmark"]["seeds"]
    assert sd["seeds"] == [0, 1, 2] and sd["variant"] == "full"
    scene = r["benchmark"]["scenes"]["figurines"]
    miou = scene["seeds"]["protocol"]["miou"]
    assert miou["values"][0] == scene["variants"]["full"]["protocol"]["miou"]  # --seed 0 reused
    assert miou["range"] == max(miou["values"]) - min(miou["values"]) and miou["sd"] >= 0
    assert len(set(miou["values"])) > 1  # other seeds, other fits
    assert sd["mean"]["protocol"]["miou"]["values"] == miou["values"]  # one scene
    assert set(scene["seeds"]["queries"]) == set(s["queries"].values())
    work = tmp_path / "r.work" / "figurines"
    assert (work / "seed-1" / "field_tfcc.h5").is_file() and not (work / "seed-0").exists()
    assert "Spread of full over seeds 0, 1, 2" in html.read_text()
    printed = capsys.readouterr().out
    assert "full over seeds 0,1,2 (mean over scenes):" in printed and "widest query" in printed
    for x, v in zip((0, 1, 2), miou["values"], strict=True):
        print(f"seed {x}: full lerf-mask mIoU {v:.4f}")

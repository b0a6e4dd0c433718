"""goi eval end to end on a small synthetic room in the benchmark layout."""

import json
import shutil

import cv2
import numpy as np
import pytest

from goi_cli.main import main
from schemas import validate_json
from stages.query.prompts import safe_name
from stages.render.rasterizer import Rasterizer
from stages.scene.gaussians import load_ply
from tests.helpers import semantic_scene


def make_room(root):
    """semantic_scene plus prompts.json, eval/masks, gaussian_ids.npy, text embeddings, RES."""
    s = semantic_scene(root, n=4000, n_views=8, size=(64, 48), dim=16)
    room = s["scene"]
    ids = s["onehot"].argmax(1).astype(np.int32)
    np.save(room / "gaussian_ids.npy", ids)
    rast = Rasterizer.from_gaussians(load_ply(room / "point_cloud.ply"))
    prompts, emb = [], {}
    for k in (1, 2):
        pid, text = f"p{k}", f"<b>object {k}</b>"  # markup must survive into the HTML escaped
        emb[text] = s["objects"][k].tolist()
        tests = []
        for name in s["train"] + s["test"]:
            share = rast.render_features(s["cameras"][name], s["onehot"]).image
            m = ((share.argmax(2) == k) & (share.sum(2) > 0.5)).astype(np.uint8) * 255
            split = "res" if name in s["train"] else "eval/masks"
            (room / split / pid).mkdir(parents=True, exist_ok=True)
            if name in s["test"] and m.any():
                tests.append(name)
            cv2.imwrite(str(room / split / pid / f"{name}.png"), m)
        prompts.append({"id": pid, "text": text, "targets": [k], "kind": "x", "test_views": tests})
    (room / "prompts.json").write_text(json.dumps(prompts))
    (room / "text_embeddings.json").write_text(json.dumps(emb))
    return s, room


@pytest.mark.slow
def test_eval_scores_all_variants_and_writes_the_report(tmp_path):
    s, room = make_room(tmp_path)
    out = tmp_path / "r.json"
    argv = ["eval", str(room), "--features", str(s["features"]), "--res-masks",
            str(room / "res"), "--out", str(out), "--html", str(tmp_path / "r.html"),
            "--iterations", "150", "--entries", "16"]  # fmt: skip
    assert main(argv) == 0
    r = json.loads(out.read_text())
    validate_json(r, "goi.eval", str(out))
    assert set(r["variants"]) == {
        "full", "without_osh", "without_tfcc", "baseline", "lifted", "lifted_fieldless"
    }  # fmt: skip
    assert r["lifted"]["res_views"] == "all mask files" and r["lifted"]["min_evidence"] == 1.0
    assert r["variants"]["lifted"]["miou"] >= 0.7
    assert r["variants"]["lifted_fieldless"]["miou"] >= 0.7
    for v in r["variants"].values():
        assert 0 <= v["miou"] <= 1 and 0 <= v["mpa"] <= 1 and 0 <= v["mp"] <= 1
        assert set(v["prompts"]) == {"p1", "p2"}
    assert r["variants"]["full"]["miou"] >= 0.7
    assert r["variants"]["full"]["miou_3d_visible"] >= 0.7
    for v in r["variants"].values():  # goi.eval 1.7: the stray share per prompt and its mean
        strays = [e["stray_share"] for e in v["prompts"].values()]
        assert all(0 <= x <= 1 for x in strays) and v["stray_share_max"] == max(strays)
        assert v["stray_share"] == pytest.approx(sum(strays) / len(strays))
    assert r["lifted"]["params"]["clean"] is True
    for e in r["variants"]["lifted"]["prompts"].values():
        assert e["clean"]["rule"] == "far_piece"
    for stage in ("extract", "init_codebook", "fit_field_tfcc", "fit_field_direct"):
        assert r["timings_s"][stage] > 0
    page = (tmp_path / "r.html").read_text()
    assert "&lt;b&gt;object 1&lt;/b&gt;" in page and "<b>object" not in page
    assert "evidence threshold" in page
    # the exact 3D answer (the targets rendered as a selection) nearly reproduces the masks,
    # which are the rendered argmax of the same one-hot objects
    exact = r["exact_answer"]
    assert set(exact["prompts"]) == {"p1", "p2"} and exact["miou"] >= 0.9
    assert "The exact 3D answer" in page and "<th>exact 3D answer</th>" in page
    assert "Per prompt (stray share)" in page and "<th>stray share (mean)</th>" in page
    for v in r["variants"].values():  # each prompt read against its exact answer too
        w = v["against_exact"]["worst"]
        assert w["share"] == v["prompts"][w["id"]]["iou"] / exact["prompts"][w["id"]]["iou"]
    assert main(argv) == 2  # the report exists: --force is needed
    # a second eval with other RES masks and the same --work refits nothing
    work = tmp_path / "r.work"
    fields = {
        f: (work / f).stat().st_mtime_ns for f in ("features.h5", "codebook.h5", "field_tfcc.h5")
    }
    out2 = tmp_path / "r2.json"
    argv2 = [*argv[:7], str(out2), *argv[-4:], "--work", str(work)]
    argv2 += ["--variants", "full,lifted", "--res-views", "3"]
    assert main(argv2) == 0
    r2 = json.loads(out2.read_text())
    assert "fit_field_tfcc" not in r2["timings_s"]
    assert {f: (work / f).stat().st_mtime_ns for f in fields} == fields
    assert r2["variants"]["full"]["miou"] == r["variants"]["full"]["miou"]  # same figures
    assert r2["lifted"]["res_views"] == 3
    assert all(len(e["fit_views"]) == 3 for e in r2["variants"]["lifted"]["prompts"].values())


def test_eval_field_free_needs_no_features(tmp_path):
    """--variants lifted_fieldless: no features, codebook or field; any other variant asks for
    --features."""
    s, room = make_room(tmp_path)
    out = tmp_path / "r.json"
    argv = ["eval", str(room), "--res-masks", str(room / "res"), "--out", str(out)]
    assert main([*argv, "--variants", "lifted,lifted_fieldless"]) == 2
    assert main([*argv, "--variants", "lifted_fieldless"]) == 0
    r = json.loads(out.read_text())
    validate_json(r, "goi.eval", str(out))
    assert set(r["variants"]) == {"lifted_fieldless"}
    assert r["variants"]["lifted_fieldless"]["miou"] >= 0.7
    assert 0 <= r["variants"]["lifted_fieldless"]["stray_share"] <= 1
    assert not any(k.startswith("fit_field") for k in r["timings_s"])
    # --no-clean: the vote's answer as it is, recorded so
    out2 = tmp_path / "r2.json"
    argv2 = ["eval", str(room), "--res-masks", str(room / "res"), "--out", str(out2)]
    assert main([*argv2, "--variants", "lifted_fieldless", "--no-clean"]) == 0
    r2 = json.loads(out2.read_text())
    assert r2["lifted"]["params"]["clean"] is False
    assert all(e["clean"] is None for e in r2["variants"]["lifted_fieldless"]["prompts"].values())
    assert all(
        e["clean"]["rule"] == "far_piece"
        for e in r["variants"]["lifted_fieldless"]["prompts"].values()
    )
    assert not (tmp_path / "r.work" / "features.h5").exists()


@pytest.mark.slow
def test_eval_with_a_res_bundle_shows_the_masks_its_fits_used(tmp_path, res_bundles, capsys):
    """--bundle instead of --res-masks: the bundle's RES (a tiny random Grounded-SAM) makes the
    masks; the page shows the ones the fits used, and the full variant's are in the work dir."""
    s, room = make_room(tmp_path)
    out, html = tmp_path / "r.json", tmp_path / "r.html"
    argv = ["eval", str(room), "--features", str(s["features"]), "--out", str(out),
            "--iterations", "150", "--entries", "16",
            "--variants", "full,without_tfcc"]  # fmt: skip
    bundle = res_bundles["grounded"]
    bad = tmp_path / "bad_bundle"
    shutil.copytree(bundle, bad)
    (bad / "sam_encoder.onnx").unlink()
    cases = [
        ([], "give one of --res-masks DIR or --bundle DIR"),
        (["--res-masks", str(room / "res"), "--bundle", str(bundle)], "give one of"),
        (["--bundle", str(bad)], "sam_encoder.onnx is missing"),
    ]
    for extra, words in cases:  # refused before anything is written
        capsys.readouterr()
        assert main(argv + extra) == 2
        err = capsys.readouterr().err
        assert err.startswith("goi: error:") and words in err, err
        assert not out.exists() and not (tmp_path / "r.work").exists()
    assert main(argv + ["--bundle", str(bundle), "--html", str(html)]) == 0
    r = json.loads(out.read_text())
    validate_json(r, "goi.eval", str(out))
    page = html.read_text()
    assert "<b>RES</b>" in page and "bundle:" in page
    for pid, text in (("p1", "<b>object 1</b>"), ("p2", "<b>object 2</b>")):
        views = r["variants"]["full"]["prompts"][pid]["fit_views"]
        assert views and r["variants"]["without_tfcc"]["prompts"][pid]["fit_views"] == views
        for view in views:
            name = f"{safe_name(pid)}_res_{view}.png"
            assert f"r_files/{name}" in page and (tmp_path / "r_files" / name).is_file()
            assert (tmp_path / "r.work" / safe_name(text) / "res" / f"{view}.png").is_file()

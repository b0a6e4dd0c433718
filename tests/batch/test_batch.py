"""goi batch: three tiny synthetic scenes x two prompts as one Snakemake workflow.

Two scenes go the paper's route (extract, init-codebook, fit-field, a query per prompt) and one
the field-free lifted route (a query per prompt). The tests run the real workflow: the dry
run's graph, a local run on 2 jobs, a rerun after one intermediate artifact is deleted (only
what depends on it runs), the cluster-generic executor with a submit command that starts each
job as a local background process, and the configuration's errors.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

pytest.importorskip("yaml")

from goi_cli.main import main  # noqa: E402
from stages.batch.config import load_batch  # noqa: E402
from stages.core.errors import GoiError  # noqa: E402
from tests.batch.scenes import PROMPTS, tiny_scene, write_config  # noqa: E402

FITTED = ("extract", "init-codebook", "fit-field", "query x2")


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("batch")
    out = {}
    for seed, name in enumerate(("a", "b", "c")):
        (root / name).mkdir()
        tiny_scene(root / name, seed)
        out[name] = root / name
    return out


def table(text: str) -> dict[str, list[str]]:
    """The summary table: scene -> [stages run, time, answers]."""
    lines = text.strip().splitlines()
    head = lines.index(next(ln for ln in lines if ln.startswith("scene ")))
    return {
        ln.split()[0]: [c.strip() for c in re.split(r"\s{2,}", ln)[1:]] for ln in lines[head + 1 :]
    }


def snakemake() -> None:
    pytest.importorskip("snakemake")


def photographed(scene: Path, out: Path) -> Path:
    """A copy of a scene directory with an image per camera (what goi index-res reads)."""
    import shutil

    from stages.scene.scene import load_scene

    shutil.copytree(scene, out)
    (out / "images").mkdir()
    for cam in load_scene(out).cameras:
        cv2.imwrite(str(out / "images" / f"{cam.name}.png"), np.zeros((cam.height, cam.width, 3)))
    return out


@pytest.mark.slow
def test_the_dry_run_shows_the_graph(scenes, res_bundles, tmp_path, capfd):
    snakemake()
    cfg = tmp_path / "batch.yaml"
    write_config(cfg, scenes, fieldfree=("c",))
    assert main(["batch", str(cfg), "--dry-run"]) == 0
    cap = capfd.readouterr()
    stats = dict(re.findall(r"^(\w+)\s+(\d+)$", cap.out + cap.err, re.M))
    want = {"extract": "2", "init_codebook": "2", "fit_field": "2", "query": "6", "total": "13"}
    assert {k: stats.get(k) for k in want} == want, (cap.out + cap.err)[-3000:]
    assert "index_res" not in stats
    assert not (tmp_path / "goi-batch" / "a" / "features.h5").exists()  # nothing ran
    # the field-free route with a RES index built first (its bundle and the scene's photos are
    # checked before the run, as goi index-res checks them)
    bundle = res_bundles["grounded"]
    scene = photographed(scenes["c"] / "scene", tmp_path / "scene")
    cfg.write_text(
        f"scenes:\n  - scene: {scene}\n    bundle: {bundle}\n"
        "    res_index: true\n    lift: true\n    prompts: [a chair, a lamp]\n"
    )
    assert main(["batch", str(cfg), "--dry-run"]) == 0
    cap = capfd.readouterr()
    err = cap.out + cap.err
    stats = dict(re.findall(r"^(\w+)\s+(\d+)$", err, re.M))
    assert {k: stats.get(k) for k in ("index_res", "query", "total")} == {
        "index_res": "1",
        "query": "2",
        "total": "4",
    }, err[-3000:]
    assert "extract" not in stats and "fit_field" not in stats
    assert "output: scene/res_index.h5" in err
    assert len(re.findall(r"rule query:\n\s+input: [^\n]*scene/res_index\.h5", err)) == 2


@pytest.mark.slow
def test_a_local_run_then_reruns_only_what_is_out_of_date(scenes, tmp_path, capsys):
    from stages.query.prompts import safe_name
    from stages.query.selection import load_selection

    snakemake()
    cfg = tmp_path / "batch.yaml"
    write_config(cfg, scenes, fieldfree=("c",))
    out = tmp_path / "goi-batch"
    assert main(["batch", str(cfg), "--jobs", "2"]) == 0
    t = table(capsys.readouterr().out)
    assert t["a"][0] == t["b"][0] == ", ".join(FITTED)
    assert t["c"][0] == "query x2"  # the field-free route: no field for it
    assert all(row[2] == "2 new, 2/2" for row in t.values()), t
    for name in ("a", "b", "c"):
        for p in PROMPTS:
            key = safe_name(p)
            sel = load_selection(out / name / "prompts" / key / key / "selection.h5")
            assert sel.prompt == p
            if name == "c":
                assert sel.mode == "lifted"
    assert not (out / "c" / "field.h5").exists()
    # nothing is out of date: nothing runs
    assert main(["batch", str(cfg), "--jobs", "2"]) == 0
    t = table(capsys.readouterr().out)
    assert {k: v[0] for k, v in t.items()} == {"a": "-", "b": "-", "c": "-"}
    assert all(row[2] == "0 new, 2/2" for row in t.values())
    # one intermediate artifact gone, one input changed: only what depends on them runs again
    (out / "a" / "codebook.h5").unlink()
    mask = sorted((scenes["b"] / "res" / "o1").glob("*.png"))[0]
    m = cv2.imread(str(mask), cv2.IMREAD_GRAYSCALE)
    m[0, 0] = 255 - m[0, 0]  # a new RES mask of object 1 on scene b (Snakemake compares
    cv2.imwrite(str(mask), m)  # contents, not only dates: a touched file is not a change)
    assert main(["batch", str(cfg), "--jobs", "2"]) == 0
    t = table(capsys.readouterr().out)
    assert {k: v[0] for k, v in t.items()} == {
        "a": "init-codebook, fit-field, query x2",
        "b": "query x1",
        "c": "-",
    }
    assert t["a"][2] == "2 new, 2/2" and t["b"][2] == "1 new, 2/2"


@pytest.mark.slow
def test_the_cluster_generic_executor_submits_every_job(scenes, tmp_path, capsys):
    """A "cluster" whose submit command starts the job script as a local background process
    and answers with its process id: the jobs really go through the executor plugin."""
    snakemake()
    pytest.importorskip("snakemake_executor_plugin_cluster_generic")
    submitted = tmp_path / "submitted.txt"
    submit = tmp_path / "submit.sh"
    submit.write_text(
        f'#!/bin/sh\necho "$1" >> {submitted}\nnohup sh "$1" > "$1.out" 2>&1 &\necho "$!"\n'
    )
    submit.chmod(0o755)
    cfg = tmp_path / "batch.yaml"
    write_config(cfg, {"c": scenes["c"], "a": scenes["a"]}, fieldfree=("c", "a"))
    args = ["batch", str(cfg), "--executor", "cluster-generic", "--jobs", "4", "--"]
    args += ["--cluster-generic-submit-cmd", str(submit), "--seconds-between-status-checks", "1"]
    assert main(args) == 0
    t = table(capsys.readouterr().out)
    assert t["c"][0] == t["a"][0] == "query x2"
    assert t["c"][2] == t["a"][2] == "2 new, 2/2"
    jobs = submitted.read_text().split()
    assert len(jobs) == 4 and all("snakejob.query" in Path(j).name for j in jobs), jobs


def _error(cfg: Path, text: str) -> str:
    cfg.write_text(text)
    with pytest.raises(GoiError) as e:
        load_batch(cfg)
    assert "\n" not in str(e.value)
    return str(e.value)


def test_configuration_errors_name_the_key_and_its_line(scenes, tmp_path):
    a, b = scenes["a"], scenes["b"]
    one = (
        f"  - scene: {a / 'scene'}\n    features: {a / 'features'}\n    prompts: [object 1]\n"
        f"    text_embeddings: {a / 'text.json'}\n"
    )
    cfg = tmp_path / "c.yaml"
    msg = _error(cfg, "scenes:\n" + one + "    res_mask: r\n")
    assert msg.startswith(f"{cfg}: line 6: unknown key 'scenes[0].res_mask'")
    msg = _error(cfg, "scenes:\n" + one.replace(str(a / "scene"), str(tmp_path / "gone")))
    assert msg == f"{cfg}: line 2: 'scenes[0].scene' {tmp_path / 'gone'}: no such file or directory"
    # two scenes writing the same output directory (both named after their directory)
    twin = tmp_path / "twin" / "scene"
    twin.parent.mkdir()
    twin.symlink_to(b / "scene")
    msg = _error(cfg, "scenes:\n" + one + one.replace(str(a / "scene"), str(twin)))
    assert msg.startswith(f"{cfg}: line 6: scenes[1] and the scene on line 2 both write ")
    assert "give one of them another 'name'" in msg
    msg = _error(cfg, "scenes:\n" + one.replace("[object 1]", "[object 1, object 2, object 1]"))
    assert msg.startswith(f"{cfg}: line 4: scenes[0]: the prompt 'object 1' is given twice")
    msg = _error(cfg, f"scenes:\n  - scene: {a / 'scene'}\n    prompts: [x]\n")
    assert "no features source" in msg and "'lift: true' and a RES source" in msg
    msg = _error(cfg, "defaults: {lift: 3}\nscenes:\n" + one)
    assert msg == f"{cfg}: line 1: 'defaults.lift' should be bool, found a number"
    msg = _error(cfg, 'schema_version: "2.0"\nscenes:\n' + one)
    assert "not readable by this goi" in msg
    msg = _error(cfg, "defaults: {options: {query: {field: f.h5}}}\nscenes:\n" + one)
    assert msg.startswith(f"{cfg}: line 1: 'defaults.options.query.field' is set by goi batch")
    msg = _error(cfg, "a: &a [*a]\n")  # an alias to itself: an endless tree
    assert msg.startswith(f"{cfg}: line 1: nested deeper than 32 levels")
    # JSON too, with its lines
    cfg = tmp_path / "c.json"
    doc = {"scenes": [{"scene": str(a / "scene"), "features": "f", "prompts": ["x"]}]}
    msg = _error(cfg, json.dumps(doc, indent=1).replace('"prompts"', '"promts"'))
    assert msg.startswith(f"{cfg}: line 6: unknown key 'scenes[0].promts'")


def test_the_cli_refuses_a_bad_configuration_in_one_line(scenes, tmp_path, capsys, monkeypatch):
    snakemake()
    a = scenes["a"]
    cfg = tmp_path / "c.yaml"
    cfg.write_text(
        f"defaults:\n  options:\n    fit-field: {{iteratons: 3}}\nscenes:\n"
        f"  - scene: {a / 'scene'}\n    features: {a / 'features'}\n    prompts: [object 1]\n"
        f"    text_embeddings: {a / 'text.json'}\n"
    )
    assert main(["batch", str(cfg)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (
        f"goi: error: {cfg}: line 3: 'options.fit-field.iteratons': goi fit-field has no option "
        "--iteratons (see goi fit-field --help)"
    )
    assert not (tmp_path / "goi-batch").exists()
    # a batch already running on the same output directory: refused before Snakemake starts
    from stages.core.files import output_lock

    cfg.write_text(cfg.read_text().replace("iteratons", "iterations"))
    state = tmp_path / "goi-batch" / ".goi-batch"
    state.mkdir(parents=True)
    with output_lock(state / "run", "--out"):
        assert main(["batch", str(cfg), "--dry-run"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"goi: error: --out: {state / 'run'} is being written by another goi")
    assert "\n" not in err and not (state / "plan.json").exists()
    # without the extra: one line saying what to install
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda n, *a: None if n == "snakemake" else real(n, *a)
    )
    assert main(["batch", str(cfg)]) == 2
    assert capsys.readouterr().err.strip() == (
        "goi: error: goi batch needs Snakemake: pip install 'goi[batch]'"
    )


@pytest.mark.slow
def test_a_failed_job_is_named_with_its_error_and_the_batch_exits_1(scenes, tmp_path, capfd):
    snakemake()
    import shutil

    c = scenes["c"]
    # the masks of object 9 are there but damaged: only the job reading them finds out
    res = tmp_path / "res"
    shutil.copytree(c / "res" / "o1", res / "o1")
    (res / "o9").mkdir()
    for f in (res / "o1").glob("*.png"):
        (res / "o9" / f.name).write_bytes(b"\x89PNG\r\n\x1a\n not an image")
    cfg = tmp_path / "batch.yaml"
    cfg.write_text(
        f"scenes:\n  - scene: {c / 'scene'}\n    res_masks: {res}\n    lift: true\n"
        "    options: {query: {export: none}}\n"
        "    prompts: [{text: object 1, id: o1}, {text: object 9, id: o9}]\n"
    )
    assert main(["batch", str(cfg), "--keep-going"]) == 1
    cap = capfd.readouterr()
    t = table(cap.out)
    assert t["scene"][0] == "query x1; failed: query x1" and t["scene"][2] == "1 new, 1/2"
    last = cap.err.strip().splitlines()[-1]
    assert last.startswith("goi: error: batch: Snakemake stopped with exit status 1; ")
    assert "query-object-9-" in last and "o9" in last, last


@pytest.mark.slow
def test_the_index_is_built_as_parallel_jobs(scenes, res_bundles, tmp_path, capfd):
    """index_jobs: 2: two goi index-res jobs each index a part of the views (at once, with
    --jobs 2), a third merges them; the parts are removed, the index holds every view."""
    from stages.query.res_index import load_res_index
    from stages.scene.scene import load_scene

    snakemake()
    bundle = res_bundles["grounded"]
    scene = photographed(scenes["c"] / "scene", tmp_path / "scene")
    cfg = tmp_path / "batch.yaml"
    cfg.write_text(
        f"scenes:\n  - scene: {scene}\n    bundle: {bundle}\n    res_index: true\n"
        "    index_jobs: 2\n    lift: true\n    prompts: [a chair]\n"
    )
    assert main(["batch", str(cfg), "--dry-run"]) == 0
    err = "".join(capfd.readouterr())
    stats = dict(re.findall(r"^(\w+)\s+(\d+)$", err, re.M))
    want = {"index_res_part": "2", "index_res": "1", "query": "1", "total": "5"}
    assert {k: stats.get(k) for k in want} == want, err[-3000:]
    assert main(["batch", str(cfg), "--jobs", "2"]) == 0
    out = tmp_path / "goi-batch" / "scene"
    index = load_res_index(out / "res_index.h5")
    assert sorted(index.views) == sorted(c.name for c in load_scene(scene).views("train"))
    assert not list(out.glob("res_index.part*"))
    logs = sorted(p.name for p in (out / "logs").glob("index-res*.log"))
    assert logs == ["index-res-1of2.log", "index-res-2of2.log", "index-res.log"]
    assert "views from 2 parts (--merge)" in (out / "logs" / "index-res.log").read_text()
    cfg.write_text(cfg.read_text().replace("res_index: true", "res_index: false"))
    assert main(["batch", str(cfg), "--dry-run"]) == 2
    assert "'scenes[0].index_jobs' is given but 'res_index' is not true" in "".join(
        capfd.readouterr()
    )
    cfg.write_text(cfg.read_text().replace("res_index: false", "res_index: true"))
    cfg.write_text(cfg.read_text().replace("index_jobs: 2", "index_jobs: 200"))
    assert main(["batch", str(cfg), "--dry-run"]) == 2
    assert "training views to share out" in "".join(capfd.readouterr())

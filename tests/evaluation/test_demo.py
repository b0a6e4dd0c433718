"""The demo end to end, with fewer field iterations, on the scene shipped with goi."""

from pathlib import Path

import pytest

import goi_cli
from goi_cli.main import main
from stages.evaluation.demo import DEMO_SCENE, DemoParams, DemoRun, run_demo
from stages.query.prompts import safe_name
from stages.scene.gaussians import load_ply


def test_demo_scene_is_small_and_attributed():
    size = sum(f.stat().st_size for f in DEMO_SCENE.rglob("*") if f.is_file())
    assert size <= 25 * 2**20
    assert "CC0" in (DEMO_SCENE / "ATTRIBUTION.md").read_text()


@pytest.mark.slow
def test_demo_finds_the_prompts_objects(tmp_path):
    res = run_demo(DemoParams(iterations=300, prompts="p01,p08"), DemoRun(out=tmp_path))
    ious = {a.prompt.id: a.iou for a in res.answers}
    assert max(ious.values()) >= 0.5, ious
    lifted = {a.prompt.id: a.lifted_iou for a in res.answers}
    assert max(lifted.values()) >= 0.5, lifted  # both answers are shown, and both find it
    page = (tmp_path / "index.html").read_text()
    assert "orange basketball" in page and ".overlay.png" in page
    assert "lifted" in page and "lifted/" in page
    for a in res.answers:
        r = a.result
        assert len(load_ply(r.ply).vertex) == r.n_selected > 0
        assert a.strays is not None and all(0 <= x <= 1 for x in a.strays)
    assert "<th>strays</th>" in page
    # the CLI runs it too, over the outputs of a previous run
    assert main(["demo", "--out", str(tmp_path), "--iterations", "20", "--prompts", "p08"]) == 0
    assert main(["demo", "--out", str(tmp_path), "--prompts", "p99"]) == 2


@pytest.mark.slow
def test_demo_with_a_res_bundle_shows_the_res_masks(tmp_path, res_bundles):
    """goi demo --bundle: the bundle's RES makes the masks; the page shows the ones used."""
    argv = ["demo", "--out", str(tmp_path), "--iterations", "20", "--prompts", "p08",
            "--bundle", str(res_bundles["grounded"])]  # fmt: skip
    assert main(argv) == 0
    page = (tmp_path / "index.html").read_text()
    res = next((tmp_path / "queries").glob("*/res"))
    views = sorted(p.stem for p in res.glob("*.png"))
    assert views and "<b>RES</b>" in page
    for view in views:
        name = f"{safe_name('p08')}_res_{view}.png"
        assert f"index_files/{name}" in page and (tmp_path / "index_files" / name).is_file()
    assert main(["demo", "--out", str(tmp_path / "x"), "--bundle", str(tmp_path)]) == 2
    assert not (tmp_path / "x").exists()


@pytest.mark.slow
def test_demo_from_a_res_index_runs_only_the_prompt_side(tmp_path, res_bundles):
    """goi index-res on the demo scene, then goi demo --res-index: the masks the fits used come
    from the index (the scene's photos), written and shown as with --bundle alone; an index of
    another bundle is refused before any work."""
    scene = Path(goi_cli.__file__).parent / "demo_scene"
    index = tmp_path / "index.h5"
    argv = ["index-res", "--scene", str(scene), "--bundle", str(res_bundles["grounded"]),
            "--out", str(index)]  # fmt: skip
    assert main(argv) == 0
    out = tmp_path / "demo"
    argv = ["demo", "--out", str(out), "--iterations", "20", "--prompts", "p08",
            "--bundle", str(res_bundles["grounded"]), "--res-index", str(index)]  # fmt: skip
    assert main(argv) == 0
    page = (out / "index.html").read_text()
    res = next((out / "queries").glob("*/res"))
    views = sorted(p.stem for p in res.glob("*.png"))
    assert views and "<b>RES</b>" in page
    assert main([*argv[:-4], "--bundle", str(res_bundles["clipseg"]), "--res-index",
                 str(index), "--out", str(tmp_path / "other")]) == 2  # fmt: skip
    assert not (tmp_path / "other").exists()

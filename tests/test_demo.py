"""The demo end to end, with fewer field iterations, on the scene shipped with goi."""

import pytest

from goi_cli.main import main
from stages.demo import DEMO_SCENE, DemoOptions, run_demo
from stages.gaussians import load_ply


def test_demo_scene_is_small_and_attributed():
    size = sum(f.stat().st_size for f in DEMO_SCENE.rglob("*") if f.is_file())
    assert size <= 25 * 2**20
    assert "CC0" in (DEMO_SCENE / "ATTRIBUTION.md").read_text()


@pytest.mark.slow
def test_demo_finds_the_prompts_objects(tmp_path):
    res = run_demo(DemoOptions(out=tmp_path, iterations=300, prompts="p01,p08"), say=lambda s: None)
    ious = {e["prompt"].id: e["iou"] for e in res["results"]}
    assert max(ious.values()) >= 0.5, ious
    page = (tmp_path / "index.html").read_text()
    assert "orange basketball" in page and ".overlay.png" in page
    for e in res["results"]:
        r = e["result"]
        assert len(load_ply(r.ply).vertex) == r.n_selected > 0
    # the CLI runs it too, over the outputs of a previous run
    assert main(["demo", "--out", str(tmp_path), "--iterations", "20", "--prompts", "p08"]) == 0
    assert main(["demo", "--out", str(tmp_path), "--prompts", "p99"]) == 2

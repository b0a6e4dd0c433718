"""The demo end to end, with fewer field iterations, on the scene shipped with goi."""

import pytest

from goi_cli.main import main
from stages.evaluation.demo import DEMO_SCENE, DemoParams, DemoRun, run_demo
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
    # the CLI runs it too, over the outputs of a previous run
    assert main(["demo", "--out", str(tmp_path), "--iterations", "20", "--prompts", "p08"]) == 0
    assert main(["demo", "--out", str(tmp_path), "--prompts", "p99"]) == 2

"""--work reuse keyed on the cameras' values, and a room read in Gaussian Grouping's LERF-Mask
release layout scored as the room's own eval scores it, prompt by prompt and view by view."""

import json

import h5py
import pytest

from goi_cli.main import main
from stages.evaluation.pipeline import (
    CAMERA_TOLERANCE,
    FitCameras,
    _reusable,
    camera_difference,
    camera_values,
)
from stages.scene.formats import load_cameras
from stages.scene.scene import load_scene
from stages.testing.public_layouts import room_as_lerf_mask
from stages.testing.synthetic import ring_cameras
from tests.evaluation.test_eval import make_room


class Lines:
    def __init__(self):
        self.lines = []

    def log(self, message):
        self.lines.append(message)

    def progress(self, items, label, length=None, show=None):
        yield from items


def _moved(values, view, k, by):
    out = {n: list(v) for n, v in values.items()}
    out[view][k] += by
    return out


def test_camera_values_within_the_tolerance_are_the_same_cameras():
    cams = ring_cameras(4, 64, 48)
    v = camera_values(cams)
    name = cams[1].name
    assert camera_difference(v, v) is None
    assert camera_difference(v, _moved(v, name, 8, 2e-7)) is None  # a COLMAP round trip
    fx = v[name][2]
    assert fx > 10 and camera_difference(v, _moved(v, name, 2, fx * 0.5e-6)) is None  # relative
    why = camera_difference(v, _moved(v, name, 16, 5e-6))
    assert why == f"view {name}'s translation differs by 5e-06, more than {CAMERA_TOLERANCE:g}"
    assert "rotation differs" in camera_difference(v, _moved(v, name, 6, 1e-4))
    assert "intrinsics differs" in camera_difference(v, _moved(v, name, 3, 0.01))
    assert camera_difference(v, _moved(v, name, 0, 1)) == f"view {name} is 65x48, was 64x48"
    fewer = {n: x for n, x in v.items() if n != name}
    assert camera_difference(v, fewer) == f"other training views: 1 view(s) gone, e.g. {name}"
    assert "a malformed record" in camera_difference({**v, name: [1.0]}, v)


def test_a_work_records_the_values_under_each_camera_files_digest(tmp_path):
    s, room = make_room(tmp_path)
    scene = load_scene(room)
    cams = FitCameras(tmp_path, scene)
    assert cams.why_not(scene.cameras_digest()) is None
    assert "did not record" in cams.why_not("0" * 64)
    cams.record()
    again = FitCameras(tmp_path, scene)
    again.digest = "f" * 64  # the same cameras read from other files
    assert again.why_not(scene.cameras_digest()) is None
    again.values = _moved(again.values, scene.train[0], 15, 1e-3)
    assert "other cameras (view" in again.why_not(scene.cameras_digest())
    (tmp_path / "fit_cameras.json").write_text('{"schema": "goi.eval_work_cameras", "sch')
    assert FitCameras(tmp_path, scene).records == {}  # a damaged record reuses nothing


def _plain_room(tmp_path):
    """make_room's room with plain prompt texts (the release files a mask under its text)."""
    s, room = make_room(tmp_path)
    prompts = json.loads((room / "prompts.json").read_text())
    emb = json.loads((room / "text_embeddings.json").read_text())
    for p in prompts:
        new = p["text"].replace("<b>", "").replace("</b>", "")
        emb[new] = emb.pop(p["text"])
        p["text"] = new
    (room / "prompts.json").write_text(json.dumps(prompts))
    (room / "text_embeddings.json").write_text(json.dumps(emb))
    return s, room, prompts


@pytest.mark.slow
def test_a_room_in_the_lerf_mask_release_layout_scores_as_the_room_with_its_field(tmp_path, capsys):
    """The room's own eval fits a field in WORK/toy; the room written as Gaussian Grouping
    releases LERF-Mask (COLMAP text cameras, numbered test_mask folders) reuses that fit, as
    its cameras are the same by value, and `full` and `lifted` score every (prompt, view) as
    the room's eval does."""
    s, room, prompts = _plain_room(tmp_path)
    work = tmp_path / "work"
    common = ["--features", str(s["features"]), "--iterations", "60", "--entries", "16",
              "--variants", "full,lifted"]  # fmt: skip
    own = tmp_path / "own.json"
    argv = ["eval", str(room), "--res-masks", str(room / "res"), "--out", str(own),
            "--work", str(work / "toy"), *common]  # fmt: skip
    assert main(argv) == 0
    conv = room_as_lerf_mask(room, tmp_path / "lerf_mask", "toy")
    assert len(load_cameras(conv["bench"] / "toy" / "sparse" / "0")) == 8
    capsys.readouterr()
    out = tmp_path / "bench.json"
    argv = ["eval", "--benchmark", "lerf-mask", str(conv["bench"]), "--scene", f"toy={room}",
            "--res-masks", str(conv["res"]), "--text-embeddings",
            str(room / "text_embeddings.json"), "--work", str(work), "--out", str(out),
            *common]  # fmt: skip
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert "goi: warning: --scene toy: not one of lerf-mask's released scenes" in err
    for f in ("features.h5", "codebook.h5", "field_tfcc.h5"):
        assert f"reusing {work / 'toy' / f} (same inputs)" in err, err
    a, b = json.loads(own.read_text()), json.loads(out.read_text())
    assert "fit_field_tfcc" not in b["timings_s"] and "extract" in b["timings_s"]
    scene = b["benchmark"]["scenes"]["toy"]
    assert scene["layout"].startswith("numbered") and scene["frames"] == {
        str(k): v for k, v in enumerate(conv["tests"]) if str(k) in scene["frames"]
    }
    n = 0
    for v in ("full", "lifted"):
        for p in prompts:
            for view, figs in a["variants"][v]["prompts"][p["id"]]["views"].items():
                k = str(conv["tests"].index(view))
                got = scene["variants"][v]["queries"][p["text"]][k]["iou"]
                assert got == pytest.approx(figs["iou"], abs=1e-12), (v, p["id"], view)
                n += 1
        assert scene["variants"][v]["goi"]["miou"] == pytest.approx(a["variants"][v]["miou"])
    assert n == 2 * sum(len(p["test_views"]) for p in prompts) > 0
    # the cameras moved by more than the tolerance: the fit is not reused, and a line says why
    cams = FitCameras(work / "toy", load_scene(room))
    cams.digest = "moved"
    cams.values = _moved(cams.values, next(iter(cams.values)), 15, 1e-3)
    lines = Lines()
    with h5py.File(work / "toy" / "features.h5", "r") as f:
        want = {**json.loads(f.attrs["inputs"]), "cameras": "moved"}
    assert not _reusable(work / "toy" / "features.h5", "goi.features", want, lines, cameras=cams)
    assert lines.lines == [
        f"eval: making {work / 'toy' / 'features.h5'} again: it was made from other cameras "
        f"(view {next(iter(cams.values))}'s translation differs by 0.001, more than 1e-06)"
    ]

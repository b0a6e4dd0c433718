"""goi view's state without a browser: every route's answer is goi select's, bit for bit; the
answer refines and can be cancelled; the history; the mask at a camera is what goi
render-mask --camera-file writes; exports are the CLI's artifacts and never replace a file
goi view did not write."""

import json
import threading

import numpy as np
import pytest

from goi_cli.main import main
from stages.core.errors import GoiError
from stages.query.pipeline import PromptSources
from stages.query.selection import load_selection
from stages.scene.images import read_mask
from stages.scene.scene import load_scene
from stages.view.session import ViewRun, ViewSession
from stages.view.worker import Cancelled, Control
from tests.helpers import write_true_res

OBJ = 2
PROMPT = f"object {OBJ}"


@pytest.fixture(scope="module")
def room(fitted, tmp_path_factory):
    """The fitted synthetic scene with text embeddings, true RES masks per object (o<k>/) and a
    prompts.json that names them."""
    s, run = fitted
    root = tmp_path_factory.mktemp("view")
    write_true_res(s, root, range(len(s["objects"])))
    prompts = [{"id": f"o{k}", "text": f"object {k}"} for k in range(len(s["objects"]))]
    (root / "prompts.json").write_text(json.dumps(prompts))
    return s, run, root


def _session(room, out, field=True, **sources) -> ViewSession:
    s, run, root = room
    src = {"text_embeddings": root / "text.json", "res_masks": root / "res", **sources}
    return ViewSession(
        load_scene(s["scene"]),
        run / "field.h5" if field else None,
        PromptSources(**src),
        ViewRun(out=out, prompts=root / "prompts.json"),
    )


def _cli(room, *args, field=True):
    s, run, root = room
    base = ["--scene", str(s["scene"]), "--prompt", PROMPT, "--text-embeddings",
            str(root / "text.json"), "--res-masks", str(root / "res"),
            "--prompt-id", f"o{OBJ}"]  # fmt: skip
    if field:
        base += ["--field", str(run / "field.h5")]
    assert main([args[0], *base, *args[1:]]) == 0


@pytest.mark.slow
@pytest.mark.parametrize("route", ["lifted", "lifted_fieldless"])
def test_a_lifted_answer_is_goi_selects(room, tmp_path, route):
    session = _session(room, tmp_path / "view", field=route == "lifted")
    partials = []
    ans = session.answer(PROMPT, route, Control(partial=partials.append, partial_every=0.0))
    _cli(room, "select", "--lift", "--out", str(tmp_path / "sel.h5"), field=route == "lifted")
    cli = load_selection(tmp_path / "sel.h5")
    np.testing.assert_array_equal(ans.selected, cli.selected)
    assert ans.final and ans.count > 0 and ans.route == route
    # it refined: partial answers on fewer views came first, none of them final
    assert partials and all(not p.final for p in partials)
    assert [p.views_done for p in partials] == sorted(p.views_done for p in partials)
    assert partials[-1].views_done < ans.views_done == ans.views_total
    if route == "lifted":  # previews: the fixed-threshold plane decides what no view reaches
        assert all(p.lifted.plane.info == {} for p in partials) and ans.lifted.plane.info


@pytest.mark.slow
def test_the_papers_routes_are_goi_selects(room, tmp_path):
    session = _session(room, tmp_path / "view")
    osh = session.answer(PROMPT, "osh")
    thr = session.answer(PROMPT, "threshold")
    h = tmp_path / "planes.h5"
    _cli(room, "fit-hyperplane", "--out", str(h))
    for mode, ans in (("hyperplane", osh), ("threshold", thr)):
        out = tmp_path / f"{mode}.h5"
        _cli(room, "select", "--hyperplanes", str(h), "--mode", mode, "--out", str(out))
        np.testing.assert_array_equal(ans.selected, load_selection(out).selected)
    # the OSH went into the viewer's prompt cache, so the field's first answer is that plane
    first = session.field_answer(PROMPT)
    assert first is not None and first.route == "osh" and "cached" in first.label
    np.testing.assert_array_equal(first.selected, osh.selected)
    assert session.answer(PROMPT, "osh").label.endswith("(cached)")


@pytest.mark.slow
def test_field_answer_without_a_cached_plane_is_the_threshold(room, tmp_path):
    session = _session(room, tmp_path / "view")
    first = session.field_answer(PROMPT)
    assert first is not None and first.route == "threshold"
    np.testing.assert_array_equal(first.selected, session.answer(PROMPT, "threshold").selected)
    assert _session(room, tmp_path / "v2", field=False).field_answer(PROMPT) is None


@pytest.mark.slow
def test_cancel_stops_an_answer_between_views(room, tmp_path):
    session = _session(room, tmp_path / "view")
    control = Control()
    seen = []

    def progress(done, total, what):
        seen.append(done)
        if done == 2:
            control.cancelled.set()

    control.progress = progress
    with pytest.raises(Cancelled):
        session.answer(PROMPT, "lifted", control)
    assert max(seen) == 2


@pytest.mark.slow
@pytest.mark.parametrize("route", ["lifted", "osh"])
def test_the_mask_at_a_camera_is_what_render_mask_writes(room, tmp_path, route):
    s, run, root = room
    session = _session(room, tmp_path / "view")
    ans = session.answer(PROMPT, route)
    from stages.view.cameras import browser_camera, browser_pose

    wxyz, pos, fov = browser_pose(s["cameras"][s["test"][0]])
    cam = browser_camera("browser", wxyz, pos + 0.05, fov, 120, 80)  # a novel view
    shown = session.mask_at(ans, cam)
    assert shown.mask.any() and shown.overlay.shape == (80, 120, 3)
    camera_file = session.save_camera(cam)
    planes = tmp_path / "view" / "hyperplanes.h5"
    extra = ["--lift"] if route == "lifted" else ["--hyperplanes", str(planes)]
    _cli(
        room, "render-mask", "--camera-file", str(camera_file), "--out", str(tmp_path / "m"), *extra
    )
    name = camera_file.stem
    np.testing.assert_array_equal(read_mask(tmp_path / "m" / f"{name}.png"), shown.mask)
    import cv2

    written = cv2.imread(str(tmp_path / "m" / f"{name}.overlay.png"))[:, :, ::-1]
    np.testing.assert_array_equal(written, shown.overlay)


@pytest.mark.slow
def test_exports_are_the_clis_artifacts(room, tmp_path):
    s, run, root = room
    out = tmp_path / "view"
    session = _session(room, out)
    ans = session.answer(PROMPT, "lifted")
    (sel_path,) = session.export(ans, "selection")
    _cli(room, "select", "--lift", "--out", str(tmp_path / "sel.h5"))
    mine, cli = load_selection(sel_path), load_selection(tmp_path / "sel.h5")
    np.testing.assert_array_equal(mine.selected, cli.selected)
    assert mine.mode == "lifted" and mine.lifted["views"] == cli.lifted["views"]
    from stages.scene.gaussians import load_ply

    (ply,) = session.export(ans, "subset")
    assert load_ply(ply).count == ans.count
    (inv,) = session.export(ans, "invert")
    assert load_ply(inv).count == ans.selected.size - ans.count
    masks = session.export(ans, "masks")
    _cli(room, "render-mask", "--lift", "--out", str(tmp_path / "m"))
    for m in masks:
        assert m.read_bytes() == (tmp_path / "m" / m.name).read_bytes()
    # exporting again replaces goi view's own files
    assert session.export(ans, "selection") == [sel_path]


@pytest.mark.slow
def test_exports_never_replace_a_file_goi_view_did_not_write(room, tmp_path):
    out = tmp_path / "view"
    session = _session(room, out, field=False)
    ans = session.answer(PROMPT, "lifted_fieldless")
    target = session.answer_dir(ans) / "selection.h5"
    target.parent.mkdir(parents=True)
    target.write_text("mine")
    with pytest.raises(GoiError, match="not written by goi view"):
        session.export(ans, "selection")
    assert target.read_text() == "mine"
    target.unlink()
    (path,) = session.export(ans, "selection")
    path.write_bytes(path.read_bytes() + b"edited")  # changed since goi view wrote it
    with pytest.raises(GoiError, match="changed since"):
        session.export(ans, "selection")


@pytest.mark.slow
def test_routes_the_inputs_do_not_allow_are_refused_with_the_reason(room, tmp_path):
    s, run, root = room
    session = _session(room, tmp_path / "view", field=False)
    routes = session.routes()
    assert routes["lifted_fieldless"] is None
    assert "--field" in routes["osh"] and "--field" in routes["threshold"]
    with pytest.raises(GoiError, match="--field"):
        session.answer(PROMPT, "osh")
    text_only = _session(room, tmp_path / "v2", res_masks=None)
    assert "RES" in text_only.routes()["lifted"] and text_only.routes()["threshold"] is None
    assert text_only.default_route() == "threshold"
    with pytest.raises(GoiError, match="prompt: the prompt is empty"):
        session.answer("  ", "lifted_fieldless")
    with pytest.raises(GoiError, match="at most"):
        session.answer("x" * 301, "lifted_fieldless")


def test_bad_view_inputs_exit_2_before_serving(fitted, tmp_path, capsys):
    s, run = fitted
    scene = ["--scene", str(s["scene"])]
    (tmp_path / "file").write_text("x")
    (tmp_path / "e.json").write_text(json.dumps({"a prompt": [1.0, 2.0]}))  # 2 dimensions
    cases = [
        ([], "nothing to answer a prompt with"),
        (
            ["--field", str(run / "field.h5"), "--route", "lifted"],
            "--route: lifted is not possible",
        ),
        (["--res-masks", str(tmp_path), "--out", str(tmp_path / "file")], "--out"),
        (["--res-masks", str(tmp_path / "nope")], "--res-masks"),
        (["--res-masks", str(tmp_path), "--prompts", str(tmp_path / "file")], "file"),
        (["--res-masks", str(tmp_path), "--port", "70000"], "--port"),
        (["--res-masks", str(tmp_path), "--max-splats", "0"], "--max-splats"),
        (
            ["--field", str(run / "field.h5"), "--text-embeddings", str(tmp_path / "e.json")],
            "embeddings of 2 dimensions",
        ),
    ]
    for args, message in cases:
        assert main(["view", *scene, *args, "--for-seconds", "0.1"]) == 2, args
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err and err.count("goi: error") == 1, err
        assert len(err.strip().splitlines()) == 1, err  # no line of work before the refusal


def test_control_report_stops_when_cancelled():
    from stages.view.session import ControlReport

    control = Control()
    seen = []
    report = ControlReport(control)
    with pytest.raises(Cancelled):
        for i in report.progress(range(5), "x"):
            seen.append(i)
            if i == 1:
                control.cancelled.set()
    assert seen == [0, 1]
    assert isinstance(control.cancelled, threading.Event)


@pytest.mark.slow
def test_every_file_goi_view_writes_is_recorded(room, tmp_path):
    """The plane cache the paper's route fills is goi view's file like its exports: recorded
    in goi-view.json, and one goi view did not write is never replaced."""
    out = tmp_path / "view"
    session = _session(room, out)
    session.answer(PROMPT, "osh")
    listed = json.loads((out / "goi-view.json").read_text())["files"]
    assert "hyperplanes.h5" in listed
    other = tmp_path / "other"
    other.mkdir()
    (other / "hyperplanes.h5").write_text("mine")
    with pytest.raises(GoiError, match="not written by goi view"):
        _session(room, other).answer(PROMPT, "osh")
    assert (other / "hyperplanes.h5").read_text() == "mine"


@pytest.mark.slow
def test_the_view_cache_serves_an_answers_pass_when_not_every_view_fits(
    room, tmp_path, monkeypatch
):
    """The rasteriser keeps views' projections least recently used first: a pass over more
    views than fit would find none kept. The viewer keeps only the views that fit, so the next
    answer projects only the others."""
    import stages.render.rasterizer as rasterizer
    from stages.render.rasterizer import Rasterizer

    s, run, root = room
    session = _session(room, tmp_path / "view", field=False)
    train = session.scene.views("train")
    r = session.rast
    probe = Rasterizer(r.means, r.quats, r.scales, r.opacities, r.sh, r.valid)
    probe.keep_views(1 << 62, [train[0]])
    probe.prepare(train[0])
    probe.view(train[0])
    session.view_cache_bytes = int(3.5 * probe.kept_bytes())  # 3 of the views fit
    session.rast.keep_views(session.view_cache_bytes, session.scene.views("all"))
    assert len(session.fit_view_cache()) == 3 < len(train)
    session.answer("object 1", "lifted_fieldless")
    projected = []
    real = rasterizer.project

    def counted(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        projected.append(args[-1].name)
        return real(*args, **kwargs)

    monkeypatch.setattr(rasterizer, "project", counted)
    session.answer(PROMPT, "lifted_fieldless")
    lifted = [v for v in projected if v in {c.name for c in train}]
    assert lifted and not {c.name for c in train[:3]} & set(lifted)

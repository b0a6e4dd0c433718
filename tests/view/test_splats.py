"""What the browser is sent: splats (held to a plain per-Gaussian reference and to viser's own
packing), the chunks a highlight resends, the browser's camera as a goi Camera and back, and
the worker's cancel and priority rules."""

import math
import threading
import time

import numpy as np
import pytest

from stages.scene.cameras import Camera
from stages.scene.gaussians import load_ply
from stages.scene.rotation import quat_to_rotmat
from stages.view.cameras import browser_camera, browser_pose, render_size
from stages.view.splats import (
    covariances,
    morton_order,
    pack,
    plan,
    rgba_words,
    scene_splats,
)
from stages.view.worker import Cancelled, Control, Gate, Worker
from tests.helpers import random_vertex, write_ply


@pytest.fixture
def gaussians(tmp_path):
    return load_ply(write_ply(tmp_path / "g.ply", random_vertex(3000, seed=3)))


def test_covariances_equal_a_plain_loop(gaussians):
    g = gaussians
    covs = covariances(g.quats, g.scales)
    for i in range(0, g.count, 97):
        R = quat_to_rotmat(g.quats[i])
        ref = R @ np.diag(g.scales[i].astype(np.float64) ** 2) @ R.T
        np.testing.assert_allclose(covs[i], ref, rtol=1e-5, atol=1e-8)


def test_pack_is_vivers_buffer(gaussians):
    viser = pytest.importorskip("viser")
    s = scene_splats(gaussians, 10**9)
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        h = server.scene.add_gaussian_splats(
            "/g", centers=s.centers, covariances=s.covariances, rgbs=s.rgbs, opacities=s.opacities
        )
        np.testing.assert_array_equal(pack(s.centers, s.covariances, s.rgbs, s.opacities), h.buffer)
    finally:
        server.stop()


def test_scene_splats_keep_the_most_visible_when_capped(gaussians):
    g = gaussians
    whole = scene_splats(g, 10**9)
    assert sorted(whole.index.tolist()) == list(range(g.count))
    capped = scene_splats(g, 500)
    assert capped.count == 500 and capped.n_scene == g.count
    s = np.sort(g.scales, axis=1)
    imp = g.opacities * s[:, 1] * s[:, 2]
    assert imp[capped.index].min() >= np.sort(imp)[-500] - 1e-12
    # Morton order: a permutation, nearby points close in it
    order = morton_order(g.means)
    assert sorted(order.tolist()) == list(range(g.count))


def test_a_highlight_resends_only_the_chunks_it_touches(gaussians):
    s = scene_splats(gaussians, 10**9)
    chunks = s.chunks(500)
    shown = [b"base"] * len(chunks)
    sel = np.zeros(s.n_scene, bool)
    sel[s.index[chunks[2]][:40]] = True  # selected Gaussians, all in the third chunk
    red = np.array([1.0, 0.0, 0.0], np.float32)
    p = plan(s, chunks, shown, sel, "tint", red)
    assert list(p.chunk_words) == [2] and p.scene_visible and p.overlay.size == 0
    words = p.chunk_words[2].view(np.uint8).reshape(-1, 4)
    assert (words[:40, 0] >= s.rgbs[chunks[2]][:40, 0] * 255 - 1).all()
    np.testing.assert_array_equal(
        p.chunk_words[2][40:], rgba_words(s.rgbs[chunks[2]], s.opacities[chunks[2]])[40:]
    )
    # the same again sends nothing; another mode resends the same chunk; nothing restores it
    assert plan(s, chunks, p.chunk_keys, sel, "tint", red).chunk_words == {}
    hide = plan(s, chunks, p.chunk_keys, sel, "hide", red)
    assert list(hide.chunk_words) == [2]
    assert (hide.chunk_words[2][:40].view(np.uint8).reshape(-1, 4)[:, 3] == 0).all()
    back = plan(s, chunks, hide.chunk_keys, None, "tint", red)
    np.testing.assert_array_equal(
        back.chunk_words[2], rgba_words(s.rgbs[chunks[2]], s.opacities[chunks[2]])
    )
    iso = plan(s, chunks, back.chunk_keys, sel, "isolate", red)
    assert not iso.scene_visible and iso.chunk_words == {}
    np.testing.assert_array_equal(iso.overlay, np.flatnonzero(sel))


def test_tint_draws_selected_gaussians_the_browser_was_not_sent(gaussians):
    s = scene_splats(gaussians, 1000)
    sel = np.ones(s.n_scene, bool)
    p = plan(s, s.chunks(), [b"base"] * len(s.chunks()), sel, "tint", np.ones(3, np.float32))
    unsent = np.setdiff1d(np.arange(s.n_scene), s.index)
    np.testing.assert_array_equal(p.overlay, unsent)
    assert p.overlay_tinted


def test_heat_colours_every_splat_by_its_score(gaussians):
    from stages.view.splats import HEAT_STOPS, heat_colors, to_uint8

    s = scene_splats(gaussians, 10**9)
    chunks = s.chunks(500)
    score = np.zeros(s.n_scene, np.float32)
    score[s.index[chunks[1]][:10]] = 1.0  # certain
    score[s.index[chunks[1]][10:20]] = 0.5  # at the cut
    red = np.ones(3, np.float32)
    p = plan(s, chunks, [b"base"] * len(chunks), score > 0, "heat", red, score)
    assert sorted(p.chunk_words) == list(range(len(chunks))) and p.scene_visible
    rgba = p.chunk_words[1].view(np.uint8).reshape(-1, 4)
    np.testing.assert_array_equal(rgba[:10, :3], np.repeat(to_uint8(HEAT_STOPS[-1:]), 10, 0))
    mid = np.repeat(to_uint8(HEAT_STOPS[2:3]), 10, 0).astype(int)  # (the score sent as a byte)
    np.testing.assert_allclose(rgba[10:20, :3].astype(int), mid, atol=3)
    grey = rgba[20:, :3].astype(int)
    assert (grey.max(1) - grey.min(1) <= 1).all()  # a score of 0: grey, the splat's own
    # the same scores again send nothing; another score resends its chunk only
    assert plan(s, chunks, p.chunk_keys, score > 0, "heat", red, score).chunk_words == {}
    score[s.index[chunks[3]][0]] = 0.9
    again = plan(s, chunks, p.chunk_keys, score > 0, "heat", red, score)
    assert list(again.chunk_words) == [3]
    # without a score the selection itself is the heat
    binary = plan(s, chunks, [b"base"] * len(chunks), score > 0, "heat", red, None)
    np.testing.assert_array_equal(binary.chunk_words[1][:10], p.chunk_words[1][:10])
    assert heat_colors(np.ones((2, 3)), np.array([0.0, 1.0])).shape == (2, 3)


def test_selections_combine_with_their_scores():
    from stages.view.selections import combine, refined_score, stretched

    a = np.array([1, 1, 0, 0], bool)
    b = np.array([1, 0, 1, 0], bool)
    sa = np.array([0.9, 0.6, 0.3, 0.0], np.float32)
    sb = np.array([0.8, 0.4, 0.7, 0.1], np.float32)
    cases = {
        "union": (a | b, np.maximum(sa, sb)),
        "intersection": (a & b, np.minimum(sa, sb)),
        "difference": (a & ~b, np.minimum(sa, 1 - sb)),
    }
    for op, (sel, score) in cases.items():
        got, s = combine(op, a, b, sa, sb)
        np.testing.assert_array_equal(got, sel)
        np.testing.assert_allclose(s, score, atol=1e-7)
    got, s = combine("invert", a, None, sa)
    np.testing.assert_array_equal(got, ~a)
    np.testing.assert_allclose(s, 1 - sa, atol=1e-7)
    got, s = combine("union", a, b)  # no scores: the selections as 0 / 1
    np.testing.assert_array_equal(s, (a | b).astype(np.float32))
    # a click's last round refines the base's score: plus the union, minus the difference
    share, evident = np.array([0.2, 0.9, 0.7, 0.5], np.float32), np.array([1, 1, 1, 0], bool)
    np.testing.assert_allclose(
        refined_score(a, sa, share, evident, True), [0.9, 0.9, 0.7, 0.0], atol=1e-7
    )
    np.testing.assert_allclose(
        refined_score(a, sa, share, evident, False), [0.8, 0.1, 0.3, 0.0], atol=1e-7
    )
    # stretched about the cut: the cut in the middle, the farthest score at an end, 0 kept
    st = stretched(np.array([0.0, 0.27, 0.5, 0.6, 0.73], np.float32))
    np.testing.assert_allclose(st, [0.0, 0.0, 0.5, 0.5 + 0.1 / 0.46, 1.0], atol=1e-6)


def test_browser_camera_round_trip():
    R = quat_to_rotmat(np.array([0.9, 0.1, -0.3, 0.2]))
    cam = Camera("c", 640, 400, 500.0, 500.0, 320, 200, R, np.array([0.1, -0.2, 2.0]))
    wxyz, pos, fov = browser_pose(cam)
    back = browser_camera("c", wxyz, pos, fov, 640, 400)
    np.testing.assert_allclose(back.R, cam.R, atol=1e-9)
    np.testing.assert_allclose(back.t, cam.t, atol=1e-9)
    assert math.isclose(back.fy, 500.0) and back.cx == 320 and back.cy == 200
    assert render_size(1280, 800) == (640, 400) and render_size(300, 900) == (213, 640)


def test_browser_camera_refuses_a_broken_pose():
    from stages.core.errors import GoiError

    with pytest.raises(GoiError):
        browser_camera("c", [np.nan, 0, 0, 1], [0, 0, 0], 1.0, 10, 10)
    with pytest.raises(GoiError):
        browser_camera("c", [1, 0, 0, 0], [0, 0, 0], 4.0, 10, 10)


def test_worker_runs_in_order_and_a_page_supersedes_only_its_own_job():
    errors = []
    w = Worker(lambda job, e: errors.append(e))
    ran = []
    release = threading.Event()

    def slow(name):
        def run(control):
            for _ in range(3000):  # up to 30 s: the test releases it long before
                control.check()
                if release.wait(0.01):
                    break
            ran.append(name)

        return run

    a1 = w.submit(1, slow("a1"), Control())
    b1 = w.submit(2, slow("b1"), Control())
    a2 = w.submit(1, slow("a2"), Control())  # page 1 asks again: its first job is cancelled
    release.set()
    for j in (a1, b1, a2):
        assert j.done.wait(10)
    assert ran == ["b1", "a2"] and not errors
    w.stop()


def test_a_flood_of_requests_from_a_page_keeps_one_job_of_it():
    """A page that asks 10,000 times while the worker is busy costs one waiting job, not a
    queue of cancelled ones (each submit is O(1))."""
    w = Worker(lambda job, e: None)
    release = threading.Event()
    busy = w.submit(0, lambda control: release.wait(30), Control())
    jobs = [w.submit(1, lambda control: None, Control()) for _ in range(10_000)]
    assert w.pending(lambda owner: owner == 1) == 1
    assert all(j.control.cancelled.is_set() and j.done.is_set() for j in jobs[:-1])
    release.set()
    assert busy.done.wait(10) and jobs[-1].done.wait(10)
    assert not jobs[-1].control.cancelled.is_set()
    w.stop()


def test_worker_reports_errors_and_carries_on():
    errors = []
    w = Worker(lambda job, e: errors.append((job.owner, str(e))))

    def boom(control):
        raise ValueError("bad")

    j = w.submit(7, boom, Control())
    ok = w.submit(8, lambda control: None, Control())
    assert j.done.wait(5) and ok.done.wait(5)
    assert errors == [(7, "bad")]
    w.stop()
    with pytest.raises(Cancelled):
        c = Control()
        c.cancelled.set()
        c.check()


def test_gate_lets_an_urgent_render_in_between_steps():
    gate = Gate()
    order = []
    started = threading.Event()

    def background():
        with gate.background():
            started.set()
            for i in range(30):
                time.sleep(0.01)
                order.append(f"step{i}")
                gate.pause()

    t = threading.Thread(target=background)
    t.start()
    started.wait()
    with gate.urgent():
        order.append("urgent")
    t.join()
    assert "urgent" in order and order.index("urgent") < len(order) - 5


def test_one_walk_gives_render_rgb_and_lifted_masks_pixels(gaussians):
    from stages.query.lift_answer import lifted_masks, rgb_and_selection
    from stages.render.rasterizer import Rasterizer
    from tests.helpers import front_camera

    rast = Rasterizer.from_gaussians(gaussians)
    cam = front_camera(96, 64)
    sel = np.zeros(gaussians.count, bool)
    sel[::3] = True
    rgb, mask = rgb_and_selection(rast, sel, cam)
    np.testing.assert_array_equal(rgb, rast.render_rgb(cam).image)
    np.testing.assert_array_equal(mask, lifted_masks(rast, sel, [cam])[cam.name])
    assert mask.any() and not mask.all()

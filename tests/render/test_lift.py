import numpy as np
import pytest

import stages.render.lift as lift_module
from stages.render.composite import blend_weights
from stages.render.lift import (
    lift_mask,
    score_map,
    selection_mask,
    selection_masks,
    visibility,
)
from stages.render.rasterizer import Rasterizer
from stages.render.reference import reference_lift, reference_project
from stages.scene.gaussians import load_ply
from tests.helpers import front_camera, random_vertex, write_ply


def _scene(tmp_path, n=300, seed=0):
    g = load_ply(write_ply(tmp_path / f"s{seed}.ply", random_vertex(n, seed=seed)))
    return g, Rasterizer.from_gaussians(g)


def _dense(indptr, ids, vals, n_pixels, n):
    """The view's weights as a dense [pixels, Gaussians] matrix."""
    W = np.zeros((n_pixels, n))
    rows = np.repeat(np.arange(n_pixels), np.diff(indptr))
    np.add.at(W, (rows, ids), vals)
    return W


def _mask(cam, seed):
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[: cam.height, : cam.width]
    disc = (xx - 0.4 * cam.width) ** 2 + (yy - 0.5 * cam.height) ** 2 < (0.3 * cam.height) ** 2
    return disc ^ (rng.random(disc.shape) < 0.05)  # a blob with salt noise


@pytest.mark.parametrize("seed", [0, 1])
def test_lift_equals_the_plain_reference(tmp_path, seed):
    g, r = _scene(tmp_path, seed=seed)
    cam = front_camera(61, 45)  # partial tiles at the right and bottom edges
    proj, bins = r.prepare(cam)
    m = _mask(cam, seed)
    s1, s0 = lift_mask(proj, bins, m)
    ref_proj = reference_project(r.means, r.quats, r.scales, r.opacities, r.valid, cam)
    r1, r0 = reference_lift(ref_proj, cam.width, cam.height, m)
    assert r1.sum() > 10 and r0.sum() > 10  # both labels are exercised
    np.testing.assert_allclose(s1, r1, atol=2e-3, rtol=1e-4)
    np.testing.assert_allclose(s0, r0, atol=2e-3, rtol=1e-4)


def test_lift_is_the_transpose_of_the_render(tmp_path):
    """s1 = W^T m and s0 = W^T (1 - m) with W the view's dense [pixels, Gaussians] weights,
    the matrix whose product with per-Gaussian values is the rendered image."""
    g, r = _scene(tmp_path, n=400, seed=3)
    cam = front_camera(64, 48)
    proj, bins = r.prepare(cam)
    indptr, ids, vals = blend_weights(proj, bins, cam.width, cam.height)
    W = _dense(indptr, ids, vals, cam.width * cam.height, g.count)
    f = np.random.default_rng(0).random(g.count)
    rendered = r.render_features(cam, f[:, None].astype(np.float32)).image[:, :, 0]
    np.testing.assert_allclose(W @ f, rendered.ravel(), atol=1e-4)  # W is the render
    m = _mask(cam, 3)
    s1, s0 = lift_mask(proj, bins, m)
    mv = m.ravel().astype(np.float64)
    np.testing.assert_allclose(s1, W.T @ mv, atol=1e-4)
    np.testing.assert_allclose(s0, W.T @ (1 - mv), atol=1e-4)
    # an empty mask puts all of every Gaussian's weight on "out"
    e1, e0 = lift_mask(proj, bins, np.zeros_like(m))
    assert not e1.any()
    np.testing.assert_allclose(e0, W.sum(axis=0), atol=1e-4)


def test_lift_is_deterministic(tmp_path):
    g, r = _scene(tmp_path, n=2000, seed=4)
    cam = front_camera(96, 72)
    proj, bins = r.prepare(cam)
    m = _mask(cam, 4)
    a = lift_mask(proj, bins, m)
    b = lift_mask(proj, bins, m)
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))


def _masks(cam):
    """A small square in a corner, a blob with salt noise, a single pixel, an empty and a full
    mask."""
    corner = np.zeros((cam.height, cam.width), bool)
    corner[3:14, 5:17] = True
    pixel = np.zeros_like(corner)
    pixel[cam.height // 2, cam.width // 2] = True
    return [corner, _mask(cam, 7), pixel, np.zeros_like(corner), np.ones_like(corner)]


def _trained_like(tmp_path):
    """Gaussians of a few pixels, as a trained scene's are, and 3 % spanning many tiles (a
    wall's), whose tiles fall in several lanes: their sums depend on each tile's lane."""
    v = random_vertex(4000, seed=6)
    rng = np.random.default_rng(6)
    big = rng.random(len(v)) < 0.03
    for c in range(3):
        v[f"scale_{c}"] = np.log(np.where(big, 0.15, rng.uniform(0.004, 0.03, len(v))))
    return Rasterizer.from_gaussians(load_ply(write_ply(tmp_path / "trained.ply", v)))


def test_lift_with_the_visibility_walks_fewer_tiles_with_the_same_bits(tmp_path, monkeypatch):
    """Given the view's visibility, a lift walks only the tiles around the mask, and every s1
    and s0 is the whole walk's bit for bit (the module doc says why)."""
    r = _trained_like(tmp_path)
    cam = front_camera(160, 120)
    proj, bins = r.prepare(cam)
    vis = visibility(proj, bins, cam.width, cam.height)
    walked = []
    whole = lift_module.label_sums

    def counted(*args):
        tiles = args[5] if len(args) > 5 else None
        walked.append(bins.tiles_x * bins.tiles_y if tiles is None else len(tiles))
        return whole(*args)

    monkeypatch.setattr(lift_module, "label_sums", counted)
    for m in _masks(cam):
        a1, a0 = lift_mask(proj, bins, m)
        b1, b0 = lift_mask(proj, bins, m, vis)
        assert np.array_equal(a1, b1) and np.array_equal(a0, b0)
    n_tiles = bins.tiles_x * bins.tiles_y
    # corner, blob, pixel, empty, full: the corner's and the pixel's walks are partial, the
    # empty mask walks nothing
    assert walked[1] < n_tiles // 2 and walked[5] < n_tiles // 2 and walked[7] == 0
    assert walked[0] == walked[2] == walked[4] == walked[6] == walked[8] == n_tiles
    np.testing.assert_array_equal(lift_mask(proj, bins, np.zeros_like(_mask(cam, 0)))[1], vis)


def test_a_kept_view_is_lifted_from_its_kept_visibility_with_the_same_bits(tmp_path, monkeypatch):
    r = _trained_like(tmp_path)
    cam = front_camera(160, 120)
    plain = [lift_mask(*r.prepare(cam), m) for m in _masks(cam)]
    r.keep_views(1 << 30, [cam])
    partial = []
    whole = lift_module.label_sums
    monkeypatch.setattr(
        lift_module,
        "label_sums",
        lambda *a: partial.append(len(a) > 5 and a[5] is not None) or whole(*a),
    )
    kept = [r.lift(cam, m) for m in _masks(cam)]
    # the visibility (a whole walk), then the corner, the blob (too many tiles: whole), the
    # pixel, the empty mask (no tile) and the full one (whole)
    assert partial == [False, True, False, True, True, False]
    assert any(k[0] == "visibility" for k in r._kept)  # kept beside the projection
    for (a1, a0), (b1, b0) in zip(plain, kept, strict=True):
        assert np.array_equal(a1, b1) and np.array_equal(a0, b0)
    with pytest.raises(ValueError, match="visibility"):
        lift_mask(*r.prepare(cam), _masks(cam)[0], np.zeros(5))
    with pytest.raises(ValueError, match="mask"):
        r.lift(cam, np.zeros((cam.height - 2, cam.width), bool))  # same tiles, not the view's


def test_lift_refuses_a_mask_of_another_size(tmp_path):
    g, r = _scene(tmp_path)
    cam = front_camera(64, 48)
    proj, bins = r.prepare(cam)
    with pytest.raises(ValueError):
        lift_mask(proj, bins, np.zeros((100, 100), bool))


def test_selection_mask_is_the_selected_share(tmp_path):
    g, r = _scene(tmp_path, n=400, seed=5)
    cam = front_camera(64, 48)
    proj, bins = r.prepare(cam)
    indptr, ids, vals = blend_weights(proj, bins, cam.width, cam.height)
    W = _dense(indptr, ids, vals, cam.width * cam.height, g.count)
    sel = np.random.default_rng(1).random(g.count) < 0.3
    got = selection_mask(proj, bins, sel, cam.width, cam.height)
    want = (W @ sel > 0.5 * W.sum(axis=1)).reshape(cam.height, cam.width)
    disagree = got != want
    # only pixels within float rounding of exactly half may differ
    share = (W @ sel) / np.maximum(W.sum(axis=1), 1e-12)
    assert np.all(np.abs(share.reshape(got.shape)[disagree] - 0.5) < 1e-4)
    assert got.any() and not got.all()
    assert not selection_mask(proj, bins, np.zeros(g.count, bool), cam.width, cam.height).any()
    assert (
        selection_mask(proj, bins, np.ones(g.count, bool), cam.width, cam.height).sum()
        == (W.sum(axis=1) > 0).sum()
    )


def test_selection_masks_walk_only_the_tiles_the_selection_is_drawn_in(tmp_path):
    """The same bits as the walk of every tile: a tile without a selected Gaussian has none of
    the selection's weight. A compact selection (a corner of the image) walks few tiles."""
    from stages.render.composite import render
    from stages.render.tiles import tiles_holding

    g, r = _scene(tmp_path, n=600, seed=7)
    cam = front_camera(128, 96)
    proj, bins = r.prepare(cam)
    corner = (proj.means2d[:, 0] < 40) & (proj.means2d[:, 1] < 30) & (proj.radii > 0)
    spread = np.random.default_rng(3).random(g.count) < 0.1
    for sel in (corner, spread, np.zeros(g.count, bool)):
        full = render(proj, bins, sel.astype(np.float32)[:, None], cam.width, cam.height)
        want = full.image[:, :, 0] > 0.5 * full.alpha
        assert np.array_equal(selection_mask(proj, bins, sel, cam.width, cam.height), want)
        both = selection_masks(proj, bins, np.stack([sel, corner], 1), cam.width, cam.height)
        assert np.array_equal(both[:, :, 0], want)
    tiles = tiles_holding(bins, corner)
    assert corner.sum() > 5 and 0 < len(tiles) < bins.tiles_x * bins.tiles_y
    assert selection_mask(proj, bins, corner, cam.width, cam.height).any()
    # a tile list given empty walks no tile (the kernel's own empty list means every tile)
    ones = np.ones((g.count, 1), np.float32)
    assert render(proj, bins, ones, cam.width, cam.height).alpha.any()
    assert not render(
        proj, bins, ones, cam.width, cam.height, tiles=np.zeros(0, np.int64)
    ).alpha.any()


def test_selection_masks_are_each_selections_mask_in_one_walk(tmp_path):
    g, r = _scene(tmp_path, n=400, seed=5)
    cam = front_camera(64, 48)
    proj, bins = r.prepare(cam)
    sels = np.random.default_rng(2).random((g.count, 3)) < [0.2, 0.5, 0.8]
    got = selection_masks(proj, bins, sels, cam.width, cam.height)
    assert got.shape == (48, 64, 3)
    for k in range(3):
        want = selection_mask(proj, bins, sels[:, k], cam.width, cam.height)
        assert np.array_equal(got[:, :, k], want) and want.any()


def test_score_map_is_the_blend_weighted_sum_of_the_scores(tmp_path):
    """sum_i w_i s_i per pixel (the dense weights' product), c * alpha for a constant score,
    0 where nothing is drawn, and above half the alpha exactly where selection_mask is."""
    g, r = _scene(tmp_path, n=400, seed=5)
    cam = front_camera(64, 48)
    proj, bins = r.prepare(cam)
    indptr, ids, vals = blend_weights(proj, bins, cam.width, cam.height)
    W = _dense(indptr, ids, vals, cam.width * cam.height, g.count)
    s = np.random.default_rng(2).random(g.count).astype(np.float32)
    got = score_map(proj, bins, s, cam.width, cam.height)
    assert got.shape == (48, 64) and got.dtype == np.float32
    np.testing.assert_allclose(got.ravel(), W @ s, atol=1e-5)
    alpha = W.sum(axis=1).reshape(got.shape)
    half = score_map(proj, bins, np.full(g.count, 0.5), cam.width, cam.height)
    np.testing.assert_allclose(half, 0.5 * alpha, atol=1e-5)
    assert (got[alpha == 0] == 0).all() and (alpha == 0).any()
    both = score_map(proj, bins, np.stack([s, 1 - s], 1), cam.width, cam.height)  # [H, W, 2]
    np.testing.assert_allclose(both[:, :, 0], got, atol=1e-6)
    np.testing.assert_allclose(both[:, :, 1], alpha - got, atol=1e-5)
    sel = s < 0.3
    binary = score_map(proj, bins, sel, cam.width, cam.height) > 0.5 * alpha
    assert np.array_equal(binary, selection_mask(proj, bins, sel, cam.width, cam.height))

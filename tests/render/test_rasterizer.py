import numpy as np
import pytest

from stages.render.composite import blend_weights, render, render_backward
from stages.render.projection import project
from stages.render.rasterizer import Rasterizer
from stages.render.reference import reference_project, reference_render, reference_weights
from stages.render.sh import sh_to_rgb
from stages.render.tiles import bin_tiles
from stages.scene.gaussians import load_ply
from tests.helpers import front_camera, random_vertex, write_ply


def _scene(tmp_path, n=250, degree=3, seed=0):
    g = load_ply(write_ply(tmp_path / f"s{seed}.ply", random_vertex(n, degree=degree, seed=seed)))
    return g, Rasterizer.from_gaussians(g)


def test_projection_matches_the_matrix_form(tmp_path):
    g, r = _scene(tmp_path)
    cam = front_camera()
    fast = project(r.means, r.quats, r.scales, r.opacities, r.valid, cam)
    ref = reference_project(r.means, r.quats, r.scales, r.opacities, r.valid, cam)
    np.testing.assert_array_equal(fast.radii > 0, ref.radii > 0)
    vis = ref.radii > 0
    assert vis.sum() > 100
    np.testing.assert_array_equal(fast.radii, ref.radii)
    np.testing.assert_allclose(fast.means2d[vis], ref.means2d[vis], atol=1e-3)
    np.testing.assert_allclose(fast.conics[vis], ref.conics[vis], rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(fast.depths[vis], ref.depths[vis], rtol=1e-6)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fast_render_equals_reference(tmp_path, seed):
    g, r = _scene(tmp_path, seed=seed)
    cam = front_camera(61, 45)  # partial tiles at the right and bottom edges
    proj, bins = r.prepare(cam)
    ref_proj = reference_project(r.means, r.quats, r.scales, r.opacities, r.valid, cam)
    rgb = sh_to_rgb(r.sh, r.means, cam.center)
    feats = np.random.default_rng(seed).normal(size=(g.count, 10)).astype(np.float32)
    bg = np.array([0.2, 0.5, 1.0])
    fast = render(proj, bins, rgb, cam.width, cam.height, bg)
    ref = reference_render(ref_proj, rgb, cam.width, cam.height, bg)
    assert fast.alpha.max() > 0.9  # the scene covers the view: the test compares something
    for name in ("image", "alpha", "depth"):
        diff = np.abs(getattr(fast, name) - getattr(ref, name)).max()
        assert diff <= 1e-4, (name, diff)
    f_fast = render(proj, bins, feats, cam.width, cam.height).image
    f_ref = reference_render(ref_proj, feats, cam.width, cam.height).image
    assert np.abs(f_fast - f_ref).max() <= 1e-4


def test_sh_degree_changes_colour_with_view(tmp_path):
    g, r = _scene(tmp_path, degree=3)
    a = sh_to_rgb(r.sh, r.means, np.array([0.0, -3.0, 0.0]))
    b = sh_to_rgb(r.sh, r.means, np.array([3.0, 0.0, 0.0]))
    assert np.abs(a - b).max() > 0.05
    g0, r0 = _scene(tmp_path, degree=0, seed=5)
    np.testing.assert_allclose(
        sh_to_rgb(r0.sh, r0.means, np.zeros(3)),
        np.maximum(0.5 + 0.28209479177387814 * r0.sh[:, 0], 0),
        atol=1e-6,
    )


def test_blend_weights_equal_reference_weights(tmp_path):
    g, r = _scene(tmp_path, n=150, seed=4)
    cam = front_camera(40, 33)
    proj, bins = r.prepare(cam)
    indptr, ids, vals = blend_weights(proj, bins, cam.width, cam.height)
    ref = reference_weights(proj, cam.width, cam.height)
    assert len(ref) == len(indptr) - 1
    for p, pix in enumerate(ref):
        a, b = indptr[p], indptr[p + 1]
        assert list(ids[a:b]) == [gid for gid, _ in pix]
        np.testing.assert_allclose(vals[a:b], [w for _, w in pix], atol=1e-5)


def test_naive_backward_is_the_transpose(tmp_path):
    g, r = _scene(tmp_path, n=150, seed=6)
    cam = front_camera(40, 33)
    proj, bins = r.prepare(cam)
    indptr, ids, vals = blend_weights(proj, bins, cam.width, cam.height)
    W = np.zeros((cam.width * cam.height, g.count))
    for p in range(len(indptr) - 1):
        W[p, ids[indptr[p] : indptr[p + 1]]] += vals[indptr[p] : indptr[p + 1]]
    grad_img = np.random.default_rng(0).normal(size=(cam.height, cam.width, 4)).astype(np.float32)
    got = render_backward(proj, bins, grad_img, g.count)
    np.testing.assert_allclose(got, W.T @ grad_img.reshape(-1, 4), atol=1e-4)


def test_camera_behind_sees_nothing(tmp_path):
    g, r = _scene(tmp_path)
    cam = front_camera()
    cam.t = cam.t + np.array([0, 0, -10.0])  # everything is now behind the near plane
    out = r.render_rgb(cam, background=(1, 0, 0))
    assert out.alpha.max() == 0 and np.all(out.image[..., 0] == 1)


def test_bins_are_front_to_back(tmp_path):
    g, r = _scene(tmp_path, n=400)
    cam = front_camera(64, 48)
    proj = project(r.means, r.quats, r.scales, r.opacities, r.valid, cam)
    bins = bin_tiles(proj, cam.width, cam.height)
    for t in range(len(bins.offsets) - 1):
        d = proj.depths[bins.ids[bins.offsets[t] : bins.offsets[t + 1]]]
        assert np.all(np.diff(d) >= 0)


def test_gpu_path_is_optional(tmp_path):
    from stages.render.gsplat_backend import auto_backend, gsplat_available, padded_channels

    assert [padded_channels(n) for n in (3, 6, 10, 16, 300)] == [3, 8, 16, 16, 512]
    g, _ = _scene(tmp_path)
    r = Rasterizer.from_gaussians(g, backend=auto_backend())
    assert r.backend_name == ("gsplat" if gsplat_available() else "cpu")


def _plain_bins(proj, width, height):
    """Per tile, the depth-ordered visible Gaussians whose rectangle covers it (plain numpy)."""
    from stages.render.reference import _reference_rect
    from stages.render.tiles import depth_order

    tiles_x, tiles_y = -(-width // 16), -(-height // 16)
    order = depth_order(proj)
    m = proj.means2d[order].astype(np.float64)
    rx0, ry0, rx1, ry1 = _reference_rect(m[:, 0], m[:, 1], proj.radii[order], tiles_x, tiles_y)
    return [
        list(order[(rx0 <= tx) & (tx < rx1) & (ry0 <= ty) & (ry1 > ty)])
        for ty in range(tiles_y)
        for tx in range(tiles_x)
    ]


def test_bins_equal_the_plain_binning_with_ties(tmp_path):
    g, r = _scene(tmp_path, n=400, seed=3)
    cam = front_camera(61, 45)
    proj = project(r.means, r.quats, r.scales, r.opacities, r.valid, cam)
    # equal depths (a Gaussian duplicated, a wall facing the camera) keep their index order
    vis = np.flatnonzero(proj.radii > 0)
    proj.depths[vis[::3]] = proj.depths[vis[0]]
    bins = bin_tiles(proj, cam.width, cam.height)
    plain = _plain_bins(proj, cam.width, cam.height)
    assert bins.ids.size > 1000
    got = [list(bins.ids[bins.offsets[t] : bins.offsets[t + 1]]) for t in range(len(plain))]
    assert got == plain


@pytest.mark.parametrize("degree", [0, 3])
def test_a_view_renders_what_the_whole_scene_renders(tmp_path, degree):
    # the compacted rows (only what the view sees, colours evaluated for those only) give the
    # same image, bit for bit, as compositing the scene-indexed arrays
    g, r = _scene(tmp_path, n=600, degree=degree, seed=7)
    cam = front_camera(61, 45)
    cam.t = cam.t + np.array([0.8, 0.0, 0.0])  # part of the scene is off to the side
    proj, bins = r.prepare(cam)
    full = render(proj, bins, sh_to_rgb(r.sh, r.means, cam.center), cam.width, cam.height)
    view = r.view(cam)
    assert 0 < view.gaussians.size < g.count
    assert np.all(view.proj.radii > 0)
    fast = r.render_rgb(cam)
    for name in ("image", "alpha", "depth"):
        np.testing.assert_array_equal(getattr(fast, name), getattr(full, name))
    feats = np.random.default_rng(1).normal(size=(g.count, 7)).astype(np.float64)
    f_full = render(proj, bins, feats.astype(np.float32), cam.width, cam.height).image
    np.testing.assert_array_equal(r.render_features(cam, feats).image, f_full)
    _, ids, w = blend_weights(proj, bins, cam.width, cam.height)
    np.testing.assert_array_equal(r.contribution(cam), np.bincount(ids, w, minlength=g.count))


def _same(a, b):
    for k, v in vars(a).items():
        w = getattr(b, k)
        if isinstance(v, np.ndarray):
            np.testing.assert_array_equal(v, w)
        else:
            assert v == w, k


def test_kept_views_are_the_same_arrays_read_only_and_within_budget(tmp_path):
    g, r = _scene(tmp_path, n=400)
    plain = Rasterizer.from_gaussians(g)
    cams = [front_camera(64, 48), front_camera(61, 45), front_camera(64, 48, name="c1")]
    p0, b0 = plain.prepare(cams[0])
    own = sum(a.nbytes for a in [*vars(p0).values(), *vars(b0).values()]
              if isinstance(a, np.ndarray) and not np.may_share_memory(a, r.opacities))  # fmt: skip
    r.keep_views(1 << 30, cams)
    for cam in cams:
        (p1, b1), (p0, b0) = r.prepare(cam), plain.prepare(cam)
        _same(p1, p0), _same(b1, b0)
        v1, v0 = r.view(cam), plain.view(cam)
        _same(v1.proj, v0.proj), _same(v1.bins, v0.bins)
        np.testing.assert_array_equal(v1.gaussians, v0.gaussians)
    # a camera asked again gets what was kept, which no caller can write into
    assert r.prepare(cams[0])[0] is r.prepare(cams[0])[0]
    assert r.view(cams[2]) is r.view(cams[2])
    for a in (r.prepare(cams[0])[0].means2d, r.prepare(cams[0])[1].ids, r.view(cams[2]).gaussians,
              r.view(cams[2]).proj.conics, r.view(cams[2]).bins.offsets):  # fmt: skip
        with pytest.raises(ValueError):
            a[0] = 1
    # the scene's own arrays, which a projection hands through, stay the scene's to write
    assert g.opacities.flags.writeable and r.opacities.flags.writeable
    # the two cameras named c0 differ in size: each has its own projection
    assert r.prepare(cams[0])[1].ids.size != r.prepare(cams[1])[1].ids.size
    # a camera not named to keep_views (the browser's, moving) is not kept, even under the
    # name and size of one that is: its pose decides
    moved = front_camera(64, 48)
    moved.t = moved.t + np.array([0.05, 0.0, 0.0])
    (pm, bm), (pp, bp) = r.prepare(moved), plain.prepare(moved)
    _same(pm, pp), _same(bm, bp)
    assert r.prepare(moved)[0] is not pm and pm.means2d.flags.writeable
    assert not np.array_equal(pm.means2d, r.prepare(cams[0])[0].means2d)
    # the budget: the least recently used go first; 0 keeps nothing
    r.keep_views(int(own * 1.5), cams)
    assert 0 < r.kept_bytes() <= own * 1.5
    kept = r.prepare(cams[1])
    r.prepare(cams[0])  # now the most recently used two, over budget together: c0's stays
    assert r.prepare(cams[0])[0] is r.prepare(cams[0])[0]
    assert r.prepare(cams[1]) is not kept
    r.keep_views(0, cams)
    assert r.kept_bytes() == 0 and r.prepare(cams[0]) is not r.prepare(cams[0])
    # rendering through kept views gives the same image
    r.keep_views(1 << 30, cams)
    for _ in range(2):
        np.testing.assert_array_equal(r.render_rgb(cams[1]).image, plain.render_rgb(cams[1]).image)

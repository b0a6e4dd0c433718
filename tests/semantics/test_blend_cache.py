import os

import numpy as np
import pytest
import torch

from stages.core.errors import GoiError
from stages.render.composite import blend_weights
from stages.scene.formats.inria import write_inria
from stages.scene.scene import load_scene
from stages.semantics.feature_renderer import FeatureRenderer
from stages.semantics.weights import morton_order, top_k
from tests.helpers import build_or_load, front_camera, random_vertex, write_ply


def _scene_dir(tmp_path, n=200, seed=0):
    write_ply(tmp_path / "point_cloud.ply", random_vertex(n, degree=1, seed=seed))
    cams = [front_camera(48, 40, "a"), front_camera(48, 40, "b")]
    cams[1].t = cams[1].t + np.array([0.3, 0.1, 0.2])
    write_inria(tmp_path / "cameras.json", cams)
    return load_scene(tmp_path)


def test_cache_render_equals_direct_render(tmp_path):
    scene = _scene_dir(tmp_path)
    cache = build_or_load(tmp_path / "cache.h5", scene, scene.views("train"))
    fr = FeatureRenderer.from_cache(cache)
    f = np.random.default_rng(0).normal(size=(scene.gaussians.count, 6)).astype(np.float32)
    from stages.render.rasterizer import Rasterizer

    rast = Rasterizer.from_gaussians(scene.gaussians)
    for cam in scene.views("train"):
        direct = rast.render_features(cam, f).image.reshape(-1, 6)
        cached = fr.render(torch.from_numpy(f), fr.rows(cam.name)).numpy()
        assert direct.std() > 0.1
        assert np.abs(cached - direct).max() <= 1e-5
        some = np.array([0, 5, 17, cam.width * cam.height - 1])
        np.testing.assert_array_equal(
            fr.render(torch.from_numpy(f), fr.rows(cam.name, some)), cached[some]
        )


def test_gradient_matches_dense_transpose_and_finite_differences(tmp_path):
    scene = _scene_dir(tmp_path, n=120, seed=2)
    cache = build_or_load(tmp_path / "cache.h5", scene, scene.views("train"))
    fr = FeatureRenderer.from_cache(cache)
    rows = np.sort(np.random.default_rng(1).choice(fr.indptr.shape[0] - 1, 700, replace=False))
    f = torch.randn(scene.gaussians.count, 3, requires_grad=True)
    target = torch.randn(len(rows), 3)
    loss = ((fr.render(f, rows) - target) ** 2).sum()
    loss.backward()
    # The same product with a dense matrix in PLY column order, through torch's own autograd.
    W = np.zeros((len(rows), scene.gaussians.count))
    for i, r in enumerate(rows):
        a, b = fr.indptr[r], fr.indptr[r + 1]
        np.add.at(W[i], fr.order[fr.indices[a:b]], fr.weights[a:b])
    Wt = torch.from_numpy(W).float()
    f2 = f.detach().clone().requires_grad_()
    ((Wt @ f2 - target) ** 2).sum().backward()
    assert f.grad is not None and f2.grad is not None
    assert f.grad.abs().max() > 0.01
    torch.testing.assert_close(f.grad, f2.grad, atol=1e-4, rtol=1e-4)
    # And a central finite difference on one touched coordinate, in float64.
    j = int(np.argmax(np.abs(W).sum(0)))
    f64 = f.detach().double()
    eps = 1e-3

    def loss_at(x):
        return float(((torch.from_numpy(W) @ x - target.double()) ** 2).sum())

    fp, fm = f64.clone(), f64.clone()
    fp[j, 1] += eps
    fm[j, 1] -= eps
    assert abs((loss_at(fp) - loss_at(fm)) / (2 * eps) - float(f.grad[j, 1])) < 1e-2


def test_top_k_keeps_the_largest_weights_in_order():
    indptr = np.array([0, 5, 6, 6], np.int64)
    ids = np.array([4, 3, 2, 1, 0, 9], np.int32)
    vals = np.array([0.1, 0.5, 0.2, 0.5, 0.05, 0.3], np.float32)
    p, i, v = top_k(indptr, ids, vals, 3)
    assert list(p) == [0, 3, 4, 4]
    assert list(i) == [3, 2, 1, 9]
    np.testing.assert_allclose(v, [0.5, 0.2, 0.5, 0.3])


def test_top_k_mass_is_recorded(tmp_path):
    scene = _scene_dir(tmp_path, n=400)
    full = build_or_load(tmp_path / "full.h5", scene, scene.views("train"), k=0)
    cut = build_or_load(tmp_path / "k2.h5", scene, scene.views("train"), k=2)
    v_full, v_cut = full.views["a"], cut.views["a"]
    assert v_full.mass_kept == 1.0
    assert 0.3 < v_cut.mass_kept < 1.0
    np.testing.assert_allclose(
        v_cut.mass_kept, v_cut.weights.sum() / v_full.weights.sum(), rtol=1e-5
    )
    assert np.diff(v_cut.indptr).max() <= 2 and v_cut.entries_total == len(v_full.indices)


def test_cache_is_reused_and_rebuilt_when_inputs_change(tmp_path):
    scene = _scene_dir(tmp_path)
    path = tmp_path / "cache.h5"
    c1 = build_or_load(path, scene, scene.views("train"))
    stamp = os.stat(path).st_mtime_ns
    c2 = build_or_load(path, scene, scene.views("train"))
    assert os.stat(path).st_mtime_ns == stamp
    np.testing.assert_array_equal(c1.views["b"].weights, c2.views["b"].weights)
    write_ply(tmp_path / "point_cloud.ply", random_vertex(200, degree=1, seed=9))
    scene = load_scene(tmp_path)
    # The file now holds another cache: replacing it is an overwrite, which needs --force.
    with pytest.raises(GoiError, match=r"--cache: .*cache.h5 exists .* pass --force"):
        build_or_load(path, scene, scene.views("train"))
    assert os.stat(path).st_mtime_ns == stamp
    c3 = build_or_load(path, scene, scene.views("train"), force=True)
    assert c3.ply_sha256 != c1.ply_sha256
    assert not np.array_equal(c3.views["b"].indices[:50], c1.views["b"].indices[:50])


def test_morton_order_is_a_permutation_that_groups_neighbours():
    pts = np.random.default_rng(0).uniform(0, 1, (5000, 3)).astype(np.float32)
    order = morton_order(pts)
    assert sorted(order.tolist()) == list(range(5000))
    step = np.linalg.norm(np.diff(pts[order], axis=0), axis=1).mean()
    assert step < 0.5 * np.linalg.norm(np.diff(pts, axis=0), axis=1).mean()


def test_cache_columns_follow_the_recorded_order(tmp_path):
    scene = _scene_dir(tmp_path)
    cache = build_or_load(tmp_path / "c.h5", scene, scene.views("train"))
    from stages.render.rasterizer import Rasterizer

    rast = Rasterizer.from_gaussians(scene.gaussians)
    proj, bins = rast.prepare(scene.camera("a"))
    _, ids, _ = blend_weights(proj, bins, 48, 40)
    np.testing.assert_array_equal(cache.order[cache.views["a"].indices], ids)


def test_pooled_rows_render_the_mean_of_their_pixels(tmp_path):
    scene = _scene_dir(tmp_path, n=300)
    full = build_or_load(tmp_path / "full.h5", scene, scene.views("train"))
    pooled = build_or_load(
        tmp_path / "pool.h5", scene, scene.views("train"), sizes={"a": (7, 5), "b": (7, 5)}
    )
    f = torch.from_numpy(
        np.random.default_rng(0).normal(size=(scene.gaussians.count, 4)).astype(np.float32)
    )
    img = FeatureRenderer.from_cache(full).render(f, np.arange(48 * 40)).numpy()
    img = img.reshape(40, 48, 4)
    cells = FeatureRenderer.from_cache(pooled, ["a"]).render(f, np.arange(35)).numpy()
    cells = cells.reshape(5, 7, 4)
    ys = ((np.arange(40) + 0.5) * 5 / 40).astype(int)
    xs = ((np.arange(48) + 0.5) * 7 / 48).astype(int)
    for cy in range(5):
        for cx in range(7):
            block = img[np.ix_(ys == cy, xs == cx)].reshape(-1, 4)
            np.testing.assert_allclose(cells[cy, cx], block.mean(0), atol=1e-5)
    # A different size is a different cache: rebuilt (with --force), not reused.
    again = build_or_load(tmp_path / "pool.h5", scene, scene.views("train"), force=True)
    assert again.views["a"].width == 48


def test_sparse_gradient_does_not_depend_on_the_thread_count(tmp_path):
    """The transpose sums over fixed row blocks: 1 thread and 2 threads give the same bits."""
    import numba
    import torch

    from stages.render.rasterizer import Rasterizer
    from stages.scene.gaussians import load_ply
    from stages.semantics.blend_cache import build_cache
    from stages.testing.synthetic import ring_cameras, room_vertex

    write_ply(tmp_path / "p.ply", room_vertex(4000, seed=1)[0])
    rast = Rasterizer.from_gaussians(load_ply(tmp_path / "p.ply"))
    fr = FeatureRenderer.from_cache(build_cache(rast, ring_cameras(2, 64, 48), 0, "", ""))
    rows = np.sort(np.random.default_rng(0).choice(2 * 64 * 48, 4000, replace=False))
    f = torch.randn(4000, 10, generator=torch.Generator().manual_seed(0), requires_grad=True)
    up = torch.randn(len(rows), 10, generator=torch.Generator().manual_seed(1))
    grads = []
    before = numba.get_num_threads()
    try:
        for threads in (1, before):
            numba.set_num_threads(threads)
            f.grad = None
            (fr.render(f, rows) * up).sum().backward()
            grads.append(f.grad.numpy().copy())
    finally:
        numba.set_num_threads(before)
    assert grads[0].tobytes() == grads[1].tobytes()

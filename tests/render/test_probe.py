"""The probe of a few pixels equals the full render at those pixels."""

import numpy as np
import pytest

from stages.render.lift import lift_mask
from stages.render.probe import probe
from stages.render.rasterizer import Rasterizer
from stages.scene.gaussians import load_ply
from tests.helpers import front_camera, random_vertex, write_ply


@pytest.mark.parametrize("seed", [0, 1])
def test_probe_equals_the_render_at_its_pixels(tmp_path, seed):
    g = load_ply(write_ply(tmp_path / "s.ply", random_vertex(400, seed=seed)))
    rast = Rasterizer.from_gaussians(g)
    cam = front_camera(61, 45)  # partial tiles at the right and bottom edges
    full = rast.render_rgb(cam)
    proj, bins = rast.prepare(cam)
    ys, xs = np.mgrid[0 : cam.height, 0 : cam.width]
    xy = np.stack([xs.ravel(), ys.ravel()], 1)
    got = probe(proj, bins, xy, cam.width, cam.height)
    assert (full.alpha > 0.5).mean() > 0.3  # the scene covers the view
    np.testing.assert_allclose(got.alpha, full.alpha.ravel(), atol=2e-6)
    np.testing.assert_allclose(got.depth, full.depth.ravel(), rtol=2e-5, atol=1e-6)
    # the top Gaussian carries the pixel's largest blend weight: a one-pixel mask's lift
    for k in np.random.default_rng(seed).choice(len(xy), 20, replace=False):
        x, y = xy[k]
        mask = np.zeros((cam.height, cam.width), bool)
        mask[y, x] = True
        s1, _ = lift_mask(proj, bins, mask)
        if s1.max() == 0:
            assert got.top[k] == -1
        else:
            assert got.top[k] == int(np.argmax(s1))


def test_probe_off_the_image_is_empty(tmp_path):
    g = load_ply(write_ply(tmp_path / "s.ply", random_vertex(100)))
    rast = Rasterizer.from_gaussians(g)
    cam = front_camera(32, 24)
    proj, bins = rast.prepare(cam)
    got = probe(proj, bins, np.array([[-1, 0], [0, 24], [32, 3]]), cam.width, cam.height)
    assert (got.alpha == 0).all() and (got.depth == 0).all() and (got.top == -1).all()

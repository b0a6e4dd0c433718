"""The fused pooled walk (`pooled_blend_weights`) against its reference, pooling the per-pixel
CSR of `blend_weights`: same cells, same columns per cell, same weights up to float32
summation order, and the same bytes whatever the thread count."""

import numba
import numpy as np
import pytest

from stages.render.composite import blend_weights, pooled_blend_weights
from stages.render.rasterizer import Rasterizer
from stages.scene.gaussians import Gaussians, load_ply
from stages.semantics.blend_cache import view_weights
from stages.semantics.weights import morton_order, pixel_cells, pool
from stages.testing.synthetic import look_at, ring_cameras, room_vertex
from tests.helpers import write_ply


@pytest.fixture(scope="module")
def room(tmp_path_factory) -> Gaussians:
    path = tmp_path_factory.mktemp("room") / "p.ply"
    write_ply(path, room_vertex(6000, seed=3)[0])
    return load_ply(path)


def _columns(rast: Rasterizer) -> np.ndarray:
    order = morton_order(rast.means)
    position = np.empty_like(order)
    position[order] = np.arange(len(order), dtype=np.int32)
    return position


def _both(rast, cam, cells_w, cells_h):
    proj, bins = rast.prepare(cam)
    position = _columns(rast)
    indptr, ids, vals = blend_weights(proj, bins, cam.width, cam.height)
    ref = pool(indptr, position[ids], vals, cam.width, cam.height, cells_w, cells_h, len(position))
    cx, cy = pixel_cells(cam.width, cells_w), pixel_cells(cam.height, cells_h)
    *fused, n = pooled_blend_weights(proj, bins, cam.width, cam.height, cx, cy, position)
    assert n == len(ids)
    return ref, fused, len(ids)


def _assert_equal(ref, fused) -> None:
    np.testing.assert_array_equal(fused[0], ref[0])  # the same number of columns per cell
    np.testing.assert_array_equal(fused[1], ref[1])  # the same columns, ascending per cell
    np.testing.assert_allclose(fused[2], ref[2], rtol=1e-5, atol=0)


# Odd sizes: cells of 7 or 8 px (and 5 px) straddle the 16 px tiles at every offset.
@pytest.mark.parametrize(
    "size, cells",
    [((123, 82), (15, 10)), ((64, 48), (8, 6)), ((97, 61), (19, 12)), ((50, 40), (3, 2))],
)
def test_fused_pooling_equals_pooling_the_pixel_weights(room, size, cells):
    rast = Rasterizer.from_gaussians(room)
    for cam in ring_cameras(3, *size, radius=1.9, height_m=1.5):
        ref, fused, n = _both(rast, cam, *cells)
        assert n > 10 * size[0] * size[1]  # a real scene: many weights per pixel
        _assert_equal(ref, fused)


def test_fused_pooling_with_saturated_pixels(room):
    """Opaque Gaussians close up: most pixels stop early (T < T_MIN) and whole tiles finish."""
    g = room
    opaque = np.full_like(g.opacities, 0.99)
    rast = Rasterizer(g.means, g.quats, 3 * g.scales, opaque, g.sh, g.valid)
    cam = ring_cameras(1, 75, 53, radius=1.9, height_m=1.5)[0]
    assert (rast.render_features(cam, np.ones((g.count, 1))).alpha > 0.999).mean() > 0.5
    ref, fused, _ = _both(rast, cam, 9, 6)
    _assert_equal(ref, fused)


def test_fused_pooling_of_an_empty_view(room):
    rast = Rasterizer.from_gaussians(room)
    away = look_at("out", np.array([9.0, 0.0, 1.0]), np.array([20.0, 0.0, 1.0]), 45, 30)
    ref, fused, n = _both(rast, away, 6, 4)
    assert n == 0 and len(fused[1]) == 0
    _assert_equal(ref, fused)


def test_fused_pooling_is_the_same_bytes_on_any_thread_count(room):
    rast = Rasterizer.from_gaussians(room)
    cam = ring_cameras(2, 101, 77, radius=1.9, height_m=1.5)[1]
    position = _columns(rast)
    before = numba.get_num_threads()
    out = []
    try:
        for threads in (1, before, 1):
            numba.set_num_threads(threads)
            vw = view_weights(rast, cam, position, 0, (12, 9))
            out.append(vw.indptr.tobytes() + vw.indices.tobytes() + vw.weights.tobytes())
    finally:
        numba.set_num_threads(before)
    assert out[0] == out[1] == out[2]


def test_view_weights_uses_the_fused_walk_only_where_it_applies(room):
    rast = Rasterizer.from_gaussians(room)
    cam = ring_cameras(1, 80, 60, radius=1.9, height_m=1.5)[0]
    position = _columns(rast)
    fused = view_weights(rast, cam, position, 0, (10, 7))
    ref = view_weights(rast, cam, position, 0, (10, 7), fused=False)
    _assert_equal(
        (ref.indptr, ref.indices, ref.weights), (fused.indptr, fused.indices, fused.weights)
    )
    assert (fused.mass_kept, fused.entries_total) == (ref.mass_kept, ref.entries_total)
    # Top-K and full-size views take the per-pixel path: identical bytes either way.
    for k, size in ((3, (10, 7)), (0, None)):
        a = view_weights(rast, cam, position, k, size)
        b = view_weights(rast, cam, position, k, size, fused=False)
        assert a.weights.tobytes() == b.weights.tobytes() and a.mass_kept == b.mass_kept


def test_tiles_that_overflow_their_room_are_walked_again(room):
    rast = Rasterizer.from_gaussians(room)
    cam = ring_cameras(1, 90, 70, radius=1.9, height_m=1.5)[0]
    proj, bins = rast.prepare(cam)
    position = _columns(rast)
    cx, cy = pixel_cells(cam.width, 11), pixel_cells(cam.height, 8)
    roomy = pooled_blend_weights(proj, bins, cam.width, cam.height, cx, cy, position)
    # Room for 50 pairs a thread: most tiles need more and go to the second walk.
    tight = pooled_blend_weights(proj, bins, cam.width, cam.height, cx, cy, position, room=50)
    assert roomy[3] == tight[3]
    for a, b in zip(roomy[:3], tight[:3], strict=True):
        assert a.tobytes() == b.tobytes()

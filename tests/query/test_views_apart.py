"""The index order and the growing index's view choice (#39) as pure math: pose distance,
farthest-point sampling on camera poses, and coverage from sides not yet seen."""

import numpy as np

from stages.query.res_index import camera_distance, index_order
from stages.query.views import next_view, next_view_apart, pose_distance
from stages.testing.synthetic import ring_cameras


def test_pose_distance_is_a_distance_of_centres_and_directions():
    centers = np.array([[1.0, 0, 0], [-1.0, 0, 0], [1.0, 0, 0]])
    axes = np.array([[-1.0, 0, 0], [1.0, 0, 0], [0.0, 1, 0]])
    d = pose_distance(centers, axes)
    np.testing.assert_allclose(d, d.T)
    np.testing.assert_allclose(np.diag(d), 0, atol=1e-12)
    # same place, a right angle apart: 1 - cos 90 = 1; facing each other across the room:
    # 2 m in units of the spread (the median distance to the mean centre, 2/3 m) plus
    # 1 - cos 180 = 2
    assert np.isclose(d[0, 2], 1.0) and np.isclose(d[0, 1], 2 / (2 / 3) + 2.0)


def test_the_index_order_spreads_any_prefix_around_the_scene():
    cams = ring_cameras(12, 32, 24, radius=2.0, height_m=1.0)
    order = [c.name for c in index_order(cams)]
    assert sorted(order) == sorted(c.name for c in cams) and len(set(order)) == 12
    i0, i1 = (next(i for i, c in enumerate(cams) if c.name == v) for v in order[:2])
    assert abs(i0 - i1) == 6  # the second view is the one across the ring
    # any prefix of 4 views holds one view in each quarter of the ring
    first4 = sorted(next(i for i, c in enumerate(cams) if c.name == v) for v in order[:4])
    assert len({(i - i0) % 12 // 3 for i in first4}) == 4
    # views already held come first, in their order; the rest spread from them
    held = [cams[5].name, cams[2].name]
    again = [c.name for c in index_order(cams, held)]
    assert again[:2] == held and sorted(again) == sorted(order)
    d = camera_distance(cams)
    nxt = next(i for i, c in enumerate(cams) if c.name == again[2])
    assert np.isclose(d[nxt, [5, 2]].min(), np.delete(d[:, [5, 2]].min(1), [5, 2]).max())


def test_a_view_that_sees_the_selection_from_another_side_wins_a_tie():
    G = 10
    S = np.zeros(G, bool)
    S[:4] = True
    E = np.zeros(G)
    same = np.zeros(G)
    same[:4] = 2.0
    # two candidates that add the same coverage: the one farther from the views lifted wins
    assert next_view_apart([same, same.copy()], S, E, np.array([0.1, 1.5])) == 1
    assert next_view_apart([same, same.copy()], S, E, np.array([1.5, 0.1])) == 0
    # before any view is lifted, the gain alone decides, as next_view does
    more = same.copy()
    more[:4] = 3.0
    vis = [same, more]
    assert next_view_apart(vis, S, E, None) == next_view(vis, S, E) == 1
    # a view that adds nothing is not taken for its distance alone over one that adds much
    none = np.zeros(G)
    assert next_view_apart([none, more], S, E, np.array([3.0, 1.5])) == 1

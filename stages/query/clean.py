"""Clean answers: a lifted selection made spatially coherent, arrays in and arrays out.

The vote keeps whatever enough views' masks put in, and some of it lies far from the object:
a few Gaussians the masks' edges graze in the views that see them, hidden Gaussians the field
decides by their codebook entry (which the object shares with things elsewhere), a confuser a
few views take in. The test views' IoU hardly sees them (a speck is a few pixels), but an
exported PLY, an isolated answer or an edit shows them floating in the room (issue #52: 1-13 %
of the demo's lifted answers lay more than 3 % of the scene's extent from the target, 20 % of
"the plant on the side table" with SAM's masks on the dev room). So, per answer:

  1. pieces   the selected Gaussians' centres, linked when closer than LINK x the scene's
              extent (a voxel hash of cells that size; `components`), fall into pieces.
  2. body     the piece the masks claim most (the lifted S1 summed over it; the largest
              piece when nothing is claimed), and every piece claimed at least STRONG_CLAIM
              of it: evidence strong in its own right, a second object of the prompt ("the
              armchairs": the second chair carries 0.26-0.30 of the first's claim on the dev
              room, a speck or a confuser 0.031 at most).
  3. near     a weaker piece within NEAR x the extent of the body is kept (a part the link
              radius cut off: 216-242 Gaussians of the white armchair); one pass, so a chain
              of specks cannot creep outwards from the body (chained, "couch" kept 2.2 % of
              strays on the dev room instead of 0.5 %).
  4. the rest is dropped, and the record says how many Gaussians and pieces, and why.

The extent is the diagonal of the box holding the central 98 % of the Gaussians' centres on
each axis (`robust_extent`): a few floaters far out in a real capture do not set the radii.
The radii are absolute shares of it, so on a scene whose Gaussians are sparse against them
an object's selection can fall into many pieces; the near rule keeps those within NEAR of the
body. Measured on the dev room's four RES sets (docs/benchmarks.md, "Clean answers").
"""

from __future__ import annotations

import numba
import numpy as np

# ------------------------------------------------------------------------------------------
# Geometry: a voxel hash over points (cells of side r), and the two questions asked of it.
# Two points within r lie in the same or adjacent cells, so each point looks at 27 cells.
# ------------------------------------------------------------------------------------------

#: The cells are this much wider than r, so that rounding in floor((p - lo) / cell) can never
#: put two points exactly r apart two cells apart.
_CELL_SLACK = 1e-6


def scene_extent(means: np.ndarray) -> float:
    """The diagonal of the Gaussians' bounding box (means [G, 3]): the scene's extent, the
    unit of the cleaning radii and of `goi eval`'s stray share. 0 for no Gaussian."""
    if means.shape[0] == 0:
        return 0.0
    m = means.astype(np.float64)
    return float(np.linalg.norm(m.max(0) - m.min(0)))


class _Grid:
    """points [N, 3] float64 hashed into cells of side `cell`: cell coordinates [N, 3], the
    points sorted by cell key (`order`), and each occupied key's run in that order."""

    def __init__(self, points: np.ndarray, r: float):
        self.points = np.ascontiguousarray(points, np.float64)
        self.cell = r * (1.0 + _CELL_SLACK)
        n = self.points.shape[0]
        self.lo = self.points.min(0) if n else np.zeros(3)
        self.coords = np.floor((self.points - self.lo) / self.cell).astype(np.int64)  # [N, 3]
        self.dims = (self.coords.max(0) + 1) if n else np.ones(3, np.int64)  # [3]
        key = _keys(self.coords, self.dims)  # [N]
        self.order = np.argsort(key, kind="stable").astype(np.int64)
        self.keys, self.start = np.unique(key[self.order], return_index=True)  # [K]
        self.end = np.append(self.start[1:], n).astype(np.int64)  # [K]
        self.start = self.start.astype(np.int64)


def _keys(coords: np.ndarray, dims: np.ndarray) -> np.ndarray:
    return (coords[:, 0] * dims[1] + coords[:, 1]) * dims[2] + coords[:, 2]


@numba.njit(cache=True)
def _run(keys, start, end, dims, cx, cy, cz):
    """The [a, b) run of the points in cell (cx, cy, cz) in the grid's order (empty outside)."""
    if cx < 0 or cy < 0 or cz < 0 or cx >= dims[0] or cy >= dims[1] or cz >= dims[2]:
        return 0, 0
    k = (cx * dims[1] + cy) * dims[2] + cz
    i = np.searchsorted(keys, k)
    if i < keys.shape[0] and keys[i] == k:
        return start[i], end[i]
    return 0, 0


@numba.njit(cache=True)
def _find(parent, i):
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@numba.njit(cache=True)
def _link_kernel(pts, coords, order, keys, start, end, dims, r2):
    """[N] component labels of the graph i ~ j when |p_i - p_j| <= r (union-find over the 27
    cells around each point), numbered by their smallest member, in order."""
    n = pts.shape[0]
    parent = np.arange(n)
    for i in range(n):
        for dx in range(-1, 2):
            for dy in range(-1, 2):
                for dz in range(-1, 2):
                    a, b = _run(keys, start, end, dims, coords[i, 0] + dx, coords[i, 1] + dy,
                                coords[i, 2] + dz)  # fmt: skip
                    for t in range(a, b):
                        j = order[t]
                        if j <= i:
                            continue
                        d0 = pts[i, 0] - pts[j, 0]
                        d1 = pts[i, 1] - pts[j, 1]
                        d2 = pts[i, 2] - pts[j, 2]
                        if d0 * d0 + d1 * d1 + d2 * d2 <= r2:
                            ri, rj = _find(parent, i), _find(parent, j)
                            if ri != rj:  # the smaller index is the root: labels in order
                                parent[max(ri, rj)] = min(ri, rj)
    labels = np.empty(n, np.int64)
    root_label = np.full(n, -1, np.int64)
    count = 0
    for i in range(n):
        r = _find(parent, i)
        if root_label[r] < 0:
            root_label[r] = count
            count += 1
        labels[i] = root_label[r]
    return labels


@numba.njit(cache=True)
def _near_kernel(q, lo, cell, pts, order, keys, start, end, dims, r2):
    """[Q] bool: whether each query point has a grid point within r."""
    out = np.zeros(q.shape[0], np.bool_)
    for i in range(q.shape[0]):
        cx = np.int64(np.floor((q[i, 0] - lo[0]) / cell))
        cy = np.int64(np.floor((q[i, 1] - lo[1]) / cell))
        cz = np.int64(np.floor((q[i, 2] - lo[2]) / cell))
        found = False
        for dx in range(-1, 2):
            for dy in range(-1, 2):
                for dz in range(-1, 2):
                    a, b = _run(keys, start, end, dims, cx + dx, cy + dy, cz + dz)
                    for t in range(a, b):
                        j = order[t]
                        d0 = q[i, 0] - pts[j, 0]
                        d1 = q[i, 1] - pts[j, 1]
                        d2 = q[i, 2] - pts[j, 2]
                        if d0 * d0 + d1 * d1 + d2 * d2 <= r2:
                            found = True
                            break
                    if found:
                        break
                if found:
                    break
            if found:
                break
        out[i] = found
    return out


def components(points: np.ndarray, r: float) -> np.ndarray:
    """[N] int64 labels of the connected components of the graph linking points [N, 3] closer
    than r (inclusive), numbered 0, 1, ... by their first member."""
    if points.shape[0] == 0:
        return np.zeros(0, np.int64)
    g = _Grid(points, r)
    return _link_kernel(g.points, g.coords, g.order, g.keys, g.start, g.end, g.dims, r * r)


def near_any(queries: np.ndarray, points: np.ndarray, r: float) -> np.ndarray:
    """[Q] bool: whether each of queries [Q, 3] lies within r (inclusive) of some point of
    points [N, 3]."""
    if points.shape[0] == 0 or queries.shape[0] == 0:
        return np.zeros(queries.shape[0], bool)
    g = _Grid(points, r)
    q = np.ascontiguousarray(queries, np.float64)
    return _near_kernel(q, g.lo, g.cell, g.points, g.order, g.keys, g.start, g.end, g.dims, r * r)


# ------------------------------------------------------------------------------------------
# The rule.
# ------------------------------------------------------------------------------------------

#: Two selected Gaussians closer than this share of the scene's extent are linked: the
#: components of that graph are the pieces of the answer (7 cm on the dev room).
LINK = 0.01
#: A weak piece within this share of the extent of the body is kept: a part of the object
#: the link radius cut off (216-242 Gaussians of the white armchair lie 1-2 % from the rest of
#: it). `goi eval`'s stray share counts what lies beyond 3 %.
NEAR = 0.03
#: A piece far from the body stays when the masks' claim on it (its S1 summed) is at least
#: this share of the claim on the piece they claim most: a second object of the prompt.
#: On the dev room's four RES sets, with and without the field, the second armchair under
#: "armchairs" carries 0.26-0.30 of the first's claim; of the pieces dropped, the most claimed
#: is the white armchair that correlated SAM masks take in under "the dark green armchair"
#: (0.031, 2,209 Gaussians), the rest (specks, a confuser a few views take in) 0.0032 at most;
#: on the demo scene 0.016 at most.
STRONG_CLAIM = 0.1
#: The extent is the diagonal of the box holding this central share of the Gaussians' centres
#: on each axis, so that a few floaters far out in a real capture do not set the radii.
EXTENT_SHARE = 0.98


def robust_extent(means: np.ndarray) -> float:
    """The diagonal of the box between the 1st and 99th percentiles of the Gaussians' centres
    (means [G, 3]) on each axis: the unit of the cleaning radii. 0 for no Gaussian."""
    if means.shape[0] == 0:
        return 0.0
    q = 50.0 * (1.0 - EXTENT_SHARE)
    lo, hi = np.percentile(means.astype(np.float64), [q, 100.0 - q], axis=0)
    return float(np.linalg.norm(hi - lo))


def clean_selection(
    means: np.ndarray, selected: np.ndarray, claim: np.ndarray
) -> tuple[np.ndarray, dict]:
    """The selection ([G] bool) without its pieces far from the answer's body, and what was
    done ({rule, n_dropped, ...}, JSON-ready). means [G, 3]: the Gaussians' centres; claim [G]:
    the evidence that each is in (the lifted vote's S1). See the module doc."""
    extent = robust_extent(means)
    record: dict = {
        "rule": "far_piece",
        "params": {"link": LINK, "near": NEAR, "strong_claim": STRONG_CLAIM,
                   "extent": round(extent, 6)},
        "n_before": int(selected.sum()),
        "n_pieces": 0,
        "n_body_pieces": 0,
        "n_near_pieces": 0,
        "n_dropped_pieces": 0,
        "n_dropped": 0,
    }  # fmt: skip
    idx = np.flatnonzero(selected)  # [S]
    if idx.size == 0 or extent <= 0.0:
        return selected.copy(), record
    pts = means[idx].astype(np.float64)  # [S, 3]
    piece = components(pts, LINK * extent)  # [S]
    n = int(piece.max()) + 1
    weight = np.bincount(piece, weights=np.asarray(claim, np.float64)[idx], minlength=n)  # [P]
    if weight.max() <= 0.0:  # nothing claimed (a field-only answer): the largest piece leads
        weight = np.bincount(piece, minlength=n).astype(np.float64)
    body = weight >= STRONG_CLAIM * weight.max()  # [P]
    near = np.zeros(n, bool)
    weak = np.flatnonzero(~body)
    if weak.size:
        close = near_any(pts[~body[piece]], pts[body[piece]], NEAR * extent)  # [S_weak]
        near[np.unique(piece[~body[piece]][close])] = True
    kept_piece = body | near
    kept = np.zeros_like(selected, dtype=bool)
    kept[idx[kept_piece[piece]]] = True
    record.update(
        n_pieces=n,
        n_body_pieces=int(body.sum()),
        n_near_pieces=int(near.sum()),
        n_dropped_pieces=int((~kept_piece).sum()),
        n_dropped=int(idx.size - kept_piece[piece].sum()),
    )
    return kept, record


# ------------------------------------------------------------------------------------------
# The plain references the kernels are held to (tests): every pair, in numpy.
# ------------------------------------------------------------------------------------------


def reference_components(points: np.ndarray, r: float) -> np.ndarray:
    """`components` by every pair's distance and a breadth-first walk (O(N^2))."""
    p = points.astype(np.float64)
    n = p.shape[0]
    labels = np.full(n, -1, np.int64)
    count = 0
    for s in range(n):
        if labels[s] >= 0:
            continue
        labels[s] = count
        todo = [s]
        while todo:
            i = todo.pop()
            d = p - p[i]
            near = np.flatnonzero((d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2])
                                  <= r * r)  # fmt: skip
            new = near[labels[near] < 0]
            labels[new] = count
            todo.extend(new.tolist())
        count += 1
    return labels


def reference_near_any(queries: np.ndarray, points: np.ndarray, r: float) -> np.ndarray:
    """`near_any` by every pair's distance (O(QN))."""
    q, p = queries.astype(np.float64), points.astype(np.float64)
    out = np.zeros(q.shape[0], bool)
    for i in range(q.shape[0]):
        d = p - q[i]
        out[i] = bool(((d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]) <= r * r).any())
    return out

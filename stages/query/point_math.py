"""The math of pointing at things, arrays in and arrays out: a click's 3D point, where it falls
in another view, and the SAM prompts a 2D mask gives (its box, its most interior pixels).

Pixel coordinates are goi's pixel-index coordinates (`Projected.means2d`): pixel (x, y)'s centre
is at (x, y); a click at column U, row V is that pixel. Boxes are x0, y0, x1, y1 in pixel edges
(a box around pixels x0..x1-1), as SAM and the detectors take them.
"""

from __future__ import annotations

import numpy as np

from stages.scene.cameras import Camera


def pixel_ray_point(cam: Camera, u: float, v: float, depth: float) -> np.ndarray:
    """[3] the world point at camera-space depth `depth` (z) under pixel (u, v) of `cam`."""
    x = (u + 0.5 - cam.cx) / cam.fx * depth
    y = (v + 0.5 - cam.cy) / cam.fy * depth
    pc = np.array([x, y, depth], np.float64)
    return np.asarray(cam.R, np.float64).T @ (pc - np.asarray(cam.t, np.float64))


def project_points(cam: Camera, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points [K, 3] -> (pixel-index coordinates [K, 2], camera-space depth z [K])."""
    pc = np.asarray(points, np.float64) @ np.asarray(cam.R, np.float64).T + np.asarray(cam.t)
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = cam.fx * pc[:, 0] / z + cam.cx - 0.5
        v = cam.fy * pc[:, 1] / z + cam.cy - 0.5
    return np.stack([u, v], 1), z


def in_view(cam: Camera, uv: np.ndarray, z: np.ndarray, near: float) -> np.ndarray:
    """[K] bool: in front of the camera (z > near) and on its image."""
    u, v = uv[:, 0], uv[:, 1]
    with np.errstate(invalid="ignore"):
        return (
            (z > near) & (u >= -0.5) & (v >= -0.5) & (u < cam.width - 0.5) & (v < cam.height - 0.5)
        )


def unoccluded(z: np.ndarray, alpha: np.ndarray, depth: np.ndarray, tol: float) -> np.ndarray:
    """[K] bool: a point at depth z [K] is what its pixel shows, given the render there (alpha
    [K], expected depth [K]): the pixel is covered and its surface lies within `tol` (relative
    to z) of the point, neither in front of it (occluded) nor far behind (the point floats)."""
    return (alpha >= 0.5) & (np.abs(depth - z) <= tol * z)


def interior_points(mask: np.ndarray, k: int) -> np.ndarray:
    """[<= k, 2] the mask's most interior pixels (x, y): the maximum of the distance to its
    boundary (the image's edge counts as boundary, so a mask cut by the edge is not pointed at
    along it), then the next maximum at least twice its distance away, and so on. SAM given
    points deep inside what is meant, not near its edge, segments the whole of it."""
    import cv2

    m = np.asarray(mask, bool)
    if k <= 0 or not m.any():
        return np.zeros((0, 2), np.int64)
    padded = np.pad(m.astype(np.uint8), 1)
    dist = cv2.distanceTransform(padded, cv2.DIST_L2, 5)[1:-1, 1:-1]
    yy, xx = np.mgrid[0 : m.shape[0], 0 : m.shape[1]]
    out = []
    for _ in range(k):
        y, x = np.unravel_index(int(np.argmax(dist)), dist.shape)
        r = float(dist[y, x])
        if r <= 0:
            break
        out.append((int(x), int(y)))
        dist[(xx - x) ** 2 + (yy - y) ** 2 <= max(2.0, 2.0 * r) ** 2] = 0
    return np.asarray(out, np.int64).reshape(-1, 2)


def main_parts(mask: np.ndarray, keep: float) -> np.ndarray:
    """[H, W] bool: the mask's 8-connected parts that hold at least `keep` of its area (a few
    stray pixels of a 3D selection seen from a view do not stretch the box around it)."""
    import cv2

    m = np.asarray(mask, bool)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(m.astype(np.uint8), connectivity=8)
    if n <= 1:
        return np.zeros_like(m)
    area = stats[1:, cv2.CC_STAT_AREA]
    big = np.nonzero(area >= keep * area.sum())[0] + 1
    return np.isin(labels, big)


def mask_box(mask: np.ndarray) -> np.ndarray | None:
    """[4] the box (x0, y0, x1, y1, pixel edges) around the mask's pixels; None when empty."""
    ys, xs = np.nonzero(mask)
    if not len(xs):
        return None
    return np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], np.float64)


def mask_iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two [H, W] bool masks (0 when both are empty)."""
    union = int(np.count_nonzero(a | b))
    return int(np.count_nonzero(a & b)) / union if union else 0.0


def expand_box(box: np.ndarray, share: float, width: int, height: int, least: float) -> np.ndarray:
    """[4] the box grown by `share` of its width and height on every side (at least `least`
    pixels), clipped to the image."""
    x0, y0, x1, y1 = (float(b) for b in box)
    dx = max(least, share * (x1 - x0))
    dy = max(least, share * (y1 - y0))
    return np.array(
        [max(0.0, x0 - dx), max(0.0, y0 - dy), min(width, x1 + dx), min(height, y1 + dy)]
    )


def box_pixels(box: np.ndarray, width: int, height: int) -> np.ndarray:
    """[H, W] bool: the pixels inside a box (pixel edges, clipped to the image)."""
    x0, y0, x1, y1 = (int(round(float(b))) for b in box)
    m = np.zeros((height, width), bool)
    m[max(0, y0) : max(0, min(height, y1)), max(0, x0) : max(0, min(width, x1))] = True
    return m

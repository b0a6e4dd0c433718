"""The browser's camera as a goi Camera, and a goi Camera as the browser's pose.

The browser (viser) reports its camera as the camera-to-world rotation (a unit quaternion
w, x, y, z) and position in OpenCV axes (x right, y down, z forward: the axes goi's cameras
use), a vertical field of view and the canvas size. goi renders the mask at that camera at a
bounded size with the canvas's aspect, square pixels and the principal point at the centre:
exactly the camera a saved camera file (INRIA cameras.json) describes, so `goi render-mask
--camera-file` renders the same pixels.
"""

from __future__ import annotations

import math

import numpy as np

from stages.core.errors import GoiError
from stages.scene.cameras import Camera
from stages.scene.rotation import quat_to_rotmat, rotmat_to_quat

#: The long side of the mask the viewer renders at the browser's camera.
MASK_SIDE = 640
#: The narrowest field of view taken from a browser (radians, about 0.06 degrees); a narrower
#: one makes a focal length that is not a number a camera file can hold.
MIN_FOV = 1e-3


def render_size(width: int, height: int, side: int = MASK_SIDE) -> tuple[int, int]:
    """(width, height) with the canvas's aspect and the long side `side`."""
    ints = all(isinstance(v, int) and not isinstance(v, bool) for v in (width, height))
    if not ints or width <= 0 or height <= 0:
        raise GoiError(f"the browser reported a canvas of {width}x{height} pixels")
    s = side / max(width, height)
    return max(1, round(width * s)), max(1, round(height * s))


def browser_camera(
    name: str,
    wxyz: np.ndarray,
    position: np.ndarray,
    fov_y: float,
    width: int,
    height: int,
) -> Camera:
    """A goi Camera at the browser's pose: wxyz [4] camera-to-world, position [3], vertical
    field of view in radians, image width x height."""
    wxyz = np.asarray(wxyz, np.float64)
    position = np.asarray(position, np.float64)
    if not (np.isfinite(wxyz).all() and np.isfinite(position).all() and np.linalg.norm(wxyz)):
        raise GoiError("the browser reported a camera pose that is not finite")
    if not (isinstance(fov_y, int | float) and MIN_FOV <= fov_y <= math.pi - MIN_FOV):
        raise GoiError(f"the browser reported a field of view of {fov_y!r} radians")
    if not all(isinstance(v, int) and not isinstance(v, bool) for v in (width, height)):
        raise GoiError(f"the browser reported a canvas of {width!r}x{height!r} pixels")
    c2w = quat_to_rotmat(wxyz)
    R = c2w.T
    f = 0.5 * height / math.tan(0.5 * fov_y)
    return Camera(name, width, height, f, f, width / 2, height / 2, R, -R @ position)


def browser_pose(cam: Camera) -> tuple[np.ndarray, np.ndarray, float]:
    """(wxyz [4] camera-to-world, position [3], vertical field of view in radians) of a goi
    Camera, for flying the browser to it."""
    fov_y = 2.0 * math.atan(0.5 * cam.height / cam.fy)
    return rotmat_to_quat(np.asarray(cam.R, np.float64).T), cam.center.astype(np.float64), fov_y


def framing(
    selected: np.ndarray,
    means: np.ndarray,
    cams: list[Camera],
    up: np.ndarray,
    fov_y: float,
    sample: int = 20_000,
) -> tuple[np.ndarray, np.ndarray]:
    """(position [3], look-at [3]) of a camera that frames the selection `selected` [G] bool
    of the Gaussians at `means` [G, 3]: it looks at the selection's middle from the side of the
    training camera (of `cams`) that sees most of it, at the distance that fits its extent in
    the vertical field of view `fov_y`, and never further out than that camera (which stands
    where a photo could be taken: inside the room, not behind a wall)."""
    pts = np.asarray(means, np.float64)[np.asarray(selected, bool)]
    if not len(pts):
        raise GoiError("the answer selects no Gaussian: there is nothing to frame")
    if len(pts) > sample:  # a spread of them is enough to place the camera
        pts = pts[np.linspace(0, len(pts) - 1, sample).astype(np.int64)]
    lo, hi = np.percentile(pts, 5, axis=0), np.percentile(pts, 95, axis=0)
    middle = 0.5 * (lo + hi)
    radius = max(0.5 * float(np.linalg.norm(hi - lo)), 1e-6)
    seen = []
    for c in cams:
        with np.errstate(divide="ignore", invalid="ignore"):  # a centre at the eye's depth
            uv, z = c.project(pts)
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < c.width)
        inside &= (uv[:, 1] >= 0) & (uv[:, 1] < c.height)
        seen.append((int(inside.sum()), -float(np.linalg.norm(c.center - middle))))
    best = cams[max(range(len(cams)), key=lambda i: seen[i])]
    away = np.asarray(best.center, np.float64) - middle
    dist = float(np.linalg.norm(away))
    if dist < 1e-9:  # the camera stands in the middle of the selection: step back along it
        away, dist = -np.asarray(best.R, np.float64)[2], 1.0
    fit = radius / math.tan(0.5 * min(max(fov_y, 0.1), 3.0)) * 1.8  # a margin around it
    position = middle + away / dist * min(dist, fit)
    # a view straight down the up axis has no defined roll: lift the eye a little
    if abs(float(np.dot(away / dist, up))) > 0.99:
        position = position + 0.1 * radius * np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9
                                                      else [0.0, 1.0, 0.0])  # fmt: skip
    return position, middle

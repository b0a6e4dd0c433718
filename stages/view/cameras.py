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


def render_size(width: int, height: int, side: int = MASK_SIDE) -> tuple[int, int]:
    """(width, height) with the canvas's aspect and the long side `side`."""
    if width <= 0 or height <= 0:
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
    if not (0 < fov_y < math.pi):
        raise GoiError(f"the browser reported a field of view of {fov_y} radians")
    c2w = quat_to_rotmat(wxyz)
    R = c2w.T
    f = 0.5 * height / math.tan(0.5 * fov_y)
    return Camera(name, width, height, f, f, width / 2, height / 2, R, -R @ position)


def browser_pose(cam: Camera) -> tuple[np.ndarray, np.ndarray, float]:
    """(wxyz [4] camera-to-world, position [3], vertical field of view in radians) of a goi
    Camera, for flying the browser to it."""
    fov_y = 2.0 * math.atan(0.5 * cam.height / cam.fy)
    return rotmat_to_quat(np.asarray(cam.R, np.float64).T), cam.center.astype(np.float64), fov_y

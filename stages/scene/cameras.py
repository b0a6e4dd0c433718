"""Pinhole cameras, as every camera format goi reads becomes one.

A `Camera` holds the world-to-camera rotation and translation in OpenCV axes (x right, y down,
z forward) and intrinsics in pixels with pixel centres at integer + 0.5, which is the convention
of COLMAP, of the INRIA rasteriser and of goi's own. The readers and writers of each file format
live in `stages.scene.formats`, whose `load_cameras` tells the format by the file's content.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from stages.core.errors import GoiError

# OpenGL camera axes (y up, z backward) to OpenCV axes (y down, z forward).
GL_TO_CV = np.diag([1.0, -1.0, -1.0])
IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")
MAX_IMAGE_SIDE = 16384
#: A view is rendered into several float32 images of its size (features, alpha, depth, index):
#: larger views are refused before anything is allocated (the same limit as images on disk).
MAX_VIEW_PIXELS = 100_000_000


@dataclass
class Camera:
    name: str  # image name without extension; the key every artifact uses for the view
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    R: np.ndarray  # [3, 3] world-to-camera rotation (OpenCV axes)
    t: np.ndarray  # [3] world-to-camera translation
    image: str | None = None  # image file, as the camera file names it (may lack an extension)

    @property
    def center(self) -> np.ndarray:  # [3]
        return -self.R.T @ self.t

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points [N, 3] -> pixel coordinates [N, 2] (continuous) and depth [N]."""
        pc = points @ self.R.T + self.t
        z = pc[:, 2]
        uv = np.stack([self.fx * pc[:, 0] / z + self.cx, self.fy * pc[:, 1] / z + self.cy], 1)
        return uv, z

    def scaled(self, width: int, height: int) -> Camera:
        """The same camera for an image resized to width x height."""
        sx, sy = width / self.width, height / self.height
        return Camera(
            self.name,
            width,
            height,
            self.fx * sx,
            self.fy * sy,
            self.cx * sx,
            self.cy * sy,
            self.R,
            self.t,
            self.image,
        )


def checked(cam: Camera, where: str) -> Camera:
    if not (math.isfinite(cam.fx) and math.isfinite(cam.fy)) or cam.fx <= 0 or cam.fy <= 0:
        raise GoiError(
            f"{where}: camera '{cam.name}' has non-positive or non-finite focal length "
            f"(fx={cam.fx}, fy={cam.fy})"
        )
    if not (0 < cam.width <= MAX_IMAGE_SIDE and 0 < cam.height <= MAX_IMAGE_SIDE):
        raise GoiError(
            f"{where}: camera '{cam.name}' has image size {cam.width}x{cam.height}; "
            f"goi accepts 1..{MAX_IMAGE_SIDE} pixels a side"
        )
    if cam.width * cam.height > MAX_VIEW_PIXELS:
        raise GoiError(
            f"{where}: camera '{cam.name}' has image size {cam.width}x{cam.height} "
            f"({cam.width * cam.height / 1e6:.0f} megapixels); goi renders views of up to "
            f"{MAX_VIEW_PIXELS // 1_000_000} megapixels"
        )
    if not (math.isfinite(cam.cx) and math.isfinite(cam.cy)):
        raise GoiError(f"{where}: camera '{cam.name}' has a non-finite principal point")
    if not (np.isfinite(cam.R).all() and np.isfinite(cam.t).all()):
        raise GoiError(f"{where}: camera '{cam.name}' has a non-finite pose")
    # A rotation is orthonormal with determinant +1; a skewed or mirrored matrix would warp
    # every projection without any other sign of trouble.
    skew = float(np.abs(cam.R @ cam.R.T - np.eye(3)).max())
    det = float(np.linalg.det(cam.R))
    if skew > 1e-3 or abs(det - 1.0) > 1e-3:
        raise GoiError(
            f"{where}: camera '{cam.name}' rotation is not a rotation (det = {det:.4f}, "
            f"|R R^T - I| = {skew:.2g})"
        )
    return cam


def num(obj: dict, key: str, where: str) -> float:
    """A finite number field."""
    if key not in obj:
        raise GoiError(f"{where}: field '{key}' is missing")
    value = obj[key]
    try:
        if isinstance(value, bool):
            raise TypeError
        x = float(value)
    except (TypeError, ValueError, OverflowError):
        raise GoiError(f"{where}: field '{key}' is not a number ({str(value)[:40]!r})") from None
    if not math.isfinite(x):
        raise GoiError(f"{where}: field '{key}' is not a finite number ({x})")
    return x


def pixels(obj: dict, key: str, where: str) -> int:
    """An image side in pixels: a whole number in 1..MAX_IMAGE_SIDE."""
    x = num(obj, key, where)
    if x != int(x) or not 0 < x <= MAX_IMAGE_SIDE:
        raise GoiError(
            f"{where}: field '{key}' is {x:g}; goi accepts whole numbers of 1..{MAX_IMAGE_SIDE}"
        )
    return int(x)


def view_name_ok(name: str) -> bool:
    """A view name goi can key artifacts by: non-empty and printable (no NUL or control
    character). Names become file names only through `view_file_name`, never as they are."""
    return bool(name.strip()) and name.isprintable()


def matrix(obj: dict, key: str, shape: tuple[int, ...], where: str) -> np.ndarray:
    try:
        m = np.asarray(obj[key], dtype=np.float64)
    except KeyError:
        raise GoiError(f"{where}: field '{key}' is missing") from None
    except (TypeError, ValueError):
        raise GoiError(f"{where}: field '{key}' is not a numeric matrix") from None
    if m.shape != shape:
        raise GoiError(f"{where}: field '{key}' has shape {m.shape}, expected {shape}")
    return m


def stem(name: str) -> str:
    base = name.replace("\\", "/").rsplit("/", 1)[-1]
    root, ext = os.path.splitext(base)
    return root if ext in IMAGE_EXTS else base

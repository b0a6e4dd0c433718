"""Projection of 3D Gaussians to 2D screen-space Gaussians (EWA splatting), numba, per view."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from stages.render.constants import ALPHA_MIN, NEAR, TILE
from stages.scene.cameras import Camera


@dataclass
class Projected:
    """The per-view 2D Gaussians; radius 0 means culled."""

    means2d: np.ndarray  # [N, 2] float32, pixel-index coordinates (pixel (x, y) centre at x, y)
    conics: np.ndarray  # [N, 3] float32 (a, b, c): q = a dx^2 + 2 b dx dy + c dy^2
    extent: np.ndarray  # [N, 2] float32 half-size of the box where alpha can reach 1/255
    depths: np.ndarray  # [N] float32 camera-space z
    radii: np.ndarray  # [N] int32
    opacities: np.ndarray  # [N] float32


def _tan_fov(cam: Camera) -> tuple[float, float]:
    return (max(cam.cx, cam.width - cam.cx) / cam.fx, max(cam.cy, cam.height - cam.cy) / cam.fy)


@numba.njit(parallel=True, cache=True, fastmath=False)
def _project_kernel(
    means,
    quats,
    scales,
    opacities,
    valid,
    R,
    t,
    fx,
    fy,
    cx,
    cy,
    limx,
    limy,
    width,
    height,
    near,
    means2d,
    conics,
    extent,
    depths,
    radii,
):
    n = means.shape[0]
    tiles_x = (width + TILE - 1) // TILE
    tiles_y = (height + TILE - 1) // TILE
    for i in numba.prange(n):
        radii[i] = 0
        if not valid[i] or opacities[i] < ALPHA_MIN:
            continue
        px, py, pz = means[i, 0], means[i, 1], means[i, 2]
        tx = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz + t[0]
        ty = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz + t[1]
        tz = R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz + t[2]
        if tz <= near:
            continue
        # Sigma = M M^T with M = Rq S
        qw, qx, qy, qz = quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3]
        r00 = 1 - 2 * (qy * qy + qz * qz)
        r01 = 2 * (qx * qy - qw * qz)
        r02 = 2 * (qx * qz + qw * qy)
        r10 = 2 * (qx * qy + qw * qz)
        r11 = 1 - 2 * (qx * qx + qz * qz)
        r12 = 2 * (qy * qz - qw * qx)
        r20 = 2 * (qx * qz - qw * qy)
        r21 = 2 * (qy * qz + qw * qx)
        r22 = 1 - 2 * (qx * qx + qy * qy)
        s0, s1, s2 = scales[i, 0], scales[i, 1], scales[i, 2]
        m00, m01, m02 = r00 * s0, r01 * s1, r02 * s2
        m10, m11, m12 = r10 * s0, r11 * s1, r12 * s2
        m20, m21, m22 = r20 * s0, r21 * s1, r22 * s2
        # Clamp the Jacobian's lateral position as INRIA does (1.3 x the field of view).
        txtz = min(limx, max(-limx, tx / tz)) * tz
        tytz = min(limy, max(-limy, ty / tz)) * tz
        j00 = fx / tz
        j02 = -fx * txtz / (tz * tz)
        j11 = fy / tz
        j12 = -fy * tytz / (tz * tz)
        # T = J W M, a 2x3 matrix; cov2d = T T^T
        w0 = (
            R[0, 0] * m00 + R[0, 1] * m10 + R[0, 2] * m20,
            R[0, 0] * m01 + R[0, 1] * m11 + R[0, 2] * m21,
            R[0, 0] * m02 + R[0, 1] * m12 + R[0, 2] * m22,
        )
        w1 = (
            R[1, 0] * m00 + R[1, 1] * m10 + R[1, 2] * m20,
            R[1, 0] * m01 + R[1, 1] * m11 + R[1, 2] * m21,
            R[1, 0] * m02 + R[1, 1] * m12 + R[1, 2] * m22,
        )
        w2 = (
            R[2, 0] * m00 + R[2, 1] * m10 + R[2, 2] * m20,
            R[2, 0] * m01 + R[2, 1] * m11 + R[2, 2] * m21,
            R[2, 0] * m02 + R[2, 1] * m12 + R[2, 2] * m22,
        )
        a0 = j00 * w0[0] + j02 * w2[0]
        a1 = j00 * w0[1] + j02 * w2[1]
        a2 = j00 * w0[2] + j02 * w2[2]
        b0 = j11 * w1[0] + j12 * w2[0]
        b1 = j11 * w1[1] + j12 * w2[1]
        b2 = j11 * w1[2] + j12 * w2[2]
        ca = a0 * a0 + a1 * a1 + a2 * a2 + 0.3
        cb = a0 * b0 + a1 * b1 + a2 * b2
        cc = b0 * b0 + b1 * b1 + b2 * b2 + 0.3
        det = ca * cc - cb * cb
        if det <= 0.0:
            continue
        mid = 0.5 * (ca + cc)
        root = math.sqrt(max(0.1, mid * mid - det))
        radius = math.ceil(3.0 * math.sqrt(max(mid + root, mid - root)))
        mx = fx * tx / tz + cx - 0.5
        my = fy * ty / tz + cy - 0.5
        # A Gaussian touching no tile is culled.
        rx0, ry0, rx1, ry1 = tile_rect(mx, my, radius, tiles_x, tiles_y)
        if (rx1 - rx0) * (ry1 - ry0) == 0:
            continue
        q = 2.0 * math.log(255.0 * opacities[i])
        means2d[i, 0] = mx
        means2d[i, 1] = my
        conics[i, 0] = cc / det
        conics[i, 1] = -cb / det
        conics[i, 2] = ca / det
        extent[i, 0] = math.sqrt(q * ca)
        extent[i, 1] = math.sqrt(q * cc)
        depths[i] = tz
        radii[i] = radius


def project(means, quats, scales, opacities, valid, cam: Camera, near: float = NEAR) -> Projected:
    """Project Gaussians (activated values, see `Gaussians`) into `cam`."""
    n = means.shape[0]
    out = Projected(
        np.zeros((n, 2), np.float32),
        np.zeros((n, 3), np.float32),
        np.zeros((n, 2), np.float32),
        np.zeros(n, np.float32),
        np.zeros(n, np.int32),
        np.ascontiguousarray(opacities, np.float32),
    )
    limx, limy = _tan_fov(cam)
    _project_kernel(
        np.ascontiguousarray(means, np.float32),
        np.ascontiguousarray(quats, np.float32),
        np.ascontiguousarray(scales, np.float32),
        out.opacities,
        np.ascontiguousarray(valid, np.bool_),
        cam.R.astype(np.float32),
        cam.t.astype(np.float32),
        np.float32(cam.fx),
        np.float32(cam.fy),
        np.float32(cam.cx),
        np.float32(cam.cy),
        np.float32(1.3 * limx),
        np.float32(1.3 * limy),
        cam.width,
        cam.height,
        np.float32(near),
        out.means2d,
        out.conics,
        out.extent,
        out.depths,
        out.radii,
    )
    return out


@numba.njit(cache=True, inline="always")
def tile_rect(mx, my, radius, tiles_x, tiles_y):
    """INRIA's tile rectangle [x0, x1) x [y0, y1) of a Gaussian at (mx, my) with `radius`."""
    x0 = min(tiles_x, max(0, int((mx - radius) / TILE)))
    y0 = min(tiles_y, max(0, int((my - radius) / TILE)))
    x1 = min(tiles_x, max(0, int((mx + radius + TILE - 1) / TILE)))
    y1 = min(tiles_y, max(0, int((my + radius + TILE - 1) / TILE)))
    return x0, y0, x1, y1

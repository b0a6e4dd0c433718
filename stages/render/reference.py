"""The rasteriser written plainly in float64 numpy and Python loops: slow, obviously correct,
and the standard the numba kernels are held to in the tests."""

from __future__ import annotations

import math

import numpy as np

from stages.render.composite import Rendered
from stages.render.constants import ALPHA_MAX, ALPHA_MIN, NEAR, T_MIN, TILE
from stages.render.projection import Projected, _tan_fov
from stages.render.tiles import depth_order
from stages.scene.cameras import Camera
from stages.scene.rotation import quats_to_rotmats


def reference_project(
    means, quats, scales, opacities, valid, cam: Camera, near: float = NEAR
) -> Projected:
    """The projection written as the paper's matrix products, in float64 numpy."""
    n = means.shape[0]
    Rq = quats_to_rotmats(quats.astype(np.float64))
    S = np.einsum("nij,nj->nij", np.eye(3)[None].repeat(n, 0), scales.astype(np.float64))
    sigma = Rq @ S @ S.transpose(0, 2, 1) @ Rq.transpose(0, 2, 1)  # [N, 3, 3]
    W = cam.R.astype(np.float64)
    pc = means.astype(np.float64) @ W.T + cam.t  # [N, 3]
    z = pc[:, 2]
    limx, limy = _tan_fov(cam)
    zs = np.where(z > 0, z, 1.0)
    xc = np.clip(pc[:, 0] / zs, -1.3 * limx, 1.3 * limx) * zs
    yc = np.clip(pc[:, 1] / zs, -1.3 * limy, 1.3 * limy) * zs
    J = np.zeros((n, 2, 3))
    J[:, 0, 0] = cam.fx / zs
    J[:, 0, 2] = -cam.fx * xc / zs**2
    J[:, 1, 1] = cam.fy / zs
    J[:, 1, 2] = -cam.fy * yc / zs**2
    cov = J @ W[None] @ sigma @ W.T[None] @ J.transpose(0, 2, 1) + 0.3 * np.eye(2)[None]
    a, b, c = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
    det = a * c - b * b
    mid = 0.5 * (a + c)
    root = np.sqrt(np.maximum(0.1, mid * mid - det))
    radius = np.ceil(3 * np.sqrt(np.maximum(mid + root, mid - root)))
    mx = cam.fx * pc[:, 0] / zs + cam.cx - 0.5
    my = cam.fy * pc[:, 1] / zs + cam.cy - 0.5
    tiles_x, tiles_y = (cam.width + TILE - 1) // TILE, (cam.height + TILE - 1) // TILE
    rect = _reference_rect(mx, my, radius, tiles_x, tiles_y)
    ok = (
        valid
        & (opacities >= ALPHA_MIN)
        & (z > near)
        & (det > 0)
        & ((rect[2] - rect[0]) * (rect[3] - rect[1]) > 0)
    )
    safe_det = np.where(det > 0, det, 1.0)
    q = 2 * np.log(255 * np.maximum(opacities, ALPHA_MIN))
    f32 = np.float32
    return Projected(
        np.where(ok[:, None], np.stack([mx, my], 1), 0).astype(f32),
        np.where(ok[:, None], np.stack([c, -b, a], 1) / safe_det[:, None], 0).astype(f32),
        np.where(ok[:, None], np.sqrt(q[:, None] * np.stack([a, c], 1)), 0).astype(f32),
        np.where(ok, z, 0).astype(f32),
        np.where(ok, radius, 0).astype(np.int32),
        opacities.astype(f32),
    )


def _reference_rect(mx, my, r, tiles_x, tiles_y):
    def clamp(v, hi):
        return np.clip(np.trunc(v), 0, hi).astype(np.int64)

    return (
        clamp((mx - r) / TILE, tiles_x),
        clamp((my - r) / TILE, tiles_y),
        clamp((mx + r + TILE - 1) / TILE, tiles_x),
        clamp((my + r + TILE - 1) / TILE, tiles_y),
    )


def reference_weights(proj: Projected, width: int, height: int) -> list[list[tuple[int, float]]]:
    """Per pixel (row-major), the (Gaussian, alpha * T) it blends, front to back, in float64."""
    tiles_x, tiles_y = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    order = depth_order(proj)
    rx0, ry0, rx1, ry1 = _reference_rect(
        proj.means2d[order, 0].astype(np.float64),
        proj.means2d[order, 1].astype(np.float64),
        proj.radii[order].astype(np.float64),
        tiles_x,
        tiles_y,
    )
    out: list[list[tuple[int, float]]] = []
    for py in range(height):
        for px in range(width):
            tx, ty = px // TILE, py // TILE
            in_tile = (rx0 <= tx) & (tx < rx1) & (ry0 <= ty) & (ty < ry1)
            T, pix = 1.0, []
            for g in order[in_tile]:
                a, b, c = proj.conics[g].astype(np.float64)
                dx, dy = proj.means2d[g, 0] - px, proj.means2d[g, 1] - py
                power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
                if power > 0:
                    continue
                alpha = min(ALPHA_MAX, float(proj.opacities[g]) * math.exp(power))
                if alpha < ALPHA_MIN:
                    continue
                if T * (1 - alpha) < T_MIN:
                    break
                pix.append((int(g), alpha * T))
                T *= 1 - alpha
            out.append(pix)
    return out


def reference_render(
    proj: Projected,
    colors: np.ndarray,
    width: int,
    height: int,
    background: np.ndarray | None = None,
) -> Rendered:
    weights = reference_weights(proj, width, height)
    n_ch = colors.shape[1]
    img = np.zeros((height * width, n_ch))
    alpha = np.zeros(height * width)
    depth = np.zeros(height * width)
    for p, pix in enumerate(weights):
        for g, w in pix:
            img[p] += w * colors[g]
            alpha[p] += w
            depth[p] += w * proj.depths[g]
    if background is not None:
        img += (1 - alpha)[:, None] * np.asarray(background)
    depth = np.where(alpha > 0, depth / np.where(alpha > 0, alpha, 1), 0)
    return Rendered(
        img.reshape(height, width, n_ch).astype(np.float32),
        alpha.reshape(height, width).astype(np.float32),
        depth.reshape(height, width).astype(np.float32),
    )


def reference_lift(
    proj: Projected, width: int, height: int, mask: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """s1, s0 [N] of a mask [H, W] bool: every pixel's weights added to its Gaussians, float64."""
    n = proj.means2d.shape[0]
    s1, s0 = np.zeros(n), np.zeros(n)
    for p, pix in enumerate(reference_weights(proj, width, height)):
        dest = s1 if mask.flat[p] else s0
        for g, w in pix:
            dest[g] += w
    return s1, s0

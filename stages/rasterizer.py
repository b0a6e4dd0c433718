"""CPU Gaussian rasteriser with the standard 3DGS semantics, and its plain reference.

Semantics (INRIA's CUDA rasteriser): EWA projection cov2d = J W Sigma W^T J^T + 0.3 I, radius
ceil(3 sqrt(lambda_max)), 16x16 tiles, front-to-back compositing in depth order,
alpha = min(0.99, o exp(-q/2)), alpha < 1/255 skipped, a pixel stops before the Gaussian that
would bring its transmittance T below 1e-4. Features are composited without a background term.

The fast path is numba, parallel over tiles. Within a tile it loops Gaussians outside and pixels
inside, and only over the pixels where alpha can reach 1/255 (an exact bound: q <= 2 ln(255 o)),
so work follows each Gaussian's footprint instead of the tile's 256 pixels. `reference_*` below is
the slow, obviously correct version the tests hold it to.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from stages.cameras import Camera

TILE = 16
ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4
NEAR = 0.2  # INRIA's frustum cull: nothing closer than 0.2 to the camera plane is drawn

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (
    1.0925484305920792,
    -1.0925484305920792,
    0.31539156525252005,
    -1.0925484305920792,
    0.5462742152960396,
)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


@dataclass
class Projected:
    """The per-view 2D Gaussians; radius 0 means culled."""

    means2d: np.ndarray  # [N, 2] float32, pixel-index coordinates (pixel (x, y) centre at x, y)
    conics: np.ndarray  # [N, 3] float32 (a, b, c): q = a dx^2 + 2 b dx dy + c dy^2
    extent: np.ndarray  # [N, 2] float32 half-size of the box where alpha can reach 1/255
    depths: np.ndarray  # [N] float32 camera-space z
    radii: np.ndarray  # [N] int32
    opacities: np.ndarray  # [N] float32


@dataclass
class Bins:
    """Gaussians per tile, each tile's list in front-to-back order."""

    tiles_x: int
    tiles_y: int
    offsets: np.ndarray  # [tiles + 1] int64 into `ids`
    ids: np.ndarray  # [pairs] int32


def quats_to_rotmats(q: np.ndarray) -> np.ndarray:
    """[N, 4] unit (w, x, y, z) -> [N, 3, 3]."""
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    return np.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        axis=1,
    ).reshape(-1, 3, 3)


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
        rx0, ry0, rx1, ry1 = _tile_rect(mx, my, radius, tiles_x, tiles_y)
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
def _tile_rect(mx, my, radius, tiles_x, tiles_y):
    """INRIA's tile rectangle [x0, x1) x [y0, y1) of a Gaussian at (mx, my) with `radius`."""
    x0 = min(tiles_x, max(0, int((mx - radius) / TILE)))
    y0 = min(tiles_y, max(0, int((my - radius) / TILE)))
    x1 = min(tiles_x, max(0, int((mx + radius + TILE - 1) / TILE)))
    y1 = min(tiles_y, max(0, int((my + radius + TILE - 1) / TILE)))
    return x0, y0, x1, y1


@numba.njit(cache=True)
def _bin_kernel(order, means2d, radii, tiles_x, tiles_y):
    n_tiles = tiles_x * tiles_y
    counts = np.zeros(n_tiles + 1, np.int64)
    for g in order:
        r = radii[g]
        if r == 0:
            continue
        x0, y0, x1, y1 = _tile_rect(means2d[g, 0], means2d[g, 1], r, tiles_x, tiles_y)
        for ty in range(y0, y1):
            for tx in range(x0, x1):
                counts[ty * tiles_x + tx + 1] += 1
    offsets = np.cumsum(counts)
    cursor = offsets[:-1].copy()
    ids = np.empty(offsets[-1], np.int32)
    for g in order:  # in depth order, so every tile's list comes out sorted front to back
        r = radii[g]
        if r == 0:
            continue
        x0, y0, x1, y1 = _tile_rect(means2d[g, 0], means2d[g, 1], r, tiles_x, tiles_y)
        for ty in range(y0, y1):
            for tx in range(x0, x1):
                ids[cursor[ty * tiles_x + tx]] = g
                cursor[ty * tiles_x + tx] += 1
    return offsets, ids


def depth_order(proj: Projected) -> np.ndarray:
    """Visible Gaussians front to back; equal depths keep their index order."""
    vis = np.flatnonzero(proj.radii > 0).astype(np.int32)
    return vis[np.argsort(proj.depths[vis], kind="stable")]


def bin_tiles(proj: Projected, width: int, height: int) -> Bins:
    tx, ty = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    offsets, ids = _bin_kernel(depth_order(proj), proj.means2d, proj.radii, tx, ty)
    return Bins(tx, ty, offsets, ids)


# One walk serves every use of the weights w = alpha * T: compositing colours (RENDER),
# counting and recording them per pixel for the blend cache (COUNT, RECORD), and pushing a
# gradient back to per-Gaussian values (BACKWARD, the naive design the cache replaces). One
# kernel keeps the alpha / transmittance rules in one place; the mode branch is loop-invariant
# and costs nothing measurable.
RENDER, COUNT, RECORD, BACKWARD = 0, 1, 2, 3


# fastmath: about 10% faster; no NaN reaches here (the PLY reader refuses them).
@numba.njit(parallel=True, cache=True, fastmath=True)
def _walk_kernel(
    mode,
    offsets,
    ids,
    means2d,
    conics,
    extent,
    opacities,
    depths,
    colors,
    width,
    height,
    tiles_x,
    out,
    alpha_out,
    depth_out,
    counts,
    row_ptr,
    w_ids,
    w_vals,
    grad_out,
    grad_colors,
):
    n_tiles = offsets.shape[0] - 1
    n_ch = colors.shape[1]
    for tile in numba.prange(n_tiles):
        x0 = (tile % tiles_x) * TILE
        y0 = (tile // tiles_x) * TILE
        x1 = min(x0 + TILE, width)
        y1 = min(y0 + TILE, height)
        T = np.ones(TILE * TILE, np.float32)
        acc = np.zeros((TILE * TILE, n_ch), np.float32)
        dacc = np.zeros(TILE * TILE, np.float32)
        n_rec = np.zeros(TILE * TILE, np.int64)
        done = np.zeros(TILE * TILE, np.bool_)
        n_left = (x1 - x0) * (y1 - y0)
        tid = numba.get_thread_id()
        for k in range(offsets[tile], offsets[tile + 1]):
            g = ids[k]
            mx, my = means2d[g, 0], means2d[g, 1]
            ca, cb, cc = conics[g, 0], conics[g, 1], conics[g, 2]
            o = opacities[g]
            q_max = 2.0 * math.log(255.0 * o)
            gx0 = max(x0, int(math.floor(mx - extent[g, 0])))
            gx1 = min(x1, int(math.ceil(mx + extent[g, 0])) + 1)
            gy0 = max(y0, int(math.floor(my - extent[g, 1])))
            gy1 = min(y1, int(math.ceil(my + extent[g, 1])) + 1)
            for py in range(gy0, gy1):
                dy = my - np.float32(py)
                # This row's span of the ellipse q <= q_max, widened by a pixel for rounding.
                disc = cb * cb * dy * dy - ca * (cc * dy * dy - q_max)
                if disc < 0.0:
                    continue
                root = math.sqrt(disc)
                sx0 = max(gx0, int(math.floor(mx - (root - cb * dy) / ca)) - 1)
                sx1 = min(gx1, int(math.ceil(mx + (root + cb * dy) / ca)) + 2)
                for px in range(sx0, sx1):
                    p = (py - y0) * TILE + (px - x0)
                    if done[p]:
                        continue
                    dx = mx - np.float32(px)
                    power = np.float32(-0.5) * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
                    if power > 0.0:
                        continue
                    alpha = min(np.float32(ALPHA_MAX), o * np.exp(power))
                    if alpha < ALPHA_MIN:
                        continue
                    test_t = T[p] * (np.float32(1.0) - alpha)
                    if test_t < T_MIN:
                        done[p] = True
                        n_left -= 1
                        continue
                    w = alpha * T[p]
                    if mode == RENDER:
                        for c in range(n_ch):
                            acc[p, c] += w * colors[g, c]
                        dacc[p] += w * depths[g]
                    elif mode == COUNT:
                        n_rec[p] += 1
                    elif mode == RECORD:
                        j = row_ptr[py * width + px] + n_rec[p]
                        w_ids[j] = g
                        w_vals[j] = w
                        n_rec[p] += 1
                    else:
                        for c in range(n_ch):
                            grad_colors[tid, g, c] += w * grad_out[py, px, c]
                    T[p] = test_t
            if n_left == 0:
                break
        for py in range(y0, y1):
            for px in range(x0, x1):
                p = (py - y0) * TILE + (px - x0)
                if mode == RENDER:
                    for c in range(n_ch):
                        out[py, px, c] = acc[p, c]
                    alpha_out[py, px] = 1.0 - T[p]
                    depth_out[py, px] = dacc[p]
                elif mode == COUNT:
                    counts[py * width + px] = n_rec[p]


_NO_F = np.zeros((0, 0), np.float32)
_NO_F1 = np.zeros(0, np.float32)
_NO_F3 = np.zeros((0, 0, 0), np.float32)
_NO_I = np.zeros(0, np.int64)
_NO_I32 = np.zeros(0, np.int32)


def _walk(
    mode,
    proj: Projected,
    bins: Bins,
    width: int,
    height: int,
    colors=_NO_F,
    out=_NO_F3,
    alpha=_NO_F,
    depth=_NO_F,
    counts=_NO_I,
    row_ptr=_NO_I,
    w_ids=_NO_I32,
    w_vals=_NO_F1,
    grad_out=_NO_F3,
    grad_colors=_NO_F3,
) -> None:
    _walk_kernel(
        mode,
        bins.offsets,
        bins.ids,
        proj.means2d,
        proj.conics,
        proj.extent,
        proj.opacities,
        proj.depths,
        colors,
        width,
        height,
        bins.tiles_x,
        out,
        alpha,
        depth,
        counts,
        row_ptr,
        w_ids,
        w_vals,
        grad_out,
        grad_colors,
    )


def blend_weights(
    proj: Projected, bins: Bins, width: int, height: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The view's blending weights as CSR (indptr [P + 1], Gaussian ids [nnz], w [nnz]).

    Rows are pixels in row-major order; within a row the entries are front to back.
    """
    counts = np.zeros(width * height, np.int64)
    _walk(COUNT, proj, bins, width, height, counts=counts)
    indptr = np.zeros(width * height + 1, np.int64)
    np.cumsum(counts, out=indptr[1:])
    ids = np.empty(indptr[-1], np.int32)
    vals = np.empty(indptr[-1], np.float32)
    _walk(RECORD, proj, bins, width, height, row_ptr=indptr, w_ids=ids, w_vals=vals)
    return indptr, ids, vals


def render_backward(
    proj: Projected, bins: Bins, grad_image: np.ndarray, n_gaussians: int
) -> np.ndarray:
    """d loss / d colors [N, C] given d loss / d image [H, W, C], by walking the tiles again."""
    height, width, n_ch = grad_image.shape
    buf = np.zeros((numba.get_num_threads(), n_gaussians, n_ch), np.float32)
    _walk(
        BACKWARD,
        proj,
        bins,
        width,
        height,
        colors=np.zeros((0, n_ch), np.float32),
        grad_out=np.ascontiguousarray(grad_image, np.float32),
        grad_colors=buf,
    )
    return buf.sum(axis=0)


@dataclass
class Rendered:
    image: np.ndarray  # [H, W, C] float32: RGB (with background) or features (without)
    alpha: np.ndarray  # [H, W] float32, 1 - final transmittance
    depth: np.ndarray  # [H, W] float32, expected depth sum(w z) / alpha (0 where alpha = 0)


def render(
    proj: Projected,
    bins: Bins,
    colors: np.ndarray,
    width: int,
    height: int,
    background: np.ndarray | None = None,
) -> Rendered:
    """Composite per-Gaussian values `colors` [N, C] (RGB or features) into an image."""
    colors = np.ascontiguousarray(colors, np.float32)
    out = np.empty((height, width, colors.shape[1]), np.float32)
    alpha = np.empty((height, width), np.float32)
    depth = np.empty((height, width), np.float32)
    _walk(RENDER, proj, bins, width, height, colors=colors, out=out, alpha=alpha, depth=depth)
    if background is not None:
        out += (1.0 - alpha)[:, :, None] * np.asarray(background, np.float32)
    with np.errstate(invalid="ignore", divide="ignore"):
        depth = np.where(alpha > 0, depth / alpha, 0.0).astype(np.float32)
    return Rendered(out, alpha, depth)


def sh_to_rgb(sh: np.ndarray, means: np.ndarray, center: np.ndarray) -> np.ndarray:
    """View-dependent colour [N, 3] from SH [N, K, 3] of degree 0-3, as INRIA evaluates it."""
    k = sh.shape[1]
    rgb = SH_C0 * sh[:, 0]
    if k > 1:
        d = means - center[None].astype(np.float32)
        d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
        x, y, z = d[:, 0:1], d[:, 1:2], d[:, 2:3]
        rgb = rgb - SH_C1 * y * sh[:, 1] + SH_C1 * z * sh[:, 2] - SH_C1 * x * sh[:, 3]
        if k > 4:
            xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
            rgb = (
                rgb
                + SH_C2[0] * xy * sh[:, 4]
                + SH_C2[1] * yz * sh[:, 5]
                + SH_C2[2] * (2 * zz - xx - yy) * sh[:, 6]
                + SH_C2[3] * xz * sh[:, 7]
                + SH_C2[4] * (xx - yy) * sh[:, 8]
            )
            if k > 9:
                rgb = (
                    rgb
                    + SH_C3[0] * y * (3 * xx - yy) * sh[:, 9]
                    + SH_C3[1] * xy * z * sh[:, 10]
                    + SH_C3[2] * y * (4 * zz - xx - yy) * sh[:, 11]
                    + SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * sh[:, 12]
                    + SH_C3[4] * x * (4 * zz - xx - yy) * sh[:, 13]
                    + SH_C3[5] * z * (xx - yy) * sh[:, 14]
                    + SH_C3[6] * x * (xx - 3 * yy) * sh[:, 15]
                )
    return np.maximum(rgb + 0.5, 0.0).astype(np.float32)


class Rasterizer:
    """Renders one scene's Gaussians from any camera (RGB, features, alpha, depth).

    `backend`: "cpu" (numba), "gsplat" (CUDA, needs gsplat) or "auto" (gsplat when present).
    """

    def __init__(self, means, quats, scales, opacities, sh, valid, backend: str = "cpu"):
        self.means = np.ascontiguousarray(means, np.float32)  # [N, 3]
        self.quats = np.ascontiguousarray(quats, np.float32)  # [N, 4]
        self.scales = np.ascontiguousarray(scales, np.float32)  # [N, 3]
        self.opacities = np.ascontiguousarray(opacities, np.float32)  # [N]
        self.sh = np.ascontiguousarray(sh, np.float32)  # [N, K, 3]
        self.valid = np.ascontiguousarray(valid, np.bool_)  # [N]
        if backend == "auto":
            from stages.gpu import gsplat_available

            backend = "gsplat" if gsplat_available() else "cpu"
        self.backend = backend

    @classmethod
    def from_gaussians(cls, g, backend: str = "cpu") -> Rasterizer:  # noqa: ANN001
        return cls(g.means, g.quats, g.scales, g.opacities, g.sh, g.valid, backend)

    def prepare(self, cam: Camera) -> tuple[Projected, Bins]:
        proj = project(self.means, self.quats, self.scales, self.opacities, self.valid, cam)
        return proj, bin_tiles(proj, cam.width, cam.height)

    def render_rgb(self, cam: Camera, background=(0.0, 0.0, 0.0)) -> Rendered:
        if self.backend == "gsplat":
            from stages.gpu import render_gsplat

            return render_gsplat(self, cam, None, np.asarray(background, np.float32))
        proj, bins = self.prepare(cam)
        colors = sh_to_rgb(self.sh, self.means, cam.center)
        return render(proj, bins, colors, cam.width, cam.height, np.asarray(background))

    def contribution(self, cam: Camera) -> np.ndarray:
        """[N] float64: each Gaussian's blending weight summed over the view's pixels (how much
        of the image it makes; 0 for Gaussians the view does not see)."""
        proj, bins = self.prepare(cam)
        _, ids, w = blend_weights(proj, bins, cam.width, cam.height)
        return np.bincount(ids, weights=w, minlength=self.means.shape[0])

    def render_features(self, cam: Camera, features: np.ndarray) -> Rendered:
        if self.backend == "gsplat":
            from stages.gpu import render_gsplat

            return render_gsplat(self, cam, np.asarray(features, np.float32))
        proj, bins = self.prepare(cam)
        return render(proj, bins, features, cam.width, cam.height)


# --- reference ---------------------------------------------------------------------------


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

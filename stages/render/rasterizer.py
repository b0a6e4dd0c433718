"""`Rasterizer`: one scene's Gaussians rendered from any camera (RGB, features, alpha, depth).

The CPU path is goi's numba kernels (projection, tiles, composite). A GPU backend, when one is
given, renders instead; the rasteriser never imports one itself (see `gsplat_backend`).
"""

from __future__ import annotations

from typing import Any, Protocol

import numba
import numpy as np

from stages.render.composite import Rendered, blend_weights, render
from stages.render.projection import Projected, project
from stages.render.sh import sh_to_rgb
from stages.render.tiles import Bins, View, bin_tiles, compact_view
from stages.scene.cameras import Camera


class RenderBackend(Protocol):
    """Another implementation of the same rasterisation rules (e.g. gsplat on CUDA)."""

    name: str

    def render(
        self,
        rast: Rasterizer,
        cam: Camera,
        values: np.ndarray | None,
        background: np.ndarray | None,
    ) -> Rendered:
        """RGB from the SH (values None) or per-Gaussian values [N, C], composited at `cam`."""
        ...


class Rasterizer:
    def __init__(
        self,
        means: np.ndarray,
        quats: np.ndarray,
        scales: np.ndarray,
        opacities: np.ndarray,
        sh: np.ndarray,
        valid: np.ndarray,
        backend: RenderBackend | None = None,
    ):
        self.means = np.ascontiguousarray(means, np.float32)  # [N, 3]
        self.quats = np.ascontiguousarray(quats, np.float32)  # [N, 4] unit (w, x, y, z)
        self.scales = np.ascontiguousarray(scales, np.float32)  # [N, 3]
        self.opacities = np.ascontiguousarray(opacities, np.float32)  # [N]
        self.sh = np.ascontiguousarray(sh, np.float32)  # [N, K, 3]
        self.valid = np.ascontiguousarray(valid, np.bool_)  # [N]
        self.backend = backend

    @property
    def backend_name(self) -> str:
        return "cpu" if self.backend is None else self.backend.name

    @classmethod
    def from_gaussians(cls, g: Any, backend: RenderBackend | None = None) -> Rasterizer:
        """From a `stages.scene.gaussians.Gaussians`."""
        return cls(g.means, g.quats, g.scales, g.opacities, g.sh, g.valid, backend)

    def prepare(self, cam: Camera) -> tuple[Projected, Bins]:
        """The projection of every Gaussian and the tiles' lists in scene indices (for callers
        that keep per-Gaussian results in scene order: weights, gradients, lifting)."""
        proj = project(self.means, self.quats, self.scales, self.opacities, self.valid, cam)
        return proj, bin_tiles(proj, cam.width, cam.height)

    def view(self, cam: Camera) -> View:
        """The Gaussians `cam` sees, in rows of their own (what a render walks; see `View`)."""
        proj = project(self.means, self.quats, self.scales, self.opacities, self.valid, cam)
        return compact_view(proj, cam.width, cam.height)

    def colors(self, cam: Camera, rows: np.ndarray | None = None) -> np.ndarray:
        """View-dependent RGB [N, 3] of the SH, or [len(rows), 3] of the Gaussians `rows` only."""
        if rows is None:
            return sh_to_rgb(self.sh, self.means, cam.center)
        return sh_to_rgb(take_rows(self.sh, rows), take_rows(self.means, rows), cam.center)

    def render_rgb(self, cam: Camera, background: Any = (0.0, 0.0, 0.0)) -> Rendered:
        bg = np.asarray(background, np.float32)
        if self.backend is not None:
            return self.backend.render(self, cam, None, bg)
        view = self.view(cam)
        colors = self.colors(cam, view.gaussians)
        return render(view.proj, view.bins, colors, cam.width, cam.height, bg)

    def render_features(self, cam: Camera, features: np.ndarray) -> Rendered:
        """Per-Gaussian values [N, C] composited without background."""
        if self.backend is not None:
            return self.backend.render(self, cam, np.asarray(features, np.float32), None)
        view = self.view(cam)
        return self.render_view(cam, view, take_rows(features, view.gaussians))

    def render_view(self, cam: Camera, view: View, values: np.ndarray) -> Rendered:
        """Per-row values [V, C] of `view` (values[r] belongs to Gaussian view.gaussians[r])
        composited without background."""
        return render(view.proj, view.bins, values, cam.width, cam.height)

    def contribution(self, cam: Camera) -> np.ndarray:
        """[N] float64: each Gaussian's blending weight summed over the view's pixels (how much
        of the image it makes; 0 for Gaussians the view does not see)."""
        view = self.view(cam)
        _, rows, w = blend_weights(view.proj, view.bins, cam.width, cam.height)
        return np.bincount(view.gaussians[rows], weights=w, minlength=self.means.shape[0])


@numba.njit(parallel=True, cache=True)
def _take_rows(values, rows, out):
    for r in numba.prange(rows.shape[0]):
        out[r] = values[rows[r]]


def take_rows(values: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """values[rows] as contiguous float32 (a parallel gather: the view's rows of a [G, ...]
    array, without converting or copying the rest)."""
    out = np.empty((rows.shape[0], *values.shape[1:]), np.float32)
    if values.dtype != np.float32 or not values.flags.c_contiguous:
        out[:] = values[rows]
    elif rows.shape[0]:
        flat = values.reshape(values.shape[0], -1)
        _take_rows(flat, rows, out.reshape(rows.shape[0], -1))
    return out

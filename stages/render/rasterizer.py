"""`Rasterizer`: one scene's Gaussians rendered from any camera (RGB, features, alpha, depth).

The CPU path is goi's numba kernels (projection, tiles, composite). A GPU backend, when one is
given, renders instead; the rasteriser never imports one itself (see `gsplat_backend`).
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Iterable
from typing import Any, Protocol

import numba
import numpy as np

from stages.render.composite import Rendered, blend_weights, render
from stages.render.lift import lift_mask, visibility
from stages.render.projection import Projected, project
from stages.render.sh import sh_to_rgb
from stages.render.tiles import Bins, View, bin_tiles, compact_view
from stages.scene.cameras import Camera

#: What a process answering prompt after prompt keeps of its cameras' projections and tiles
#: (`Rasterizer.keep_views`): every camera of the dev room (about 8 MB each at 121k Gaussians, and
#: 1 MB of visibility once a mask is lifted there),
#: about 80 cameras of a 300k-Gaussian scene.
KEEP_VIEWS_BYTES = 1 << 30


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
        # (what, camera) -> (bytes, Projected and Bins, or View), least recently used first
        self._kept: OrderedDict[tuple, tuple[int, Any]] = OrderedDict()
        self._keep_bytes = 0
        self._keepable: set[tuple] = set()

    @property
    def backend_name(self) -> str:
        return "cpu" if self.backend is None else self.backend.name

    @classmethod
    def from_gaussians(cls, g: Any, backend: RenderBackend | None = None) -> Rasterizer:
        """From a `stages.scene.gaussians.Gaussians`."""
        return cls(g.means, g.quats, g.scales, g.opacities, g.sh, g.valid, backend)

    def keep_views(self, max_bytes: int, cameras: Iterable[Camera]) -> None:
        """Keep the projection and tiles (`prepare`, `view`) of these `cameras` for the calls
        after, up to `max_bytes` in all, the least recently used going first (0: keep none,
        the default). A process that answers prompt after prompt asks the same cameras each
        time (goi view, goi eval: the training views lifted, the masks at the test views);
        other cameras (the browser's, which moves) are not kept. The kept arrays are
        read-only, and the scene's Gaussians must not change while they are kept. One thread
        at a time: goi view's renders and answers already take turns (stages.view.worker's
        gate), and nothing else renders from two threads."""
        self._keep_bytes = max(0, int(max_bytes))
        self._keepable = {_camera_key(c) for c in cameras}
        self._evict()

    @property
    def keeping(self) -> bool:
        """Whether some cameras' projections are kept (keep_views)."""
        return self._keep_bytes > 0

    def kept_bytes(self) -> int:
        return sum(n for n, _ in self._kept.values())

    def prepare(self, cam: Camera) -> tuple[Projected, Bins]:
        """The projection of every Gaussian and the tiles' lists in scene indices (for callers
        that keep per-Gaussian results in scene order: weights, gradients, lifting)."""
        key = ("prepare", *_camera_key(cam))
        if key in self._kept:
            self._kept.move_to_end(key)
            return self._kept[key][1]
        proj = project(self.means, self.quats, self.scales, self.opacities, self.valid, cam)
        out = proj, bin_tiles(proj, cam.width, cam.height)
        self._keep(key, out, [*vars(out[0]).values(), *vars(out[1]).values()])
        return out

    def visibility(self, cam: Camera) -> np.ndarray:
        """[N] float64: each Gaussian's blend weight summed over the view (the s0 of an empty
        mask's lift; 0 where the view does not see it); kept with the view's projection."""
        key = ("visibility", *_camera_key(cam))
        if key in self._kept:
            self._kept.move_to_end(key)
            return self._kept[key][1]
        proj, bins = self.prepare(cam)
        out = visibility(proj, bins, cam.width, cam.height)
        self._keep(key, out, [out])
        return out

    def lift(self, cam: Camera, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The view's s1, s0 [N] float64 of `mask` [H, W] bool (stages.render.lift.lift_mask).
        A view whose projection is kept gets its visibility kept too, and each mask's walk
        then covers only the tiles around the mask: the same numbers, a fraction of the walk."""
        if mask.shape != (cam.height, cam.width):
            raise ValueError(f"mask {mask.shape} != view {cam.name}'s ({cam.height}, {cam.width})")
        proj, bins = self.prepare(cam)
        kept = self._keeps(_camera_key(cam))
        return lift_mask(proj, bins, mask, self.visibility(cam) if kept else None)

    def view(self, cam: Camera) -> View:
        """The Gaussians `cam` sees, in rows of their own (what a render walks; see `View`)."""
        key = ("view", *_camera_key(cam))
        if key in self._kept:
            self._kept.move_to_end(key)
            return self._kept[key][1]
        proj = project(self.means, self.quats, self.scales, self.opacities, self.valid, cam)
        out = compact_view(proj, cam.width, cam.height)
        arrays = [*vars(out.proj).values(), *vars(out.bins).values(), out.gaussians]
        self._keep(key, out, arrays)
        return out

    def _keeps(self, camera_key: tuple) -> bool:
        """Whether the camera's results are kept (keep_views named it, with a budget)."""
        return self._keep_bytes > 0 and camera_key in self._keepable

    def _keep(self, key: tuple, value: Any, parts: list[Any]) -> None:
        if not self._keeps(key[1:]):
            return
        # a projection may hand the scene's own arrays through (its opacities): those are
        # neither counted nor made read-only
        own = (self.means, self.quats, self.scales, self.opacities, self.sh, self.valid)
        arrays = [
            a for a in parts
            if isinstance(a, np.ndarray) and not any(np.may_share_memory(a, o) for o in own)
        ]  # fmt: skip
        size = sum(a.nbytes for a in arrays)
        if size > self._keep_bytes:
            return
        for a in arrays:  # a caller that wrote into a kept array would change later answers
            a.flags.writeable = False
        self._kept[key] = (size, value)
        self._evict()

    def _evict(self) -> None:
        total = self.kept_bytes()
        while self._kept and total > self._keep_bytes:
            _, (size, _) = self._kept.popitem(last=False)
            total -= size

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


def _camera_key(cam: Camera) -> tuple:
    """A camera by everything its projection depends on (two cameras of one name may differ:
    `Camera.scaled`, the viewer's free camera)."""
    return (
        cam.name, cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy,
        np.asarray(cam.R, np.float64).tobytes(), np.asarray(cam.t, np.float64).tobytes(),
    )  # fmt: skip


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

"""The frozen-geometry blend cache: every training view's blend weights, built once, on disk.

GOI never moves the Gaussians while it fits semantics, so for a fixed view the rendered feature
map is linear in the per-Gaussian features: F_view = W_view f, with W_view a sparse
[pixels x Gaussians] matrix of blending weights alpha_i T_i. Rasterise every training view once,
keep W_view, and each training step is a sparse product (and its transpose for the gradient)
instead of a rasterisation.

Columns are stored in Morton (Z-curve) order of the Gaussian centres: Gaussians that meet at a
pixel sit close in memory, which is what makes the sparse products fast.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from stages.core.artifacts import check_writable, open_h5, put, stamp, write_h5
from stages.core.errors import GoiError
from stages.core.files import create_partial, finish_partial, partial_exists, regular_file
from stages.core.hdf5 import read_h5
from stages.core.report import SILENT, Report, size_text
from stages.core.staging import kept_on_interrupt
from stages.render.composite import blend_weights, pooled_blend_weights
from stages.render.rasterizer import Rasterizer
from stages.scene.cameras import Camera
from stages.scene.scene import Scene
from stages.semantics.weights import morton_order, pixel_cells, pool, top_k

SCHEMA = "goi.blend_cache"


@dataclass
class ViewWeights:
    """One view's W as CSR [height * width, n_gaussians]; columns are positions in `order`."""

    width: int
    height: int
    indptr: np.ndarray  # [P + 1] int64
    indices: np.ndarray  # [nnz] int32
    weights: np.ndarray  # [nnz] float32
    mass_kept: float  # sum of kept weights / sum of all weights (1 without top-K)
    entries_total: int  # entries before top-K

    @property
    def nbytes(self) -> int:
        return self.indptr.nbytes + self.indices.nbytes + self.weights.nbytes


def view_weights(
    rast: Rasterizer,
    cam: Camera,
    position: np.ndarray,
    k: int = 0,
    size: tuple[int, int] | None = None,
    fused: bool = True,
) -> ViewWeights:
    """Rasterise `cam` once and keep its weights; `position` maps Gaussian id -> column.
    With `size` (width, height) smaller than the image, pixels are pooled into that grid:
    without top-K, in the walk itself (`fused`; the per-pixel weights are never held), else
    by pooling the per-pixel CSR (the reference the fused walk is tested against)."""
    proj, bins = rast.prepare(cam)
    w, h = size or (cam.width, cam.height)
    pooled = (w, h) != (cam.width, cam.height)
    if pooled and k <= 0 and fused:
        cx, cy = pixel_cells(cam.width, w), pixel_cells(cam.height, h)
        kp, ki, kv, n = pooled_blend_weights(proj, bins, cam.width, cam.height, cx, cy, position)
        return ViewWeights(w, h, kp, ki, kv, 1.0, n)
    indptr, ids, vals = blend_weights(proj, bins, cam.width, cam.height)
    total = float(vals.sum(dtype=np.float64))
    kp, ki, kv = top_k(indptr, position[ids], vals, k)
    kept = float(kv.sum(dtype=np.float64))
    if pooled:
        kp, ki, kv = pool(kp, ki, kv, cam.width, cam.height, w, h, len(position))
    return ViewWeights(w, h, kp, ki, kv, kept / total if total > 0 else 1.0, int(len(ids)))


@dataclass
class BlendCache:
    order: np.ndarray  # [G] int32: column j is Gaussian order[j]
    views: dict[str, ViewWeights]
    top_k: int
    ply_sha256: str
    cameras_sha256: str

    @property
    def n_gaussians(self) -> int:
        return int(len(self.order))

    def save(self, path: str | os.PathLike[str], force: bool = True) -> None:
        inputs = {"ply": self.ply_sha256, "cameras": self.cameras_sha256}
        with write_h5(path, SCHEMA, inputs, force=force) as f:
            f.attrs.update(
                n_gaussians=self.n_gaussians,
                top_k=self.top_k,
                ply_sha256=self.ply_sha256,
                cameras_sha256=self.cameras_sha256,
            )
            put(f, "order", self.order)
            views = f.create_group("views", track_order=True)
            for name, vw in self.views.items():
                write_view(views, name, vw)

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> BlendCache:
        with open_h5(path, SCHEMA) as f:
            n = int(f.attrs["n_gaussians"])
            views = {
                name: read_view(grp, n, f"{path}: view '{name}'")
                for name, grp in f["views"].items()
            }
            return cls(
                read_order(f, path),
                views,
                int(f.attrs["top_k"]),
                str(f.attrs["ply_sha256"]),
                str(f.attrs["cameras_sha256"]),
            )

    def weight_stats(self) -> dict[str, float]:
        n_views = max(len(self.views), 1)
        return {
            "views": float(len(self.views)),
            "entries_per_pixel": sum(len(v.indices) for v in self.views.values())
            / max(sum(v.width * v.height for v in self.views.values()), 1),
            "mass_kept": sum(v.mass_kept for v in self.views.values()) / n_views,
            "mib_per_view": sum(v.nbytes for v in self.views.values()) / n_views / 2**20,
        }


def read_order(f: h5py.File, path: str | os.PathLike[str]) -> np.ndarray:
    """The cache's column order [G] int32, checked to be a permutation."""
    n = int(f.attrs["n_gaussians"])
    order = f["order"][()]
    if order.shape != (n,) or not np.array_equal(np.sort(order), np.arange(n)):
        raise GoiError(f"{path}: 'order' is not a permutation of the {n} Gaussians")
    return order


def read_view(
    grp: h5py.Group,
    n_gaussians: int,
    where: str,
    check: bool = True,
    indices: np.ndarray | None = None,
    weights: np.ndarray | None = None,
) -> ViewWeights:
    """One view's weights from its group in a cache file, checked unless told otherwise; read
    into `indices` and `weights` when given (slices of a larger array, of the right size)."""
    a = grp.attrs
    vw = ViewWeights(
        int(a["width"]),
        int(a["height"]),
        grp["indptr"][()],
        _read_into(grp["indices"], indices),
        _read_into(grp["weights"], weights),
        float(a["mass_kept"]),
        int(a["entries_total"]),
    )
    if len(vw.indptr) != vw.width * vw.height + 1:
        raise GoiError(
            f"{where} has {len(vw.indptr) - 1} pixel rows for a {vw.width}x{vw.height} image"
        )
    if check:
        _check_view(vw, n_gaussians, where)
    return vw


def _read_into(ds: h5py.Dataset, out: np.ndarray | None) -> np.ndarray:
    if out is None:
        return ds[()]
    if ds.shape != out.shape:
        raise GoiError(f"{ds.file.filename}: '{ds.name}' changed while being read")
    ds.read_direct(out)
    return out


def _check_view(vw: ViewWeights, n_gaussians: int, where: str) -> None:
    """The CSR a damaged or forged file could break: every row inside the arrays, every column
    a Gaussian, every weight a blending weight (alpha T lies in [0, 1])."""
    ptr = vw.indptr
    if ptr[0] != 0 or ptr[-1] != len(vw.indices) or (np.diff(ptr) < 0).any():
        raise GoiError(f"{where}: its row pointers do not index its {len(vw.indices)} entries")
    if len(vw.weights) != len(vw.indices):
        raise GoiError(f"{where}: {len(vw.indices)} Gaussian ids but {len(vw.weights)} weights")
    if len(vw.indices) and (vw.indices.min() < 0 or vw.indices.max() >= n_gaussians):
        raise GoiError(f"{where}: a Gaussian id is outside 0..{n_gaussians - 1}")
    w = vw.weights
    if not (np.isfinite(w).all() and (w >= 0).all() and (w <= 1.0001).all()):
        raise GoiError(f"{where}: holds weights outside [0, 1] or NaN/inf")


def build_cache(
    rast: Rasterizer,
    cameras: list[Camera],
    k: int,
    ply_sha256: str,
    cameras_sha256: str,
    sizes: dict[str, tuple[int, int]] | None = None,
    report: Report = SILENT,
) -> BlendCache:
    order = morton_order(rast.means)
    position = np.empty_like(order)
    position[order] = np.arange(len(order), dtype=np.int32)
    views = {
        cam.name: view_weights(rast, cam, position, k, (sizes or {}).get(cam.name))
        for cam in report.progress(cameras, "blend cache", length=len(cameras))
    }
    return BlendCache(order, views, k, ply_sha256, cameras_sha256)


def cache_target(
    path: str | os.PathLike[str],
    scene: Scene,
    cameras: list[Camera],
    k: int,
    sizes: dict[str, tuple[int, int]],
    force: bool,
) -> bool:
    """Check the cache path before any work: True when it already holds this very cache (to
    be reused); False when it is free, or holds something else and `force` allows replacing
    it. A directory, or another file without --force, is refused."""
    p = Path(path)
    if p.is_dir():
        raise GoiError(f"--cache: {p} is a directory; give the path of the blend cache file")
    if not (p.exists() or p.is_symlink()):
        check_writable(p, force, "--cache")
        return False
    regular_file(p, "blend cache file (--cache)")
    want = cache_sizes(cameras, sizes)
    if _matches(p, scene.ply_digest(), scene.cameras_digest(), k, want, scene.gaussians.count):
        return True
    if not force:
        raise GoiError(
            f"--cache: {p} exists and is not the blend cache of these views, PLY and options; "
            "pass --force to replace it, or give another --cache path"
        )
    check_writable(p, force, "--cache")
    return False


def cache_sizes(
    cameras: list[Camera], sizes: dict[str, tuple[int, int]]
) -> dict[str, tuple[int, int]]:
    """Each view's (width, height) in the cache: its feature grid when pooled, else its image."""
    return {c.name: sizes.get(c.name, (c.width, c.height)) for c in cameras}


def cache_identity(scene: Scene, k: int, want: dict[str, tuple[int, int]]) -> dict[str, str | int]:
    """What a cache was built from: a cache (or a cut-off build) with other values is not it."""
    return {
        "ply_sha256": scene.ply_digest(),
        "cameras_sha256": scene.cameras_digest(),
        "top_k": k,
        "sizes": json.dumps(sorted(want.items())),
    }


def build_cache_file(
    path: Path,
    scene: Scene,
    cameras: list[Camera],
    k: int,
    want: dict[str, tuple[int, int]],
    report: Report = SILENT,
) -> None:
    """Rasterise the views one at a time into `<path>.partial` (memory: one view's weights),
    then rename it to `path`. A cut-off build resumes there: the views it finished are kept."""
    identity = cache_identity(scene, k, want)
    partial = path.with_name(path.name + ".partial")
    t = time.perf_counter()
    rast = Rasterizer.from_gaussians(scene.gaussians)
    order = morton_order(rast.means)
    position = np.empty_like(order)
    position[order] = np.arange(len(order), dtype=np.int32)
    mode = "w"
    if partial_exists(partial, "--cache"):
        problem = _partial_problem(partial, identity, order, want)
        if problem is None:
            mode = "r+"
        else:
            report.log(f"{partial}: {problem}; building the cache again")
    if mode == "w":
        create_partial(partial, "--cache")
    inputs = {"ply": scene.ply_digest(), "cameras": scene.cameras_digest()}
    with kept_on_interrupt(partial, created=mode == "w"):
        with h5py.File(partial, mode, track_order=True) as f:
            if mode == "w":
                f.attrs.update(n_gaussians=len(order), **identity)
                put(f, "order", order)
                f.create_group("views", track_order=True)
            views = f["views"]
            for name in list(views):
                if "weights" not in views[name]:
                    del views[name]  # cut off while being written
            todo = [c for c in cameras if c.name not in views]
            if len(todo) < len(cameras):
                report.log(f"resuming {partial}: {len(cameras) - len(todo)} views done")
            for cam in report.progress(todo, "blend cache", length=len(todo)):
                write_view(views, cam.name, view_weights(rast, cam, position, k, want[cam.name]))
                f.flush()
            stamp(f, SCHEMA, inputs)  # once, at the end: equal inputs give equal bytes
    finish_partial(partial, path)
    report.log(
        f"blend cache built in {time.perf_counter() - t:.1f} s ({len(cameras)} views, "
        f"{size_text(path.stat().st_size)} at {path})"
    )


def _partial_problem(
    partial: Path,
    identity: dict[str, str | int],
    order: np.ndarray,
    want: dict[str, tuple[int, int]],
) -> str | None:
    """Why a cut-off build in `partial` is not this cache's (None when it is): its recorded
    identity is not believed alone; the Gaussian count, the column order, and each finished
    view's grid and weights are checked against the real inputs."""
    try:
        with read_h5(partial) as f:
            a = f.attrs
            if not all(a.get(key) == value for key, value in identity.items()):
                return "made from other inputs or options"
            if int(a.get("n_gaussians", -1)) != len(order) or not np.array_equal(
                f["order"][()], order
            ):
                return f"not made for these {len(order)} Gaussians"
            for name, grp in f["views"].items():
                if name not in want:
                    return f"holds view '{name}', which is not one of the training views"
                if "weights" not in grp:
                    continue  # cut off while being written: redone
                vw = read_view(grp, len(order), f"{partial}: view '{name}'")
                if (vw.width, vw.height) != want[name]:
                    return f"view '{name}' has a {vw.width}x{vw.height} grid, not {want[name]}"
    except GoiError as e:
        return str(e)
    except (OSError, KeyError, ValueError, TypeError, RuntimeError) as e:
        return f"not a readable cache ({str(e)[:120]})"
    return None


def write_view(views: h5py.Group, name: str, vw: ViewWeights) -> None:
    grp = views.create_group(name)
    grp.attrs.update(
        width=vw.width, height=vw.height, mass_kept=vw.mass_kept, entries_total=vw.entries_total
    )
    put(grp, "indptr", vw.indptr)
    put(grp, "indices", vw.indices)
    put(grp, "weights", vw.weights)  # last: its presence marks the view complete


def ensure_cache(
    path: str | os.PathLike[str],
    scene: Scene,
    cameras: list[Camera],
    k: int = 0,
    sizes: dict[str, tuple[int, int]] | None = None,
    report: Report = SILENT,
    force: bool = False,
) -> Path:
    """`path` holding the cache of these views: reused when it was built for the same PLY,
    cameras, top-K and view sizes, otherwise built there (replacing another file only with
    `force`). `sizes` gives a view's (width, height) when it is pooled below image size."""
    sizes = sizes or {}
    p = Path(path)
    if not cache_target(p, scene, cameras, k, sizes, force):
        build_cache_file(p, scene, cameras, k, cache_sizes(cameras, sizes), report)
    return p


def cache_nbytes(path: str | os.PathLike[str], views: list[str]) -> dict[str, int]:
    """Each view's weights in memory (bytes), from the dataset shapes alone."""
    with read_h5(path) as f:
        return {
            v: sum(f["views"][v][d].size * f["views"][v][d].dtype.itemsize for d in _ARRAYS)
            for v in views
        }


_ARRAYS = ("indptr", "indices", "weights")


def _matches(
    p: Path, ply_sha: str, cam_sha: str, k: int, want: dict[str, tuple[int, int]], n: int
) -> bool:
    try:
        with read_h5(p) as f:
            a, views = f.attrs, f.get("views", {})
            return (
                a.get("schema") == SCHEMA
                and a.get("ply_sha256") == ply_sha
                and a.get("cameras_sha256") == cam_sha
                and int(a.get("top_k", -1)) == k
                and int(a.get("n_gaussians", -1)) == n
                and all(
                    v in views
                    and (int(views[v].attrs["width"]), int(views[v].attrs["height"])) == wh
                    for v, wh in want.items()
                )
            )
    except (OSError, KeyError, ValueError, TypeError, RuntimeError):
        return False

"""The blend cache split by columns for a distributed fit: rank r's shard holds, for every
training view, only the weights of its own Gaussians (a contiguous range of the Morton-ordered
columns, so a rank's Gaussians are also close in space).

Rendering is linear in the features, so a pixel's feature is the sum over the shards of the
pixel's row restricted to each shard's columns. The shards are built in parallel by view: rank
r rasterises the views i with i % world == r and splits each view's matrix by column range
into a parts file; after a barrier each rank gathers its columns of every view from the parts
files into its shard, so that it reads only its own columns. Files are shared through the
file system the ranks see (one node, or a cluster's shared file system).
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from stages.core.artifacts import put, write_h5
from stages.core.errors import GoiError
from stages.core.hdf5 import read_h5
from stages.core.report import SILENT, Report
from stages.render.rasterizer import Rasterizer
from stages.scene.cameras import Camera
from stages.scene.scene import Scene
from stages.semantics.blend_cache import ViewWeights, cache_identity, view_weights, write_view
from stages.semantics.distributed import Ranks
from stages.semantics.weights import morton_order

SCHEMA = "goi.blend_cache_shard"

_SHARD = re.compile(r"\.shard-(\d+)-of-(\d+)$")


def column_range(n_gaussians: int, world: int, rank: int) -> tuple[int, int]:
    """Rank `rank`'s columns [lo, hi) of `n_gaussians`, in nearly equal contiguous blocks."""
    return n_gaussians * rank // world, n_gaussians * (rank + 1) // world


def shard_path(cache: Path, rank: int, world: int) -> Path:
    return cache.with_name(f"{cache.stem}.shard-{rank}-of-{world}{cache.suffix}")


def _parts_path(cache: Path, rank: int, world: int) -> Path:
    return cache.with_name(f"{cache.name}.parts-{rank}-of-{world}")


def shard_worlds(cache: Path) -> set[int]:
    """The world sizes of the shard files found beside `cache`."""
    worlds = set()
    for p in cache.parent.glob(f"{cache.stem}.shard-*-of-*{cache.suffix}"):
        m = _SHARD.search(p.name[: len(p.name) - len(cache.suffix)] if cache.suffix else p.name)
        if m:
            worlds.add(int(m.group(2)))
    return worlds


def split_columns(vw: ViewWeights, bounds: np.ndarray) -> list[ViewWeights]:
    """A view's CSR [P, G] cut into len(bounds) - 1 column blocks [bounds[s], bounds[s+1]),
    each with its columns counted from the block's start; entries keep their order within a
    row (front to back), so each block's row sum adds in the single matrix's order."""
    n_rows = len(vw.indptr) - 1
    row_of = np.repeat(np.arange(n_rows, dtype=np.int64), np.diff(vw.indptr))  # [nnz]
    block = np.searchsorted(bounds, vw.indices, side="right") - 1  # [nnz]
    out = []
    for s in range(len(bounds) - 1):
        keep = block == s
        indptr = np.zeros(n_rows + 1, np.int64)
        np.cumsum(np.bincount(row_of[keep], minlength=n_rows), out=indptr[1:])
        out.append(
            ViewWeights(
                vw.width,
                vw.height,
                indptr,
                (vw.indices[keep] - bounds[s]).astype(np.int32),
                vw.weights[keep],
                vw.mass_kept,
                vw.entries_total,
            )
        )
    return out


@dataclass
class ShardPlan:
    """Where this rank's shard lives, and what it must hold."""

    path: Path
    rank: int
    world: int
    lo: int
    hi: int
    n_gaussians: int
    identity: dict[str, str | int]

    def attrs(self) -> dict[str, str | int]:
        return {
            **self.identity,
            "n_gaussians": self.hi - self.lo,
            "n_gaussians_total": self.n_gaussians,
            "column_lo": self.lo,
            "column_hi": self.hi,
            "rank": self.rank,
            "world_size": self.world,
        }


def plan_shard(
    cache: Path,
    scene: Scene,
    n: int,
    k: int,
    want: dict[str, tuple[int, int]],
    ranks: Ranks,
    force: bool,
) -> tuple[ShardPlan, bool]:
    """This rank's shard and whether it can be reused as it is. Shards built for another
    world size are refused unless `force` (then new ones are built beside them). `n`: the
    scene's Gaussians (from the PLY's header: the Gaussians themselves are not read here)."""
    lo, hi = column_range(n, ranks.world, ranks.rank)
    plan = ShardPlan(
        shard_path(cache, ranks.rank, ranks.world),
        ranks.rank,
        ranks.world,
        lo,
        hi,
        n,
        cache_identity(scene, k, want),
    )
    others = sorted(shard_worlds(cache) - {ranks.world})
    if others and not shard_worlds(cache) & {ranks.world} and not force:
        raise GoiError(
            f"--cache: the blend cache shards beside {cache} "
            f"({shard_path(cache, 0, others[0]).name}, ...) were built for {others[0]} "
            f"ranks, this run has {ranks.world}; start torchrun with {others[0]} processes in "
            f"all, or pass --force to build shards for {ranks.world} beside them"
        )
    p = plan.path
    if p.is_dir():
        raise GoiError(f"--cache: {p} is a directory; the blend cache shard is a file there")
    if not p.exists():
        return plan, False
    if _matches(p, plan.attrs(), list(want)):
        return plan, True
    if not force:
        raise GoiError(
            f"--cache: {p} exists and is not this rank's shard of the blend cache of these "
            "views, PLY and options; pass --force to replace it, or give another --cache path"
        )
    return plan, False


def _matches(p: Path, attrs: dict[str, str | int], views: list[str]) -> bool:
    try:
        with read_h5(p) as f:
            a = f.attrs
            return (
                a.get("schema") == SCHEMA
                and all(a.get(key) == value for key, value in attrs.items())
                and all(v in f["views"] and "weights" in f["views"][v] for v in views)
            )
    except (OSError, KeyError, ValueError, TypeError, RuntimeError):
        return False


def build_shards(
    plan: ShardPlan,
    scene: Scene,
    cameras: list[Camera],
    k: int,
    want: dict[str, tuple[int, int]],
    ranks: Ranks,
    cache: Path,
    report: Report = SILENT,
) -> None:
    """Every rank's shard, built together: this rank rasterises its share of the views into
    its parts file, then (after every rank has) copies its columns of every view from the
    parts files into its shard, written atomically. Memory: one view's weights."""
    rast = Rasterizer.from_gaussians(scene.gaussians)
    order = morton_order(rast.means)  # [G] the single cache's column order
    position = np.empty_like(order)
    position[order] = np.arange(len(order), dtype=np.int32)
    bounds = np.array(
        [column_range(plan.n_gaussians, ranks.world, r)[0] for r in range(ranks.world)]
        + [plan.n_gaussians],
        np.int64,
    )
    mine = [c for i, c in enumerate(cameras) if i % ranks.world == ranks.rank]
    parts = _parts_path(cache, ranks.rank, ranks.world)
    tmp = parts.with_name(parts.name + ".tmp")
    try:
        with h5py.File(tmp, "w") as f:
            for cam in report.progress(mine, "blend cache shards", length=len(mine)):
                vw = view_weights(rast, cam, position, k, want[cam.name])
                grp = f.create_group(cam.name)
                for s, piece in enumerate(split_columns(vw, bounds)):
                    write_view(grp, str(s), piece)
        os.replace(tmp, parts)
        del rast, position
        ranks.barrier("the blend cache's parts")
        inputs = {"ply": scene.ply_digest(), "cameras": scene.cameras_digest()}
        with write_h5(plan.path, SCHEMA, inputs, force=True) as out:
            out.attrs.update(plan.attrs())
            put(out, "order", order[plan.lo : plan.hi])
            views = out.create_group("views", track_order=True)
            for i, cam in enumerate(cameras):
                owner = _parts_path(cache, i % ranks.world, ranks.world)
                with read_h5(owner) as f:
                    src = f[cam.name][str(ranks.rank)]
                    views.copy(src, cam.name)
        ranks.barrier("the blend cache's shards")
    finally:
        tmp.unlink(missing_ok=True)
        parts.unlink(missing_ok=True)
    report.log(f"blend cache shard {plan.path} built ({len(mine)} views rasterised here)")


def shard_order(plan: ShardPlan) -> np.ndarray:
    """[hi - lo] int32: the PLY ids of the shard's columns, checked against the plan."""
    with read_h5(plan.path) as f:
        order = f["order"][()]
    if order.shape != (plan.hi - plan.lo,) or (
        len(order) and (order.min() < 0 or order.max() >= plan.n_gaussians)
    ):
        raise GoiError(f"{plan.path}: 'order' does not hold this shard's {plan.hi - plan.lo} ids")
    return order.astype(np.int32)

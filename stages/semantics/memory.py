"""How much memory a field fit needs, estimated from shapes before any work (`--max-memory-gib`).

The estimate counts the large arrays a fit holds, not Python's overhead; the scale benchmark
measures the real peak beside it (docs/performance.md).
"""

from __future__ import annotations

import os
from pathlib import Path

from stages.core.errors import GoiError
from stages.scene.cameras import Camera
from stages.scene.scene import Scene
from stages.semantics.feature_renderer import T_BLOCKS
from stages.semantics.field_params import FieldParams

GIB = 2**30

#: Blend-weight entries per pixel of a full-resolution view while its cache row is built
#: (measured 20-45 on the synthetic and dev rooms; the margin covers denser scenes), each an
#: int64 row pointer share, an int32 id and a float32 weight, twice over while it is pooled.
_ENTRIES_PER_PIXEL = 64
_ENTRY_BYTES = 2 * (4 + 4) + 8


def machine_memory() -> int:
    """Physical memory, or the container's limit when lower (bytes)."""
    total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if limit.isdigit():
            total = min(total, int(limit))
    except OSError:
        pass
    return int(total)


def memory_budget(max_memory_gib: float) -> int:
    """The budget in bytes: the option, or three quarters of the machine when it is 0."""
    if max_memory_gib == 0:
        return machine_memory() * 3 // 4
    if max_memory_gib * GIB > machine_memory():
        raise GoiError(
            f"--max-memory-gib: {max_memory_gib:g} GiB is more than this machine has "
            f"({machine_memory() / GIB:.1f} GiB)"
        )
    return int(max_memory_gib * GIB)


def working_set(
    n_gaussians: int,
    scene: Scene,
    cameras: list[Camera],
    sizes: dict[str, tuple[int, int]],
    dim: int,
    entries: int,
    p: FieldParams,
) -> int:
    """Bytes a fit holds besides the blend cache's weights."""
    parts = _parts(scene, cameras, sizes, dim, entries, p)
    return sum(parts.values()) + _optimiser(n_gaussians, p)


def rank_working_set(
    n_gaussians: int,
    n_columns: int,
    scene: Scene,
    cameras: list[Camera],
    sizes: dict[str, tuple[int, int]],
    dim: int,
    entries: int,
    p: FieldParams,
    leader: bool,
    building: bool,
    world: int,
) -> int:
    """Bytes one rank of a distributed fit holds besides its shard of the blend cache: the
    feature maps (every rank reads them all), then the larger of two phases. While the
    shards are `building`, the PLY and one view's rasterisation (rasterising a view needs
    every Gaussian; the rank lets them go before fitting; with shards already built the PLY
    is never read). Then its `n_columns` Gaussians' optimiser state, the step's batch and,
    on the leader, the field's [G, S] features in PLY order and one other rank's share of
    them at a time as it receives them."""
    parts = _parts(scene, cameras, sizes, dim, entries, p, building)
    build = parts["gaussians"] + parts["raster"] if building else 0
    fit = _optimiser(n_columns, p) + parts["batch"]
    if leader:
        fit += n_gaussians * p.sem_dim * 4 + -(-n_gaussians // world) * (p.sem_dim + 1) * 4
    return parts["features"] + max(build, fit)


def _optimiser(n_gaussians: int, p: FieldParams) -> int:
    # features, gradient, Adam's two moments, the transpose's block buffers, and a copy of the
    # features in PLY order when the field is saved
    return n_gaussians * p.sem_dim * 4 * (5 + T_BLOCKS)


def _parts(
    scene: Scene,
    cameras: list[Camera],
    sizes: dict[str, tuple[int, int]],
    dim: int,
    entries: int,
    p: FieldParams,
    gaussians: bool = True,
) -> dict[str, int]:
    cells = {c.name: sizes.get(c.name, (c.width, c.height)) for c in cameras}
    per_step = max(w * h for w, h in cells.values()) * p.views_per_step
    if p.cells_per_view:
        per_step = min(per_step, p.cells_per_view * p.views_per_step)
    return {
        "features": sum(w * h for w, h in cells.values()) * dim * 2,  # float16
        # the PLY, its arrays, the rasteriser's (counted only when they are read)
        "gaussians": scene.gaussians.vertex.nbytes * 3 if gaussians else 0,
        "batch": per_step * (entries * 4 * 4 + dim * (2 + 4 + 4)),
        "raster": max(c.width * c.height for c in cameras) * _ENTRIES_PER_PIXEL * _ENTRY_BYTES,
    }


def cache_floor(sizes: dict[str, tuple[int, int]], views_per_step: int) -> int:
    """The least a streamed step holds of the blend cache, known before it is built: the row
    pointers [cells + 1] int64 of its largest views (their weights come on top)."""
    cells = sorted((w * h + 1) * 8 for w, h in sizes.values())
    return sum(cells[-views_per_step:])

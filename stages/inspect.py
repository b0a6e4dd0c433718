"""`goi inspect`: what a PLY or HDF5 artifact holds, and whether it is valid."""

from __future__ import annotations

import json
import os
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import h5py
import numpy as np

from schemas import validate_file
from stages.core.errors import GoiError
from stages.core.files import regular_file
from stages.core.hdf5 import read_h5
from stages.scene.gaussians import load_ply

if TYPE_CHECKING:
    from stages.query.ply_labels import Labels


def inspect_ply(path: Path) -> tuple[list[str], list[str]]:
    """Lines describing the PLY and the problems found (a problem that stops loading raises)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        g = load_ply(path)
    problems = [str(w.message) for w in caught]
    lo, hi = g.means.min(0), g.means.max(0)
    lines = [
        f"{path}: INRIA 3DGS PLY",
        f"  gaussians     {g.count}",
        f"  sh degree     {g.sh_degree} ({g.sh.shape[1]} coefficients per channel)",
        f"  normals       {'yes' if 'nx' in (g.vertex.dtype.names or ()) else 'no'}",
        f"  extra fields  {', '.join(g.extra_fields) or 'none'}",
        f"  bounds        x [{lo[0]:.3f}, {hi[0]:.3f}]  y [{lo[1]:.3f}, {hi[1]:.3f}]  "
        f"z [{lo[2]:.3f}, {hi[2]:.3f}]",
        f"  opacity       median {np.median(g.opacities):.3f}, "
        f"{int((g.opacities < 1 / 255).sum())} below 1/255",
        f"  scale         median {np.median(g.scales):.4g}, max {g.scales.max():.4g}",
    ]
    from stages.query.ply_labels import labels_of

    try:
        labels = labels_of(g)
    except GoiError as e:
        return [*lines, "  labels        (unreadable)"], [*problems, str(e)]
    if labels is not None:
        lines += _describe_labels(labels)
    return lines, problems


def _describe_labels(labels: Labels) -> list[str]:
    """The named selections of a labels PLY: ids, names, counts and scores."""
    counts = labels.counts()
    lines = [
        f"  labels        {len(labels.names)} named selections (goi.labels_ply "
        f"{labels.version}; overlaps: {labels.overlap or '?'})",
        f"  label 0       (none): {counts[0]} Gaussians",
    ]
    for i, name in enumerate(labels.names, start=1):
        score = labels.score[labels.label == i]
        line = f"  label {i:<8d}{json.dumps(name)}: {counts[i]} Gaussians"
        if score.size:
            line += f", score median {np.median(score):.3f}, min {score.min():.3f}"
        lines.append(line)
    return lines


def _describe_h5(f: h5py.File) -> list[str]:
    lines: list[str] = []
    for key in ("schema", "schema_version", "goi_version", "created", "command"):
        if key in f.attrs:
            lines.append(f"  {key + ' ':14s}{f.attrs[key]}")  # schema_version fills the column
    if "inputs" in f.attrs:
        try:
            for role, digest in json.loads(f.attrs["inputs"]).items():
                lines.append(f"  input         {role}: sha256 {str(digest)[:16]}...")
        except (ValueError, AttributeError):
            pass
    skip = {"schema", "schema_version", "goi_version", "created", "command", "inputs"}
    for key, value in f.attrs.items():
        if key not in skip:
            lines.append(f"  attr          {key} = {_short(value)}")
    datasets: list[str] = []
    groups: dict[str, int] = {}

    def visit(name: str, obj: object) -> None:
        parts = name.split("/")
        if len(parts) > 2 and len(datasets) > 40:  # summarise wide per-view trees
            groups[parts[0]] = groups.get(parts[0], 0) + 1
            return
        if isinstance(obj, h5py.Dataset):
            datasets.append(f"  dataset       {name} {obj.dtype} {list(obj.shape)}")

    f.visititems(visit)
    lines += datasets
    lines += [f"  ...           {n} more datasets under {g}/" for g, n in groups.items()]
    return lines


def _short(value: object) -> str:
    text = str(value)
    return text if len(text) < 80 else text[:77] + "..."


def _semantic_problems(path: Path, schema: str) -> list[str]:
    """What the artifact's own reader refuses beyond its schema (values, shapes, cross
    references): the very checks every command runs before using it."""
    from stages.query.hyperplanes import read_hyperplanes
    from stages.query.res_index import check_values, load_res_index
    from stages.query.selection import load_selection
    from stages.semantics.blend_cache import BlendCache
    from stages.semantics.codebook import load_codebook
    from stages.semantics.features import load_features
    from stages.semantics.field import load_field

    readers: dict[str, Callable[[Path], object]] = {
        "goi.features": load_features,
        "goi.codebook": load_codebook,
        "goi.field": load_field,
        "goi.blend_cache": BlendCache.load,
        "goi.hyperplanes": read_hyperplanes,
        "goi.selection": load_selection,
        # no bundle here: every view's arrays against the index's own spec, and finite
        "goi.res_index": lambda p: check_values(idx := load_res_index(p), idx.spec),
    }
    reader = readers.get(schema)
    if reader is None:
        return []
    try:
        reader(path)
    except GoiError as e:
        return [str(e)]
    return []


def inspect_file(path: str | os.PathLike[str]) -> tuple[list[str], list[str]]:
    p = regular_file(path, "PLY or HDF5 file")
    with open(p, "rb") as fh:
        magic = fh.read(8)
    if magic.startswith(b"ply"):
        return inspect_ply(p)
    if magic == b"\x89HDF\r\n\x1a\n":
        schema, problems = validate_file(p)
        lines = [f"{p}: HDF5 artifact {schema or '(no goi schema)'}"]
        try:
            with read_h5(p) as f:
                lines += _describe_h5(f)
        except (OSError, KeyError, ValueError, RuntimeError, TypeError) as e:
            return lines, problems or [f"not a readable HDF5 file ({str(e)[:200]})"]
        if not problems and schema:
            problems = _semantic_problems(p, schema)
        return lines, problems
    raise GoiError(f"{p}: neither a PLY nor an HDF5 file")

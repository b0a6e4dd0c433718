"""`goi export-ply`: the paper's edits of the Gaussians of interest, as an INRIA PLY.

The subset alone, the scene without it (deletion), with it recoloured (highlight) or moved
(translate), optionally with the field's per-Gaussian features as sem_* properties. Named
selections as labels of the whole scene: `stages.query.ply_labels`.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stages.core.artifacts import check_writable
from stages.core.errors import GoiError
from stages.core.files import refuse_inputs
from stages.query.ply_labels import LABEL, goi_comments
from stages.query.selection import Selection
from stages.scene.gaussians import SH_C0, Gaussians, save_ply
from stages.semantics.field import Field

_NAMED = {
    "red": (1.0, 0.0, 0.0),
    "green": (0.0, 1.0, 0.0),
    "blue": (0.0, 0.0, 1.0),
    "yellow": (1.0, 1.0, 0.0),
    "magenta": (1.0, 0.0, 1.0),
    "cyan": (0.0, 1.0, 1.0),
    "white": (1.0, 1.0, 1.0),
    "black": (0.0, 0.0, 0.0),
    "orange": (1.0, 0.5, 0.0),
}


def parse_color(text: str, option: str = "--highlight") -> np.ndarray:
    """'red', '#ff8800' or 'r,g,b' with 0..1 or 0..255 numbers -> [3] float 0..1."""
    t = text.strip().lower()
    if t in _NAMED:
        return np.asarray(_NAMED[t], np.float32)
    if re.fullmatch(r"#[0-9a-f]{6}", t):
        return np.asarray([int(t[i : i + 2], 16) / 255 for i in (1, 3, 5)], np.float32)
    v = _three_numbers(t)
    if v is not None and v.min() >= 0 and v.max() <= 255:
        return np.asarray(v / 255 if v.max() > 1 else v, np.float32)
    raise GoiError(
        f"{option}: {text!r} is not a colour (a name like red, #rrggbb, or r,g,b of 0..1 or 0..255)"
    )


def _three_numbers(text: str) -> np.ndarray | None:
    """'a,b,c' -> [3] finite float64, else None."""
    try:
        v = np.asarray([float(x) for x in text.split(",")], np.float64)
    except ValueError:
        return None
    return v if v.shape == (3,) and np.all(np.isfinite(v)) else None


def parse_vector(text: str, option: str) -> np.ndarray:
    v = _three_numbers(text)
    if v is None:
        raise GoiError(f"{option}: {text!r} is not three numbers DX,DY,DZ")
    return v


@dataclass
class PlyEditParams:
    invert: bool = False
    """Write the scene without the selected Gaussians (deletion)."""
    highlight: str | None = None
    """Write the whole scene with the selected Gaussians recoloured: a name, #rrggbb or r,g,b."""
    translate: str | None = None
    """Write the whole scene with the selected Gaussians moved by DX,DY,DZ (scene units)."""
    semantics: bool = False
    """Add the field's per-Gaussian features as sem_0.. properties (needs --field)."""


@dataclass
class PlyExportRun:
    out: Path
    """PLY to write (INRIA layout, binary little-endian)."""
    force: bool = False
    """Overwrite an existing PLY."""


def export_ply(
    g: Gaussians,
    sel: Selection,
    ply_sha: str,
    o: PlyEditParams,
    run: PlyExportRun,
    field: Field | None = None,
) -> tuple[Path, int]:
    """Write the edited PLY; returns its path and its number of Gaussians."""
    check_writable(run.out, run.force, "--out")
    refuse_inputs({"--out": run.out}, [g.path])
    if sel.ply_sha256 != ply_sha:
        raise GoiError(
            f"--selection: it was made for another PLY (sha256 {sel.ply_sha256[:12]}...); "
            "select again on this scene"
        )
    if sel.selected.size != len(g.vertex):
        raise GoiError(f"--selection: {sel.selected.size} Gaussians, the PLY has {len(g.vertex)}")
    edits = [o.invert, o.highlight is not None, o.translate is not None]
    if sum(edits) > 1:
        raise GoiError("give at most one of --invert, --highlight and --translate")
    if o.highlight is not None:
        parse_color(o.highlight)  # a bad colour is refused before anything is computed
    v = g.vertex.copy()
    s = sel.selected
    if o.semantics:
        if field is None:
            raise GoiError("--semantics needs --field FILE")
        from numpy.lib import recfunctions as rfn

        names = [f"sem_{i}" for i in range(field.features.shape[1])]
        clash = [n for n in names if n in (v.dtype.names or ())]
        if clash:
            v = rfn.drop_fields(v, clash, usemask=False)
        cols = [field.features[:, i].astype(np.float32) for i in range(len(names))]
        v = rfn.append_fields(v, names, cols, usemask=False)
    if o.highlight is not None:
        rgb = parse_color(o.highlight)
        for i in range(3):
            v[f"f_dc_{i}"][s] = (rgb[i] - 0.5) / SH_C0
        for name in v.dtype.names or ():
            if name.startswith("f_rest_"):
                v[name][s] = 0  # view-independent colour
    elif o.translate is not None:
        d = parse_vector(o.translate, "--translate")
        for i, axis in enumerate("xyz"):
            moved = v[axis][s].astype(np.float64) + d[i]
            with np.errstate(over="ignore"):
                stored = moved.astype(v[axis].dtype)
            if not np.isfinite(stored).all():
                raise GoiError(
                    f"--translate: {o.translate!r} moves Gaussians beyond what the PLY's "
                    f"{v[axis].dtype} '{axis}' can hold"
                )
            v[axis][s] = stored
    else:
        keep = ~s if o.invert else s
        if not keep.any():
            raise GoiError(
                f"the selection of {sel.prompt[:60]!r} leaves no Gaussian to write"
                + ("" if o.invert else "; nothing was selected")
            )
        v = v[keep]
    # a labelled scene's labels stay named in its edits (every edit keeps the properties)
    carried = goi_comments(g) if LABEL in (v.dtype.names or ()) else []
    save_ply(run.out, v, run.force, carried)
    return Path(run.out), len(v)

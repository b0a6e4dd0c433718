"""INRIA 3DGS PLY: read (any SH degree, with or without normals, extra fields kept) and write.

The PLY stores pre-activation values: opacity is a logit, scales are logs, rotations are
unnormalised quaternions (w, x, y, z). `Gaussians` keeps the raw vertex table for lossless
export next to the activated arrays the rasteriser uses.
"""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import plyfile

from stages.core.artifacts import atomic_path
from stages.core.errors import GoiError, warn
from stages.core.files import regular_file

SH_C0 = 0.28209479177387814
REQUIRED = (
    "x",
    "y",
    "z",
    "f_dc_0",
    "f_dc_1",
    "f_dc_2",
    "opacity",
    "scale_0",
    "scale_1",
    "scale_2",
    "rot_0",
    "rot_1",
    "rot_2",
    "rot_3",
)
#: f_rest_* counts of SH degrees 0..3: 3 * ((d + 1)^2 - 1)
REST_COUNTS = {0: 0, 9: 1, 24: 2, 45: 3}
#: A header may not declare more vertices than this (about 60 GB of float32 at 59 fields).
MAX_VERTICES = 250_000_000
_PLY_SIZES = {
    "char": 1,
    "uchar": 1,
    "int8": 1,
    "uint8": 1,
    "short": 2,
    "ushort": 2,
    "int16": 2,
    "uint16": 2,
    "int": 4,
    "uint": 4,
    "int32": 4,
    "uint32": 4,
    "float": 4,
    "float32": 4,
    "double": 8,
    "float64": 8,
}


def vertex_fields(
    sh_degree: int = 0, normals: bool = True, extra: tuple[str, ...] = ()
) -> list[str]:
    """The INRIA vertex fields, in INRIA's order, for an SH degree."""
    rest = [f"f_rest_{i}" for i in range(3 * ((sh_degree + 1) ** 2 - 1))]
    normal = ["nx", "ny", "nz"] if normals else []
    return [*REQUIRED[:3], *normal, *REQUIRED[3:6], *rest, *REQUIRED[6:], *extra]


@dataclass
class Gaussians:
    path: Path
    vertex: np.ndarray  # structured [N], every field of the file, native byte order
    means: np.ndarray  # [N, 3] float32
    quats: np.ndarray  # [N, 4] float32, unit (w, x, y, z)
    scales: np.ndarray  # [N, 3] float32, standard deviations (exp of the stored logs)
    opacities: np.ndarray  # [N] float32 in (0, 1)
    sh: np.ndarray  # [N, K, 3] float32, K = (degree + 1)^2, coefficient-major
    sh_degree: int
    valid: np.ndarray = field(default_factory=lambda: np.ones(0, bool))  # [N] renderable
    comments: list[str] = field(default_factory=list)  # the header's comment lines, in order

    @property
    def count(self) -> int:
        return int(self.means.shape[0])

    def colors_dc(self) -> np.ndarray:
        """[N, 3] base colour, as a viewer shows it without view dependence."""
        return np.clip(0.5 + SH_C0 * self.sh[:, 0, :], 0.0, 1.0)

    @property
    def extra_fields(self) -> list[str]:
        known = set(REQUIRED) | {"nx", "ny", "nz"} | {f"f_rest_{i}" for i in range(45)}
        return [n for n in (self.vertex.dtype.names or ()) if n not in known]


def ply_count(path: str | os.PathLike[str]) -> int:
    """The number of Gaussians a PLY declares, from its header alone (checked as `load_ply`
    checks it): for a stage that needs the count but not the Gaussians."""
    p = regular_file(path, "PLY file")
    return _check_header(p)


def _check_header(path: Path) -> int:
    """Refuse truncated files and absurd sizes before plyfile allocates anything; returns the
    declared vertex count."""
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(1 << 16)
    if not head.startswith(b"ply"):
        raise GoiError(f"{path}: not a PLY file (it does not start with 'ply')")
    end = head.find(b"end_header")
    if end < 0:
        raise GoiError(f"{path}: PLY header has no 'end_header' in its first 64 KiB")
    body_start = head.index(b"\n", end) + 1 if b"\n" in head[end:] else len(head)
    for i, raw in enumerate(head[:end].splitlines()):
        if not raw.isascii():
            shown = raw.decode("ascii", "backslashreplace").strip()[:120]
            raise GoiError(f"{path}: PLY header line {i + 1} is not ASCII: {shown!r}")
    lines = head[:end].decode("ascii", "replace").splitlines()
    fmt = next(((ln.split() + ["", ""])[1] for ln in lines if ln.startswith("format ")), "")
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise GoiError(f"{path}: unknown PLY format {fmt!r}")
    # Per element: its name, declared row count and the fewest bytes a row can take (exact for
    # binary rows without lists; a list takes at least its count; an ASCII value at least a
    # character and a separator). No element may need more bytes than the file holds.
    elements: list[tuple[str, int, int]] = []
    for ln in lines:
        tok = ln.split()
        if not tok:
            continue
        if tok[0] == "element" and len(tok) == 3:
            if not re.fullmatch(r"\d{1,15}", tok[2]):
                raise GoiError(f"{path}: bad element count {tok[2]!r} for '{tok[1]}'")
            elements.append((tok[1], int(tok[2]), 0))
        elif tok[0] == "property" and elements:
            if len(tok) < 3 or (tok[1] == "list" and len(tok) < 5):
                raise GoiError(f"{path}: malformed PLY header line {ln.strip()!r}")
            kind = tok[2] if tok[1] == "list" else tok[1]  # a list row starts with its count
            if kind not in _PLY_SIZES or (tok[1] == "list" and tok[3] not in _PLY_SIZES):
                raise GoiError(f"{path}: unknown PLY property type in {ln.strip()!r}")
            name, count, row = elements[-1]
            elements[-1] = (name, count, row + (2 if fmt == "ascii" else _PLY_SIZES[kind]))
    vert = next((e for e in elements if e[0] == "vertex"), None)
    if vert is None:
        raise GoiError(f"{path}: no 'vertex' element: not a 3D Gaussian Splatting PLY")
    if vert[1] > MAX_VERTICES:
        raise GoiError(
            f"{path}: header declares {vert[1]} vertices, more than goi accepts ({MAX_VERTICES})"
        )
    have = size - body_start
    need = 0
    for name, count, row in elements:
        need += count * max(row, 1)
        if need > have:
            rows = "vertices" if name == "vertex" else f"'{name}' rows"
            raise GoiError(
                f"{path}: truncated or corrupt: the header declares {count} {rows} "
                f"(at least {need} bytes of data up to them) but the file holds {have} bytes"
            )
    return vert[1]


def load_ply(path: str | os.PathLike[str]) -> Gaussians:
    p = regular_file(path, "PLY file")
    _check_header(p)
    try:
        ply = plyfile.PlyData.read(str(p))
        vertex = ply["vertex"].data
    except (plyfile.PlyParseError, ValueError, KeyError, EOFError, IndexError) as e:
        raise GoiError(f"{p}: cannot parse PLY ({e})") from None
    names = vertex.dtype.names or ()
    odd = [nm for nm in names if vertex.dtype[nm].kind not in "iuf" or vertex.dtype[nm].shape]
    if odd:
        raise GoiError(
            f"{p}: vertex property '{odd[0]}' is a list (or not a number); the properties of "
            "a 3DGS PLY are single numbers"
        )
    missing = [n for n in REQUIRED if n not in names]
    if missing:
        raise GoiError(f"{p}: field(s) {', '.join(missing)} missing: not an INRIA 3DGS PLY")
    n = len(vertex)
    if n == 0:
        raise GoiError(f"{p}: holds zero Gaussians")
    rest = sorted(
        (nm for nm in names if nm.startswith("f_rest_")),
        key=lambda s: int(s.split("_")[-1]) if s.split("_")[-1].isdigit() else -1,
    )
    if len(rest) not in REST_COUNTS or rest != [f"f_rest_{i}" for i in range(len(rest))]:
        raise GoiError(
            f"{p}: {len(rest)} f_rest_* fields; an SH degree 0-3 needs 0, 9, 24 or 45 "
            "numbered from f_rest_0"
        )
    vertex = vertex.astype(vertex.dtype.newbyteorder("="))  # big-endian files become native

    def cols(fields: list[str] | tuple[str, ...]) -> np.ndarray:
        out = np.stack([np.asarray(vertex[f], dtype=np.float32) for f in fields], axis=1)
        bad = ~np.isfinite(out)
        if bad.any():
            col = int(np.argmax(bad.any(axis=0)))
            raise GoiError(
                f"{p}: field '{fields[col]}' holds {int(bad[:, col].sum())} NaN/inf "
                f"values (first at vertex {int(np.argmax(bad[:, col]))})"
            )
        return out

    degree = REST_COUNTS[len(rest)]
    k = (degree + 1) ** 2
    means = cols(["x", "y", "z"])
    dc = cols(["f_dc_0", "f_dc_1", "f_dc_2"])
    sh = np.empty((n, k, 3), np.float32)
    sh[:, 0] = dc
    if degree:
        # f_rest is channel-major: all R coefficients, then G, then B.
        sh[:, 1:] = cols(rest).reshape(n, 3, k - 1).transpose(0, 2, 1)
    op_logit = cols(["opacity"])[:, 0]
    log_scales = cols(["scale_0", "scale_1", "scale_2"])
    rots = cols(["rot_0", "rot_1", "rot_2", "rot_3"]).astype(np.float64)  # float32 squares overflow
    norm = np.linalg.norm(rots, axis=1)
    valid = norm > 1e-12
    quats = rots / np.where(valid, norm, 1.0)[:, None]
    if not valid.any():
        raise GoiError(f"{p}: every Gaussian has a zero quaternion (rot_0..3): nothing to render")
    if not valid.all():
        warn(f"{p}: {int((~valid).sum())} Gaussians have a zero quaternion and are skipped")
    with np.errstate(over="ignore"):
        scales = np.exp(np.minimum(log_scales, 80.0)).astype(np.float32)
        opacities = (1.0 / (1.0 + np.exp(-op_logit))).astype(np.float32)
    return Gaussians(
        p,
        vertex,
        means,
        quats.astype(np.float32),
        scales,
        opacities,
        sh,
        degree,
        valid,
        list(ply.comments),
    )


def save_ply(
    path: str | os.PathLike[str],
    vertex: np.ndarray,
    force: bool = False,
    comments: Sequence[str] = (),
) -> None:
    """Write a vertex table as a binary little-endian PLY, atomically, with `comments` as the
    header's comment lines (printable ASCII: readers decode the header as ASCII, goi too)."""
    from numpy.lib.recfunctions import repack_fields

    bad = [c for c in comments if not (c.isascii() and c.isprintable())]
    if bad:  # a caller's bug, never the user's: comments are built by goi
        raise ValueError(f"PLY comment {bad[0][:60]!r} is not printable ASCII")
    le = repack_fields(vertex).astype(repack_fields(vertex).dtype.newbyteorder("<"))
    el = plyfile.PlyElement.describe(le, "vertex")
    with atomic_path(path, force) as tmp:
        plyfile.PlyData([el], text=False, byte_order="<", comments=list(comments)).write(str(tmp))

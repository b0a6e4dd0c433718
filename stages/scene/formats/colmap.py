"""COLMAP sparse models (cameras + images, .txt or .bin), PINHOLE or SIMPLE_PINHOLE cameras."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from stages.core.errors import GoiError
from stages.core.files import read_bytes, read_text
from stages.scene.cameras import Camera, checked, stem
from stages.scene.rotation import quat_to_rotmat, rotmat_to_quat

#: images.bin holds every image's 2D points; a model of this size has tens of thousands of images.
MAX_COLMAP_BYTES = 8 << 30

_COLMAP_MODELS = {
    0: ("SIMPLE_PINHOLE", 3),
    1: ("PINHOLE", 4),
    2: ("SIMPLE_RADIAL", 4),
    3: ("RADIAL", 5),
    4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8),
    6: ("FULL_OPENCV", 12),
    7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5),
    10: ("THIN_PRISM_FISHEYE", 12),
}


def _colmap_intrinsics(model: str, params: list[float], cam_id: int, where: str):
    if model == "PINHOLE":
        return params[0], params[1], params[2], params[3]
    if model == "SIMPLE_PINHOLE":
        return params[0], params[0], params[1], params[2]
    raise GoiError(
        f"{where}: camera {cam_id} uses the {model} model; goi needs PINHOLE or "
        "SIMPLE_PINHOLE: undistort the images first (colmap image_undistorter)"
    )


def _read_colmap_txt(d: Path):
    cams: dict[int, tuple] = {}
    where = str(d / "cameras.txt")
    for ln in read_text(d / "cameras.txt", "COLMAP cameras.txt").splitlines():
        tok = ln.split()
        if not tok or tok[0].startswith("#"):
            continue
        try:
            cid, model, w, h = int(tok[0]), tok[1], int(tok[2]), int(tok[3])
            params = [float(v) for v in tok[4:]]
        except (ValueError, IndexError):
            raise GoiError(f"{where}: malformed line {ln!r}") from None
        known = {name: n for name, n in _COLMAP_MODELS.values()}
        if model in known and len(params) != known[model]:
            raise GoiError(f"{where}: camera {cid} ({model}) needs {known[model]} parameters")
        cams[cid] = (w, h, *_colmap_intrinsics(model, params, cid, where))
    images = []
    where = str(d / "images.txt")
    text = read_text(d / "images.txt", "COLMAP images.txt")
    lines = [ln for ln in text.splitlines() if not ln.startswith("#")]
    # Each image takes two lines; the second (its 2D points) may be empty.
    for ln in lines[0::2]:
        tok = ln.split()
        if not tok:
            continue
        if len(tok) < 10:
            raise GoiError(f"{where}: malformed image line {ln!r}")
        try:
            q = np.array([float(v) for v in tok[1:5]])
            t = np.array([float(v) for v in tok[5:8]])
            cid = int(tok[8])
        except ValueError:
            raise GoiError(f"{where}: malformed image line {ln!r}") from None
        images.append((" ".join(tok[9:]), q, t, cid))
    return cams, images


class _Reader:
    def __init__(self, path: Path):
        self.path, self.pos = path, 0
        self.buf = read_bytes(path, "COLMAP binary file", limit=MAX_COLMAP_BYTES)

    def read(self, fmt: str):
        size = struct.calcsize(fmt)
        if self.pos + size > len(self.buf):
            raise GoiError(f"{self.path}: truncated COLMAP binary file")
        out = struct.unpack_from(fmt, self.buf, self.pos)
        self.pos += size
        return out

    def cstring(self) -> str:
        end = self.buf.find(b"\0", self.pos)
        if end < 0:
            raise GoiError(f"{self.path}: truncated COLMAP binary file")
        s = self.buf[self.pos : end].decode("utf-8", "replace")
        self.pos = end + 1
        return s


def _read_colmap_bin(d: Path):
    r = _Reader(d / "cameras.bin")
    cams: dict[int, tuple] = {}
    (n,) = r.read("<Q")
    for _ in range(n):
        cid, mid, w, h = r.read("<iiQQ")
        if mid not in _COLMAP_MODELS:
            raise GoiError(f"{r.path}: camera {cid} has unknown model id {mid}")
        model, npar = _COLMAP_MODELS[mid]
        params = list(r.read(f"<{npar}d"))
        cams[cid] = (w, h, *_colmap_intrinsics(model, params, cid, str(r.path)))
    r = _Reader(d / "images.bin")
    images = []
    (n,) = r.read("<Q")
    for _ in range(n):
        _iid, *rest = r.read("<i7di")
        q, t, cid = np.array(rest[0:4]), np.array(rest[4:7]), rest[7]
        name = r.cstring()
        (npts,) = r.read("<Q")
        r.pos += npts * 24  # x, y (double) and point3D id (int64) per 2D point
        images.append((name, q, t, cid))
    return cams, images


def read_colmap(d: Path) -> list[Camera]:
    if (d / "cameras.bin").is_file() and (d / "images.bin").is_file():
        cams, images = _read_colmap_bin(d)
    elif (d / "cameras.txt").is_file() and (d / "images.txt").is_file():
        cams, images = _read_colmap_txt(d)
    else:
        raise GoiError(f"{d}: no COLMAP model (cameras.bin/images.bin or cameras.txt/images.txt)")
    out = []
    for name, q, t, cid in sorted(images, key=lambda im: im[0]):
        if cid not in cams:
            raise GoiError(f"{d}: image {name!r} refers to camera {cid}, which is not defined")
        w, h, fx, fy, cx, cy = cams[cid]
        if np.linalg.norm(q) < 1e-12:
            raise GoiError(f"{d}: image {name!r} has a zero quaternion")
        out.append(
            checked(
                Camera(
                    stem(name),
                    int(w),
                    int(h),
                    fx,
                    fy,
                    cx,
                    cy,
                    quat_to_rotmat(q),
                    t.astype(np.float64),
                    name,
                ),
                str(d),
            )
        )
    return out


_MODEL_IDS = {"SIMPLE_PINHOLE": 0, "PINHOLE": 1, "OPENCV": 4}


def _params(c: Camera, model: str) -> list[float]:
    if model == "SIMPLE_PINHOLE":
        return [c.fx, c.cx, c.cy]
    if model == "PINHOLE":
        return [c.fx, c.fy, c.cx, c.cy]
    return [c.fx, c.fy, c.cx, c.cy, 0.01, 0.0, 0.0, 0.0]  # OPENCV, for the refusal tests


def _floats(values) -> str:  # noqa: ANN001
    return " ".join(repr(float(v)) for v in values)


def write_colmap(d: Path, cams: list[Camera], binary: bool, model: str = "PINHOLE") -> Path:
    """cameras and images (.bin or .txt) of a COLMAP model, one camera per image; each image
    gets one 2D point, or none, so that both line layouts of images.txt occur."""
    d.mkdir(parents=True, exist_ok=True)
    if binary:
        with open(d / "cameras.bin", "wb") as f:
            f.write(struct.pack("<Q", len(cams)))
            for i, c in enumerate(cams):
                params = _params(c, model)
                f.write(struct.pack("<iiQQ", i + 1, _MODEL_IDS[model], c.width, c.height))
                f.write(struct.pack(f"<{len(params)}d", *params))
        with open(d / "images.bin", "wb") as f:
            f.write(struct.pack("<Q", len(cams)))
            for i, c in enumerate(cams):
                f.write(struct.pack("<i7di", i + 1, *rotmat_to_quat(c.R), *c.t, i + 1))
                f.write(f"{c.name}.png".encode() + b"\0")
                f.write(struct.pack("<Q", 1))
                f.write(struct.pack("<ddq", 1.0, 2.0, -1))
        return d
    lines = ["# Camera list"]
    lines += [
        f"{i + 1} {model} {c.width} {c.height} {_floats(_params(c, model))}"
        for i, c in enumerate(cams)
    ]
    (d / "cameras.txt").write_text("\n".join(lines) + "\n")
    lines = ["# Image list"]
    for i, c in enumerate(cams):
        lines.append(f"{i + 1} {_floats(rotmat_to_quat(c.R))} {_floats(c.t)} {i + 1} {c.name}.png")
        lines.append("" if i % 2 else "1.0 2.0 -1")
    (d / "images.txt").write_text("\n".join(lines) + "\n")
    return d

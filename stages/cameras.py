"""Pinhole cameras from INRIA cameras.json, Blender/NeRF transforms*.json and COLMAP models.

All loaders produce the same `Camera`: world-to-camera rotation and translation in OpenCV axes
(x right, y down, z forward) and intrinsics in pixels with pixel centres at integer + 0.5, which is
the convention of COLMAP, of the INRIA rasteriser and of goi's own.
"""

from __future__ import annotations

import json
import math
import os
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stages.errors import GoiError

# OpenGL camera axes (y up, z backward) to OpenCV axes (y down, z forward).
GL_TO_CV = np.diag([1.0, -1.0, -1.0])
IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")
MAX_IMAGE_SIDE = 16384


@dataclass
class Camera:
    name: str  # image name without extension; the key every artifact uses for the view
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    R: np.ndarray  # [3, 3] world-to-camera rotation (OpenCV axes)
    t: np.ndarray  # [3] world-to-camera translation
    image: str | None = None  # image file, as the camera file names it (may lack an extension)

    @property
    def center(self) -> np.ndarray:  # [3]
        return -self.R.T @ self.t

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points [N, 3] -> pixel coordinates [N, 2] (continuous) and depth [N]."""
        pc = points @ self.R.T + self.t
        z = pc[:, 2]
        uv = np.stack([self.fx * pc[:, 0] / z + self.cx, self.fy * pc[:, 1] / z + self.cy], 1)
        return uv, z

    def scaled(self, width: int, height: int) -> Camera:
        """The same camera for an image resized to width x height."""
        sx, sy = width / self.width, height / self.height
        return Camera(
            self.name,
            width,
            height,
            self.fx * sx,
            self.fy * sy,
            self.cx * sx,
            self.cy * sy,
            self.R,
            self.t,
            self.image,
        )


def _checked(cam: Camera, where: str) -> Camera:
    if not (math.isfinite(cam.fx) and math.isfinite(cam.fy)) or cam.fx <= 0 or cam.fy <= 0:
        raise GoiError(
            f"{where}: camera '{cam.name}' has non-positive or non-finite focal length "
            f"(fx={cam.fx}, fy={cam.fy})"
        )
    if not (0 < cam.width <= MAX_IMAGE_SIDE and 0 < cam.height <= MAX_IMAGE_SIDE):
        raise GoiError(
            f"{where}: camera '{cam.name}' has image size {cam.width}x{cam.height}; "
            f"goi accepts 1..{MAX_IMAGE_SIDE} pixels a side"
        )
    if not (np.isfinite(cam.R).all() and np.isfinite(cam.t).all()):
        raise GoiError(f"{where}: camera '{cam.name}' has a non-finite pose")
    if abs(np.linalg.det(cam.R) - 1.0) > 1e-3:
        raise GoiError(
            f"{where}: camera '{cam.name}' rotation is not a rotation (det = "
            f"{np.linalg.det(cam.R):.4f})"
        )
    return cam


def _num(obj: dict, key: str, where: str) -> float:
    if key not in obj:
        raise GoiError(f"{where}: field '{key}' is missing")
    try:
        return float(obj[key])
    except (TypeError, ValueError):
        raise GoiError(f"{where}: field '{key}' is not a number ({obj[key]!r})") from None


def _matrix(obj: dict, key: str, shape: tuple[int, int], where: str) -> np.ndarray:
    try:
        m = np.asarray(obj[key], dtype=np.float64)
    except KeyError:
        raise GoiError(f"{where}: field '{key}' is missing") from None
    except (TypeError, ValueError):
        raise GoiError(f"{where}: field '{key}' is not a numeric matrix") from None
    if m.shape != shape:
        raise GoiError(f"{where}: field '{key}' has shape {m.shape}, expected {shape}")
    return m


def _stem(name: str) -> str:
    base = name.replace("\\", "/").rsplit("/", 1)[-1]
    root, ext = os.path.splitext(base)
    return root if ext in IMAGE_EXTS else base


def load_inria(path: Path) -> list[Camera]:
    data = _read_json(path)
    if not isinstance(data, list):
        raise GoiError(f"{path}: INRIA cameras.json should be a list of cameras")
    cams = []
    for i, c in enumerate(data):
        where = f"{path} [camera {i}]"
        if not isinstance(c, dict):
            raise GoiError(f"{where}: not an object")
        if "img_name" not in c:
            raise GoiError(f"{where}: field 'img_name' is missing")
        c2w = _matrix(c, "rotation", (3, 3), where)  # camera-to-world, OpenCV axes
        pos = (
            _matrix({"p": [c.get("position")]}, "p", (1, 3), where)[0] if "position" in c else None
        )
        if pos is None:
            raise GoiError(f"{where}: field 'position' is missing")
        w, h = int(_num(c, "width", where)), int(_num(c, "height", where))
        R = c2w.T
        cams.append(
            _checked(
                Camera(
                    _stem(str(c["img_name"])),
                    w,
                    h,
                    _num(c, "fx", where),
                    _num(c, "fy", where),
                    w / 2,
                    h / 2,
                    R,
                    -R @ pos,
                    str(c["img_name"]),
                ),
                where,
            )
        )
    return cams


def _image_size(image: Path, where: str) -> tuple[int, int]:
    import cv2

    found = _find_image(image)
    if found is None:
        raise GoiError(f"{where}: no 'w'/'h' given and image {image} is missing")
    img = cv2.imread(str(found), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise GoiError(f"{found}: cannot read image")
    return int(img.shape[1]), int(img.shape[0])


def _find_image(path: Path) -> Path | None:
    if path.suffix in IMAGE_EXTS and path.is_file():
        return path
    for ext in IMAGE_EXTS:
        cand = path.with_name(path.name + ext)
        if cand.is_file():
            return cand
    return None


def load_transforms(path: Path) -> list[Camera]:
    data = _read_json(path)
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list):
        raise GoiError(f"{path}: a transforms.json needs a 'frames' list")
    cams = []
    for i, fr in enumerate(data["frames"]):
        where = f"{path} [frame {i}]"
        if not isinstance(fr, dict) or "file_path" not in fr:
            raise GoiError(f"{where}: field 'file_path' is missing")
        meta = {**data, **fr}  # per-frame intrinsics (nerfstudio) override the shared ones
        c2w = _matrix(fr, "transform_matrix", (4, 4), where)
        file_path = str(fr["file_path"])
        if "w" in meta and "h" in meta:
            w, h = int(_num(meta, "w", where)), int(_num(meta, "h", where))
        else:
            w, h = _image_size(path.parent / file_path, where)
        if "fl_x" in meta:
            fx = _num(meta, "fl_x", where)
            fy = _num(meta, "fl_y", where) if "fl_y" in meta else fx
        elif "camera_angle_x" in meta:
            fx = 0.5 * w / math.tan(0.5 * _num(meta, "camera_angle_x", where))
            fy = (
                0.5 * h / math.tan(0.5 * _num(meta, "camera_angle_y", where))
                if "camera_angle_y" in meta
                else fx
            )
        else:
            raise GoiError(f"{where}: no intrinsics: needs 'camera_angle_x' or 'fl_x'")
        cx = _num(meta, "cx", where) if "cx" in meta else w / 2
        cy = _num(meta, "cy", where) if "cy" in meta else h / 2
        R_c2w = c2w[:3, :3] @ GL_TO_CV
        R = R_c2w.T
        cams.append(
            _checked(
                Camera(_stem(file_path), w, h, fx, fy, cx, cy, R, -R @ c2w[:3, 3], file_path), where
            )
        )
    return cams


# --- COLMAP -------------------------------------------------------------------------------

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


def quat_to_rotmat(q: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) -> [3, 3] rotation matrix."""
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


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
    for ln in (d / "cameras.txt").read_text().splitlines():
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
    lines = [ln for ln in (d / "images.txt").read_text().splitlines() if not ln.startswith("#")]
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
        self.path, self.buf, self.pos = path, path.read_bytes(), 0

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


def load_colmap(d: Path) -> list[Camera]:
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
            _checked(
                Camera(
                    _stem(name),
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


def _read_json(path: Path):
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise GoiError(f"{path}: no such file") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise GoiError(f"{path}: not valid JSON ({e})") from None


def load_cameras(path: str | os.PathLike[str]) -> list[Camera]:
    """Load cameras from a file or COLMAP directory, telling the format by its content."""
    p = Path(path)
    if p.is_dir():
        sub = p / "sparse" / "0"
        cams = load_colmap(sub if sub.is_dir() else p)
    elif not p.exists():
        raise GoiError(f"{p}: no such cameras file")
    elif p.suffix == ".json":
        data = _read_json(p)
        cams = load_inria(p) if isinstance(data, list) else load_transforms(p)
    else:
        raise GoiError(
            f"{p}: unknown cameras format: give cameras.json, transforms*.json or a "
            "COLMAP sparse model directory"
        )
    if not cams:
        raise GoiError(f"{p}: holds no cameras")
    names = [c.name for c in cams]
    if len(set(names)) != len(names):
        dup = next(n for n in names if names.count(n) > 1)
        raise GoiError(f"{p}: view name '{dup}' appears more than once")
    return cams

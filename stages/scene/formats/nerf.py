"""Blender/NeRF transforms*.json: camera_angle_x (or fl_x/fl_y/cx/cy, shared or per frame) and
frames of {file_path, transform_matrix}, a 4x4 camera-to-world in OpenGL axes (y up, z back)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from stages.core.errors import GoiError
from stages.scene.cameras import GL_TO_CV, IMAGE_EXTS, Camera, checked, matrix, num, pixels, stem
from stages.scene.images import image_size, read_rgb


def _image_size(image: Path, where: str) -> tuple[int, int]:
    found = _find_image(image)
    if found is None:
        raise GoiError(f"{where}: no 'w'/'h' given and image {image} is missing")
    size = image_size(found)  # from the header, without decoding
    if size is None:
        rgb = read_rgb(found)
        size = (int(rgb.shape[1]), int(rgb.shape[0]))
    return size


def _find_image(path: Path) -> Path | None:
    if path.suffix in IMAGE_EXTS and path.is_file():
        return path
    for ext in IMAGE_EXTS:
        cand = path.with_name(path.name + ext)
        if cand.is_file():
            return cand
    return None


def _angle(meta: dict, key: str, where: str) -> float:
    """A field of view in radians, strictly between 0 and pi."""
    a = num(meta, key, where)
    if not 0 < a < math.pi:
        raise GoiError(f"{where}: field '{key}' is {a:g} radians; a field of view is in (0, pi)")
    return a


def read_transforms(path: Path, data: object) -> list[Camera]:
    """Cameras from the parsed JSON `data` of `path`."""
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list):
        raise GoiError(f"{path}: a transforms.json needs a 'frames' list")
    cams = []
    for i, fr in enumerate(data["frames"]):
        where = f"{path} [frame {i}]"
        if not isinstance(fr, dict) or "file_path" not in fr:
            raise GoiError(f"{where}: field 'file_path' is missing")
        meta = {**data, **fr}  # per-frame intrinsics (nerfstudio) override the shared ones
        c2w = matrix(fr, "transform_matrix", (4, 4), where)
        file_path = str(fr["file_path"])
        if "w" in meta and "h" in meta:
            w, h = pixels(meta, "w", where), pixels(meta, "h", where)
        else:
            w, h = _image_size(path.parent / file_path, where)
        if "fl_x" in meta:
            fx = num(meta, "fl_x", where)
            fy = num(meta, "fl_y", where) if "fl_y" in meta else fx
        elif "camera_angle_x" in meta:
            fx = 0.5 * w / math.tan(0.5 * _angle(meta, "camera_angle_x", where))
            fy = (
                0.5 * h / math.tan(0.5 * _angle(meta, "camera_angle_y", where))
                if "camera_angle_y" in meta
                else fx
            )
        else:
            raise GoiError(f"{where}: no intrinsics: needs 'camera_angle_x' or 'fl_x'")
        cx = num(meta, "cx", where) if "cx" in meta else w / 2
        cy = num(meta, "cy", where) if "cy" in meta else h / 2
        R_c2w = c2w[:3, :3] @ GL_TO_CV
        R = R_c2w.T
        cams.append(
            checked(
                Camera(stem(file_path), w, h, fx, fy, cx, cy, R, -R @ c2w[:3, 3], file_path), where
            )
        )
    return cams


def write_transforms(path: Path, cams: list[Camera], intrinsics: str = "angle") -> Path:
    """The cameras as one transforms.json; the first camera's intrinsics are shared, as
    `camera_angle_x` (intrinsics="angle"), fl_x/fl_y/cx/cy ("focal"), or left out ("none",
    which goi refuses to read: for the tests)."""
    c0 = cams[0]
    data: dict = {"w": c0.width, "h": c0.height}
    if intrinsics == "angle":
        data["camera_angle_x"] = 2 * np.arctan(0.5 * c0.width / c0.fx)
    elif intrinsics == "focal":
        data.update(fl_x=c0.fx, fl_y=c0.fy, cx=c0.cx, cy=c0.cy)
    frames = []
    for c in cams:
        m = np.eye(4)
        m[:3, :3] = c.R.T @ GL_TO_CV
        m[:3, 3] = c.center
        frames.append({"file_path": f"images/{c.name}.png", "transform_matrix": m.tolist()})
    data["frames"] = frames
    path.write_text(json.dumps(data))
    return path

"""INRIA 3DGS cameras.json: a list of {id, img_name, width, height, position (camera centre),
rotation (3x3 camera-to-world, OpenCV axes), fx, fy}; the principal point is the image centre."""

from __future__ import annotations

import json
from pathlib import Path

from stages.core.errors import GoiError
from stages.scene.cameras import Camera, checked, matrix, num, pixels, stem, view_name_ok


def read_inria(path: Path, data: object) -> list[Camera]:
    """Cameras from the parsed JSON `data` of `path`."""
    if not isinstance(data, list):
        raise GoiError(f"{path}: INRIA cameras.json should be a list of cameras")
    cams = []
    for i, c in enumerate(data):
        where = f"{path} [camera {i}]"
        if not isinstance(c, dict):
            raise GoiError(f"{where}: not an object")
        name = c.get("img_name")
        if not isinstance(name, str) or not view_name_ok(stem(name)):
            raise GoiError(
                f"{where}: field 'img_name' must be an image file name (a non-empty string "
                f"without control characters); found {str(name)[:60]!r}"
            )
        c2w = matrix(c, "rotation", (3, 3), where)  # camera-to-world, OpenCV axes
        pos = matrix(c, "position", (3,), where)
        w, h = pixels(c, "width", where), pixels(c, "height", where)
        R = c2w.T
        cams.append(
            checked(
                Camera(
                    stem(name),
                    w,
                    h,
                    num(c, "fx", where),
                    num(c, "fy", where),
                    w / 2,
                    h / 2,
                    R,
                    -R @ pos,
                    name,
                ),
                where,
            )
        )
    return cams


def write_inria(path: Path, cams: list[Camera]) -> Path:
    """The cameras as an INRIA cameras.json (principal points other than the centre are lost)."""
    out = [
        {
            "id": i,
            "img_name": c.name,
            "width": c.width,
            "height": c.height,
            "position": c.center.tolist(),
            "rotation": c.R.T.tolist(),
            "fx": c.fx,
            "fy": c.fy,
        }
        for i, c in enumerate(cams)
    ]
    path.write_text(json.dumps(out))
    return path

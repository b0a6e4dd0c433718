"""INRIA 3DGS cameras.json: a list of {id, img_name, width, height, position (camera centre),
rotation (3x3 camera-to-world, OpenCV axes), fx, fy}; the principal point is the image centre."""

from __future__ import annotations

import json
from pathlib import Path

from stages.core.errors import GoiError
from stages.scene.cameras import Camera, checked, matrix, num, pixels, stem


def read_inria(path: Path, data: object) -> list[Camera]:
    """Cameras from the parsed JSON `data` of `path`."""
    if not isinstance(data, list):
        raise GoiError(f"{path}: INRIA cameras.json should be a list of cameras")
    cams = []
    for i, c in enumerate(data):
        where = f"{path} [camera {i}]"
        if not isinstance(c, dict):
            raise GoiError(f"{where}: not an object")
        if "img_name" not in c:
            raise GoiError(f"{where}: field 'img_name' is missing")
        c2w = matrix(c, "rotation", (3, 3), where)  # camera-to-world, OpenCV axes
        pos = matrix({"p": [c.get("position")]}, "p", (1, 3), where)[0] if "position" in c else None
        if pos is None:
            raise GoiError(f"{where}: field 'position' is missing")
        w, h = pixels(c, "width", where), pixels(c, "height", where)
        R = c2w.T
        cams.append(
            checked(
                Camera(
                    stem(str(c["img_name"])),
                    w,
                    h,
                    num(c, "fx", where),
                    num(c, "fy", where),
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

"""One module per camera file format; each reads into and writes from `Camera`.

`load_cameras` tells the format of a file or directory by its content.
"""

from __future__ import annotations

import os
from pathlib import Path

from stages.core.errors import GoiError
from stages.core.files import read_json
from stages.scene.cameras import Camera
from stages.scene.formats import colmap, inria, nerf


def load_cameras(path: str | os.PathLike[str]) -> list[Camera]:
    """Load cameras from a file or COLMAP directory, telling the format by its content."""
    p = Path(path)
    if p.is_dir():
        sub = p / "sparse" / "0"
        cams = colmap.read_colmap(sub if sub.is_dir() else p)
    elif not p.exists():
        raise GoiError(f"{p}: no such cameras file")
    elif p.suffix == ".json":
        data = read_json(p, "no such file")
        cams = (
            inria.read_inria(p, data) if isinstance(data, list) else nerf.read_transforms(p, data)
        )
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

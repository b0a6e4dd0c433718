"""GOI's Mip-NeRF360 set (Quyans/GOI-Hyperplane, eval_seg.py `m360`).

<root>/<scene>/<prompt>/masks/<image>.<ext>: the prompt folder is the query with underscores
(sofa_in_dark_green); the image keeps its capture name (DSCF4667); ground truth > 0 (read as
cv2 greys). A mask whose image has no camera is skipped with a warning, as the script skips a
missing rendering.
"""

from __future__ import annotations

from pathlib import Path

from stages.core.errors import GoiError
from stages.evaluation.benchmarks.common import (
    BenchmarkScene,
    Frame,
    Query,
    camera_or_skip,
    checked_size,
    read_grey_cv2,
    require_dir,
)
from stages.query.prompts import check_plain_name
from stages.scene.cameras import IMAGE_EXTS, Camera

SCENES = ("room", "bonsai", "garden", "kitchen")


def read_goi_m360(root: Path, scene: str, cameras: list[Camera]) -> BenchmarkScene:
    d = require_dir(root / scene, "GOI's Mip-NeRF360 set keeps <scene>/<prompt>/masks/ there")
    by_name = {c.name: c for c in cameras}
    out = BenchmarkScene(scene, d, [], [])
    frames: dict[str, Frame] = {}
    for prompt in sorted(p for p in d.iterdir() if p.is_dir()):
        masks = require_dir(prompt / "masks", "each prompt folder holds masks/<image>")
        qid = check_plain_name(prompt.name, str(prompt))
        q = Query(qid, prompt.name.replace("_", " "))
        files = sorted(p for p in masks.iterdir() if p.suffix in IMAGE_EXTS)
        if not files:
            raise GoiError(f"{masks}: no mask images")
        out.queries.append(q)
        for f in files:
            name = f.name.split(".")[0]
            cam = camera_or_skip(out, by_name, name, f)
            if cam is None:
                continue
            frame = frames.get(name)
            if frame is None:  # the size from the header, checked before decoding
                frame = frames[name] = Frame(
                    name, checked_size(cam, f, "ground-truth mask"), masks, {}
                )
            else:
                checked_size(cam, f, "ground-truth mask", frame.camera)
            if q.id in frame.gts:
                raise GoiError(f"{f}: a second mask of image {name!r} for prompt {prompt.name!r}")
            frame.gts[q.id] = read_grey_cv2(f, "ground-truth mask") > 0
    if not out.queries:
        raise GoiError(f"{d}: no <prompt>/masks/ folders")
    out.frames = list(frames.values())
    return out

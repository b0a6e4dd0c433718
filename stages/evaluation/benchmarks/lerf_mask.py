"""LERF-Mask as Gaussian Grouping releases it (script/eval_lerf_mask.py).

<root>/<scene>/{images, images_train, sparse, test_mask}: ground truth
test_mask/<view>/<prompt>.png (grey > 128 is in); the test views are the cameras whose image is
not in images_train/ (the field never trains on them). A view folder without a camera is
skipped with a warning, as the script skips a missing prediction.
"""

from __future__ import annotations

from pathlib import Path

from stages.core.errors import GoiError
from stages.evaluation.benchmarks.common import (
    BenchmarkScene,
    Frame,
    Query,
    query_id,
    read_grey,
    require_dir,
    scaled_to,
    skip,
)
from stages.scene.cameras import Camera

SCENES = ("figurines", "ramen", "teatime")


def read_lerf_mask(root: Path, scene: str, cameras: list[Camera]) -> BenchmarkScene:
    d = root / scene
    masks = require_dir(d / "test_mask", "LERF-Mask keeps the ground truth in test_mask/<view>/")
    train_dir = require_dir(d / "images_train", "LERF-Mask's training images tell the test views")
    trained = {p.stem for p in train_dir.iterdir() if p.is_file()}
    by_name = {c.name: c for c in cameras}
    out = BenchmarkScene(scene, masks, [], [])
    out.held_out = {c.name for c in cameras if c.name not in trained}
    queries: dict[str, Query] = {}
    for view_dir in sorted(p for p in masks.iterdir() if p.is_dir()):
        cam = by_name.get(view_dir.name)
        if cam is None:
            skip(out, f"{view_dir}: no camera named {view_dir.name!r}; view skipped")
            continue
        if cam.name in trained:
            raise GoiError(
                f"{view_dir}: view {cam.name!r} has ground truth but is in images_train/ "
                "(LERF-Mask's test views are the images not in images_train)"
            )
        pngs = sorted(view_dir.glob("*.png"))
        if not pngs:
            skip(out, f"{view_dir}: no <prompt>.png; view skipped")
            continue
        frame: Frame | None = None
        for png in pngs:
            text = png.name.split(".")[0]  # the script's cat_id
            gt = read_grey(png, "ground-truth mask")
            if frame is None:
                frame = Frame(
                    view_dir.name, scaled_to(cam, gt.shape[1], gt.shape[0], str(png)), view_dir, {}
                )
            elif gt.shape != frame.gts[next(iter(frame.gts))].shape:
                raise GoiError(
                    f"{png}: {gt.shape[1]}x{gt.shape[0]}, other masks of the view differ"
                )
            q = queries.setdefault(text, Query(query_id(text), text))
            frame.gts[q.id] = gt
        assert frame is not None
        out.frames.append(frame)
    out.queries = list(queries.values())
    return out

"""3D-OVS (Kunhao-Liu/3D-OVS, dataLoader/llff.py, renderer.py).

<scene>/images/, segmentations/classes.txt (one class per line, stripped, sorted) and
segmentations/<NN>/<class>.png for every class (grey 'L', resized PIL-nearest to the evaluation
size, `/255` as int8: only 255 counts); int(NN) indexes sorted(images/*). Evaluated at
1/`downsample` of the image size (the reference scripts: 8).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from stages.core.errors import GoiError, warn
from stages.core.files import read_text
from stages.evaluation.benchmarks.common import (
    BenchmarkScene,
    Frame,
    Query,
    pil_nearest,
    query_id,
    read_grey,
    require_dir,
    scaled_to,
)
from stages.scene.cameras import Camera

SCENES = (
    "bed",
    "bench",
    "blue_sofa",
    "covered_desk",
    "lawn",
    "office_desk",
    "room",
    "snacks",
    "sofa",
    "table",
)


def read_classes(path: Path) -> list[str]:
    classes = [line.strip() for line in read_text(path, "3D-OVS class list").splitlines()]
    if not classes or any(not c for c in classes):
        raise GoiError(f"{path}: expected one class name per line, without blank lines")
    if len(set(classes)) != len(classes):
        raise GoiError(f"{path}: a class is listed twice")
    return sorted(classes)


def read_three_d_ovs(
    root: Path, scene: str, cameras: list[Camera], downsample: int = 8
) -> BenchmarkScene:
    d = root / scene
    seg = require_dir(d / "segmentations", "3D-OVS keeps classes.txt and <NN>/<class>.png there")
    images = sorted(
        p
        for p in require_dir(d / "images", "int(NN) indexes its sorted images").iterdir()
        if p.is_file()
    )
    classes = read_classes(seg / "classes.txt")
    by_image = {}
    for c in cameras:
        by_image[Path(c.image or c.name).name] = c
        by_image.setdefault(c.name, c)
    out = BenchmarkScene(scene, seg, [Query(query_id(c), c) for c in classes], [])
    for folder in sorted(p for p in seg.iterdir() if p.is_dir()):
        try:
            idx = int(folder.name)
        except ValueError:
            raise GoiError(
                f"{folder}: a segmentation folder is named by its image index (NN)"
            ) from None
        if not 0 <= idx < len(images):
            raise GoiError(
                f"{folder}: image index {idx}, but {d / 'images'} holds {len(images)} "
                "images: the frame has no camera"
            )
        image = images[idx]
        cam = by_image.get(image.name) or by_image.get(image.stem)
        if cam is None:
            raise GoiError(f"{folder}: its image {image.name} has no camera in the scene")
        cam = scaled_to(cam, int(cam.width / downsample), int(cam.height / downsample), str(folder))
        extra = sorted({p.stem for p in folder.glob("*.png")} - set(classes))
        if extra:
            warn(
                f"{folder}: mask(s) {', '.join(extra[:3])} of no class in classes.txt; "
                "ignored, as the reference does"
            )
        frame = Frame(folder.name, cam, folder, {})
        for q in out.queries:
            png = folder / f"{q.text}.png"
            if not png.is_file():
                raise GoiError(
                    f"{png}: missing; classes.txt lists {q.text!r}, and every class needs "
                    "a mask in every frame"
                )
            grey = pil_nearest(read_grey(png, "class mask"), cam.width, cam.height)
            frame.gts[q.id] = (grey.astype(np.float64) / 255.0).astype(np.int8)
        out.frames.append(frame)
    if not out.frames:
        raise GoiError(f"{seg}: no <NN>/ segmentation folders")
    return out

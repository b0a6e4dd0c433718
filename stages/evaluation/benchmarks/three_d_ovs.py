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
    MAX_ID_BYTES,
    BenchmarkScene,
    Frame,
    Query,
    checked_size,
    frame_index,
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
    """classes.txt as read_classes_names reads it: `[line.strip() for line in lines]`, sorted.
    A class names its mask file <class>.png in each frame folder: a name that is no plain file
    name (a '/', '..', a control character, too long) can name no mask, and is refused here."""
    classes = [line.strip() for line in read_text(path, "3D-OVS class list").splitlines()]
    if not classes or any(not c for c in classes):
        raise GoiError(f"{path}: expected one class name per line, without blank lines")
    if len(set(classes)) != len(classes):
        raise GoiError(f"{path}: a class is listed twice")
    for i, c in enumerate(classes):
        if (
            c in (".", "..")
            or any(x in c for x in "/\\")
            or not c.isprintable()
            or len(c.encode("utf-8", "surrogatepass")) > MAX_ID_BYTES
        ):
            raise GoiError(
                f"{path}: line {i + 1}: class {c[:60]!r} is not a file name (each class's mask "
                "is segmentations/<NN>/<class>.png)"
            )
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
    outside = f", but {d / 'images'} holds {len(images)} images: the frame has no camera"
    for folder in sorted(p for p in seg.iterdir() if p.is_dir()):
        bad = f"{folder}: a segmentation folder is named by its image index (NN)"
        idx = frame_index(folder.name, int, len(images), bad, (f"{folder}: image index ", outside))
        image = images[idx]
        cam = by_image.get(image.name) or by_image.get(image.stem)
        if cam is None:
            raise GoiError(f"{folder}: its image {image.name} has no camera in the scene")
        full = cam
        cam = scaled_to(cam, int(cam.width / downsample), int(cam.height / downsample), str(folder))
        extra = sorted({p.stem for p in folder.glob("*.png")} - set(classes))
        if extra:
            warn(
                f"{folder}: mask(s) {', '.join(extra[:3])} of no class in classes.txt; "
                "ignored, as the reference does"
            )
        frame = Frame(folder.name, cam, folder, {})
        # the class names are data: matched against the folder's file names, never joined
        pngs = {p.name[: -len(".png")]: p for p in folder.iterdir() if p.name.endswith(".png")}
        for q in out.queries:
            png = pngs.get(q.text)
            if png is None or not png.is_file():
                raise GoiError(
                    f"{folder}: no {q.text}.png; classes.txt lists {q.text!r}, and every class "
                    "needs a mask in every frame"
                )
            checked_size(full, png, "class mask")  # the image's size, before decoding
            grey = pil_nearest(read_grey(png, "class mask"), cam.width, cam.height)
            frame.gts[q.id] = (grey.astype(np.float64) / 255.0).astype(np.int8)
        out.frames.append(frame)
    if not out.frames:
        raise GoiError(f"{seg}: no <NN>/ segmentation folders")
    return out

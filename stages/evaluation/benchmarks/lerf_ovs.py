"""LERF-OVS as LangSplat releases it (eval/evaluate_iou_loc.py, eval_gt_lerfdata).

Labels: <root>/label/<scene>/frame_XXXXX.json (labelme-like) with `info.{height,width,name}`
and `objects[]` of `category`, `bbox` (x1 y1 x2 y2, reshaped flat) and `segmentation` (one
polygon, [x, y] points, int32, cv2.fillPoly). A category repeated in a frame: masks OR'd,
boxes concatenated. Frame -> view: idx = int(name.split('_')[-1].split('.jpg')[0]) - 1 into the
cameras sorted by image name (the labelled frames are training views). Scored at
info.height x info.width.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from stages.core.errors import GoiError, warn
from stages.core.files import read_json
from stages.evaluation.benchmarks.common import (
    BenchmarkScene,
    Frame,
    Query,
    frame_index,
    query_id,
    require_dir,
    scaled_to,
    sorted_by_image,
)
from stages.scene.cameras import Camera

SCENES = ("figurines", "ramen", "teatime", "waldo_kitchen")


def _int(x: object, where: str) -> int:
    if not isinstance(x, int) or isinstance(x, bool) or x < 2:
        raise GoiError(f"{where}: expected an integer of at least 2, found {x!r}")
    return x


def polygon_mask(h: int, w: int, polygon: object, where: str) -> np.ndarray:
    """[h, w] bool: the polygon filled as polygon_to_mask does (int32 points, cv2.fillPoly)."""
    import cv2

    try:
        pts = np.asarray(polygon, dtype=np.float64)
    except (TypeError, ValueError):
        raise GoiError(f"{where}: 'segmentation' is not a list of [x, y] points") from None
    pts = pts.reshape(-1, 2) if pts.size % 2 == 0 and pts.ndim >= 1 else pts
    if pts.ndim != 2 or pts.shape[1] != 2 or not len(pts) or not np.isfinite(pts).all():
        raise GoiError(f"{where}: 'segmentation' must be one polygon of finite [x, y] points")
    if (pts < 0).any() or (pts[:, 0] > w).any() or (pts[:, 1] > h).any():
        warn(
            f"{where}: the polygon reaches outside the {w}x{h} image; filled clipped to it, as "
            "the reference's cv2.fillPoly does"
        )
    mask = np.zeros((h, w), np.uint8)
    cv2.fillPoly(mask, [pts.astype(np.int32)], 1)
    return mask.astype(bool)


def read_lerf_ovs(root: Path, scene: str, cameras: list[Camera]) -> BenchmarkScene:
    labels = require_dir(root / "label" / scene, f"LERF-OVS keeps scene {scene!r}'s labels there")
    paths = sorted(labels.glob("frame_*.json"))
    if not paths:
        raise GoiError(f"{labels}: no frame_*.json labels")
    by_index = sorted_by_image(cameras)
    out = BenchmarkScene(scene, labels, [], [])
    queries: dict[str, Query] = {}
    for path in paths:
        doc = read_json(path)
        if not isinstance(doc, dict) or not isinstance(doc.get("info"), dict):
            raise GoiError(f"{path}: no 'info' object ({{height, width, name}})")
        info = doc["info"]
        h = _int(info.get("height"), f"{path}: field 'info.height'")
        w = _int(info.get("width"), f"{path}: field 'info.width'")
        name = info.get("name")
        if not isinstance(name, str):
            raise GoiError(f"{path}: field 'info.name' is missing or not a string")
        idx = frame_index(
            name,
            lambda n: int(n.split("_")[-1].split(".jpg")[0]),
            len(by_index),
            f"{path}: field 'info.name' {name!r} is not frame_<number>.jpg",
            (
                f"{path}: frame {name!r} is view ",
                f" of the cameras sorted by image name, but the scene has {len(by_index)} "
                "cameras: this frame has no camera",
            ),
            first=1,  # frame_00001 is the first view
        )
        objects = doc.get("objects")
        if not isinstance(objects, list):
            raise GoiError(f"{path}: no 'objects' list (the frame's annotated queries)")
        # the frame's size against its camera's before any array of it is made
        cam = scaled_to(by_index[idx], w, h, f"{path}: fields 'info.width' x 'info.height'")
        frame = Frame(Path(name).stem, cam, path, {})
        for k, obj in enumerate(objects):
            where = f"{path}: objects[{k}]"
            if not isinstance(obj, dict):
                raise GoiError(f"{where} is not an object {{category, bbox, segmentation}}")
            text = obj.get("category")
            if not isinstance(text, str) or not text.strip():
                raise GoiError(f"{where}: field 'category' is missing or not a string")
            try:
                box = np.asarray(obj.get("bbox"), dtype=np.float64).reshape(-1)
            except (TypeError, ValueError):
                raise GoiError(f"{where}: field 'bbox' is not a list of numbers") from None
            if box.size == 0 or box.size % 4 or not np.isfinite(box).all():
                raise GoiError(f"{where}: field 'bbox' must hold x1, y1, x2, y2 (4 numbers)")
            mask = polygon_mask(h, w, obj.get("segmentation"), where)
            q = queries.setdefault(text, Query(query_id(text), text))
            if q.id in frame.gts:
                frame.gts[q.id] = frame.gts[q.id] | mask
                frame.boxes[q.id] = np.concatenate([frame.boxes[q.id], box.reshape(-1, 4)])
            else:
                frame.gts[q.id], frame.boxes[q.id] = mask, box.reshape(-1, 4)
        out.frames.append(frame)
    out.queries = list(queries.values())
    return out

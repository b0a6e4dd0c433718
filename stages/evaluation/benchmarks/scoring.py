"""A benchmark scene's answers scored by its protocol and by goi's own metrics.

`predictions` is {query id: {camera name: [H, W] bool}} for one variant: goi's mask of every
annotated (frame, query) at the frame's camera. Every scene also gets `goi` (the paper's per-image
IoU / mPA / mP as goi's own metrics compute them, stages.evaluation.metrics: mean over a query's
frames, then over queries), so that goi's figure and the protocol's stand side by side on the
same frames.

How goi's answer enters each protocol:
- lerf-ovs: twice, as two relevancy maps of one level each (goi has no scales): the rendered
  0/1 mask, and (`score_maps`) the continuous score map, each Gaussian's score (the plane's
  probability or the lifted vote's share) composited by the rasteriser. The protocol's
  smoothing, normalisation, threshold and majority filter run on each unchanged, and
  localisation takes the maxima of its 30x30 mean.
- 3d-ovs: the per-pixel argmax over the classes runs over the 0/1 masks (classes in sorted
  order; a pixel that no class claims, or several do, goes to the first of them), and over the
  classes' continuous score maps.
- goi-m360, replica-goi, lerf-mask: binary masks, as the protocols score them.
"""

from __future__ import annotations

import numpy as np

from stages.core.errors import GoiError
from stages.evaluation.benchmarks.common import BenchmarkScene, Frame
from stages.evaluation.benchmarks.protocols import (
    binary_iou,
    closed_set,
    goi_eval_seg_image,
    lerf_mask_scores,
    lerf_ovs_localised,
    lerf_ovs_mask,
    nanless,
    three_d_ovs_scores,
)
from stages.evaluation.metrics import Scores, image_scores, mean_scores

#: benchmark -> (protocol name, the metrics it reports), in the report's order
PROTOCOLS = {
    "lerf-ovs": ("lerf-ovs (LangSplat evaluate_iou_loc.py)", ("miou", "localisation_accuracy")),
    "lerf-mask": ("lerf-mask (Gaussian Grouping eval_lerf_mask.py)", ("miou", "boundary_miou")),
    "3d-ovs": ("3d-ovs (3D-OVS renderer.py, closed set)", ("miou", "accuracy")),
    "goi-m360": ("goi-eval-seg m360 (GOI eval_seg.py)", ("miou", "mpa", "mp")),
    "replica-goi": ("goi-eval-seg replica_top7 (GOI eval_seg.py)", ("miou", "mpa", "mp")),
}


#: the protocols built on a continuous map, which also score goi's score maps
SCORE_MAP_BENCHMARKS = ("lerf-ovs", "3d-ovs")


def gt_bool(gt: np.ndarray) -> np.ndarray:
    """A ground truth as a binary mask: LERF-Mask's greys are in above 128, others are 0/1."""
    return gt > 128 if gt.dtype == np.uint8 else gt.astype(bool)


def _mean(values: list[float]) -> float:
    return float(np.mean(values)) if values else float("nan")


def goi_scores(scene: BenchmarkScene, predictions: dict[str, dict[str, np.ndarray]]) -> dict:
    """The paper's metrics as goi computes them: per query over its frames, then over queries."""
    per_query = []
    for q in scene.queries:
        s = [
            image_scores(predictions[q.id][f.camera.name], gt_bool(f.gts[q.id]))
            for f in scene.frames
            if q.id in f.gts
        ]
        if s:
            per_query.append(mean_scores(s))
    m = mean_scores(per_query) if per_query else Scores(np.nan, np.nan, np.nan)
    return {"miou": m.iou, "mpa": m.mpa, "mp": m.mp}


def protocol_scores(
    benchmark: str,
    scene: BenchmarkScene,
    predictions: dict[str, dict[str, np.ndarray]],
    score_maps: dict[str, dict[str, np.ndarray]] | None = None,
) -> tuple[dict, dict]:
    """(the scene's figures under the benchmark's protocol, per query and frame detail).
    `score_maps` ({query id: {camera: [H, W] float}}, lerf-ovs and 3d-ovs): the continuous
    maps, scored as well (the figures' *_score_map keys)."""
    detail: dict[str, dict[str, dict]] = {q.id: {} for q in scene.queries}

    def pred(qid: str, f: Frame, maps: dict | None = None) -> np.ndarray:
        p = (predictions if maps is None else maps)[qid][f.camera.name]
        if benchmark in ("lerf-ovs", "3d-ovs") and p.shape != f.gts[qid].shape[:2]:
            raise GoiError(
                f"{f.source}: a prediction of {p.shape[1]}x{p.shape[0]} for the "
                f"{f.gts[qid].shape[1]}x{f.gts[qid].shape[0]} ground truth of {qid!r}; the "
                f"{benchmark} protocol scores them at one size and resizes nothing"
            )
        return p

    if benchmark == "lerf-ovs":
        ious, goi_ious, hits, map_ious, map_hits = [], [], 0, [], 0
        for f in scene.frames:
            for qid, gt in f.gts.items():
                r = pred(qid, f).astype(np.float32)  # goi's mask as the relevancy map
                iou = binary_iou(lerf_ovs_mask(r).astype(bool), gt)
                hit = lerf_ovs_localised(r, f.boxes[qid])
                ious.append(iou)
                goi_ious.append(binary_iou(pred(qid, f), gt))
                hits += hit
                detail[qid][f.key] = {"iou": iou, "localised": hit, "goi_iou": goi_ious[-1]}
                if score_maps is not None:  # the continuous score map as the relevancy map
                    m = pred(qid, f, score_maps).astype(np.float32)
                    map_ious.append(binary_iou(lerf_ovs_mask(m).astype(bool), gt))
                    map_hit = lerf_ovs_localised(m, f.boxes[qid])
                    map_hits += map_hit
                    detail[qid][f.key].update(
                        {"iou_score_map": map_ious[-1], "localised_score_map": map_hit}
                    )
        pairs = sum(len(f.gts) for f in scene.frames)
        figures = {
            "miou": _mean(ious),
            "localisation_accuracy": hits / pairs if pairs else float("nan"),
            "goi_binary_miou": _mean(goi_ious),  # the raw mask, same (frame, category) pairs
        }
        if score_maps is not None:
            figures["miou_score_map"] = _mean(map_ious)
            figures["localisation_accuracy_score_map"] = map_hits / pairs if pairs else float("nan")
    elif benchmark == "lerf-mask":
        per_q_iou, per_q_biou = [], []
        for q in scene.queries:
            ious, bious = [], []
            for f in scene.frames:
                if q.id in f.gts:
                    p = pred(q.id, f).astype(np.uint8) * 255
                    iou, biou = lerf_mask_scores(p, f.gts[q.id])
                    ious.append(iou)
                    bious.append(biou)
                    detail[q.id][f.key] = {"iou": iou, "boundary_iou": biou}
            if ious:
                per_q_iou.append(_mean(ious))
                per_q_biou.append(_mean(bious))
        figures = {"miou": _mean(per_q_iou), "boundary_miou": _mean(per_q_biou)}
    elif benchmark == "3d-ovs":
        all_ious, accs, map_all, map_accs = [], [], [], []
        for f in scene.frames:
            ids = [q.id for q in scene.queries]  # sorted class order
            masks = np.stack([pred(i, f) for i in ids])  # [C, H, W]
            gt = np.stack([f.gts[i] for i in ids], axis=-1)  # [H, W, C]
            class_ious, acc = three_d_ovs_scores(closed_set(masks), gt)
            all_ious.append(class_ious)
            accs.append(acc)
            for i, qid in enumerate(ids):
                detail[qid][f.key] = {"iou": float(class_ious[i])}
            if score_maps is not None:  # the argmax over the classes' continuous maps
                maps = np.stack([pred(i, f, score_maps) for i in ids])  # [C, H, W]
                class_map, map_acc = three_d_ovs_scores(closed_set(maps), gt)
                map_all.append(class_map)
                map_accs.append(map_acc)
                for i, qid in enumerate(ids):
                    detail[qid][f.key]["iou_score_map"] = float(class_map[i])
        figures = {"miou": float(np.mean(all_ious)), "accuracy": _mean(accs)}
        if score_maps is not None:
            figures["miou_score_map"] = float(np.mean(map_all))
            figures["accuracy_score_map"] = _mean(map_accs)
    elif benchmark == "goi-m360":  # image -> prompt -> scene
        per_q: list[tuple[float, float, float]] = []
        for q in scene.queries:
            s = []
            for f in scene.frames:
                if q.id in f.gts:
                    s.append(goi_eval_seg_image(pred(q.id, f), f.gts[q.id]))
                    detail[q.id][f.key] = dict(zip(("iou", "mpa", "mp"), s[-1], strict=True))
            per_q.append(tuple(np.mean(s, axis=0)) if s else (np.nan,) * 3)  # type: ignore[arg-type]
        m = np.mean(per_q, axis=0)
        figures = {"miou": float(m[0]), "mpa": float(m[1]), "mp": float(m[2])}
    elif benchmark == "replica-goi":  # prompt -> image -> scene
        per_img = []
        for f in scene.frames:
            s = []
            for qid, gt in f.gts.items():
                s.append(goi_eval_seg_image(pred(qid, f), gt))
                detail[qid][f.key] = dict(zip(("iou", "mpa", "mp"), s[-1], strict=True))
            per_img.append(tuple(np.mean(s, axis=0)) if s else (np.nan,) * 3)
        m = np.mean(per_img, axis=0)
        figures = {"miou": float(m[0]), "mpa": float(m[1]), "mp": float(m[2])}
    else:
        raise ValueError(benchmark)
    return figures, detail


def json_figures(d: dict) -> dict:
    """NaN (the references' 0/0) as null, recursively; booleans and strings kept."""
    out: dict = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out[k] = json_figures(v)
        elif isinstance(v, bool | str) or v is None:
            out[k] = v
        else:
            out[k] = nanless(float(v))
    return out

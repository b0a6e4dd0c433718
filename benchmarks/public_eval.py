"""What a public benchmark adds to a query: the annotation reading and the metric, on a
synthetic scene written in each benchmark's exact layout (stages/testing/public_layouts.py),
against the same run's query time (the baseline).

Per benchmark (seconds, medians of `repeat` runs unless named otherwise):
  <b>_read_s           reading and matching the scene's annotations (2 frames, 3-5 queries)
  <b>_metric_s         the protocol's metric and goi's own on every (frame, query), one variant
                       (lerf-ovs, 3d-ovs: on the 0/1 masks and on the score maps)
  <b>_score_map_s      lerf-ovs, 3d-ovs: rendering the score maps of all queries on the frames
                       (one run, its `score_map_full` timing)
  <b>_query_s          baseline: goi's `full` answers of all queries on the frames (one run of
                       `goi eval --benchmark`, its `query_full` timing; fields fitted outside)
  <b>_added_ratio      (read + metric + score map) / query
Frames are 640x480 (3D-OVS: 1280x960 images scored at 1/8), 20k Gaussians.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from stages.evaluation.benchmarks.run import BENCHMARKS, load_bench_scene, run_benchmark
from stages.evaluation.benchmarks.scoring import (
    SCORE_MAP_BENCHMARKS,
    goi_scores,
    gt_bool,
    protocol_scores,
)
from stages.evaluation.pipeline import EvalParams, EvalRun
from stages.query.prompts import load_text_embeddings
from stages.testing.public_layouts import synthetic_benchmark

SIZE = {"3d-ovs": (1280, 960)}


def suite_public_eval(repeat: int, tmp: Path, median_s: Callable) -> dict[str, float]:
    out: dict[str, float] = {}
    for b in BENCHMARKS:
        root = tmp / f"public-{b}"
        s = synthetic_benchmark(root, b, n=20_000, size=SIZE.get(b, (640, 480)), stride=8)
        emb_path = s["embeddings"]
        emb = load_text_embeddings(emb_path)
        doc = run_benchmark(
            b,
            s["bench"],
            [f"toy={s['trained']}"],
            s["features"],
            s["res"],
            EvalParams(iterations=100, entries=32),
            EvalRun(root / "r.json", variants="full", text_embeddings=emb_path),
        ).report
        bench, _ = load_bench_scene(b, s["bench"], "toy", s["trained"], emb, emb_path)
        preds = {
            q.id: {f.camera.name: gt_bool(f.gts[q.id]) for f in bench.frames if q.id in f.gts}
            for q in bench.queries
        }

        maps = None
        if b in SCORE_MAP_BENCHMARKS:
            maps = {q: {c: m.astype(np.float32) for c, m in v.items()} for q, v in preds.items()}

        def metric(b=b, bench=bench, preds=preds, maps=maps) -> None:  # noqa: ANN001
            protocol_scores(b, bench, preds, maps)
            goi_scores(bench, preds)

        read = median_s(
            lambda b=b, s=s, emb=emb, path=emb_path: load_bench_scene(
                b, s["bench"], "toy", s["trained"], emb, path
            ),
            repeat,
        )
        met = median_s(metric, repeat)
        query = float(doc["timings_s"]["query_full"])
        maps_s = float(doc["timings_s"].get("score_map_full", 0.0))
        out[f"{b}_read_s"] = read
        out[f"{b}_metric_s"] = met
        if b in SCORE_MAP_BENCHMARKS:
            out[f"{b}_score_map_s"] = maps_s
        out[f"{b}_query_s"] = query
        out[f"{b}_added_ratio"] = (read + met + maps_s) / query if query else float(np.nan)
    return out

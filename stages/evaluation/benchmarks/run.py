"""`goi eval --benchmark NAME DIR --scene TRAINED ...`: a public benchmark's scenes answered by
goi's variants and scored by the benchmark's protocol and by goi's own metrics.

Per scene: the trained 3DGS PLY (INRIA `point_cloud/iteration_*/point_cloud.ply`) with the
benchmark scene's COLMAP cameras (DIR/<scene>/sparse/0, as LERF-OVS, LERF-Mask and 3D-OVS ship
them) or, where the benchmark has none (GOI's Mip-NeRF360 masks, Replica), the trained
directory's cameras. The annotations are read and matched to cameras first; every annotated
frame becomes a test camera at the ground truth's size; the field trains on every other view
the protocol allows (LERF-Mask holds its test views out). Then the stages `goi eval` runs
(features, codebook, fields, the variants' answers) and the scoring.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from schemas import current_version, validate_json
from stages import __version__
from stages.core.artifacts import check_writable, command_line, write_json
from stages.core.errors import GoiError, warn
from stages.core.files import refuse_inputs
from stages.core.params import check_params
from stages.core.report import SILENT, Report
from stages.core.staging import staged_outputs
from stages.evaluation.benchmarks import goi_m360, lerf_mask, lerf_ovs, replica_goi, three_d_ovs
from stages.evaluation.benchmarks.common import BenchmarkScene
from stages.evaluation.benchmarks.goi_m360 import read_goi_m360
from stages.evaluation.benchmarks.lerf_mask import read_lerf_mask
from stages.evaluation.benchmarks.lerf_ovs import read_lerf_ovs
from stages.evaluation.benchmarks.page import benchmark_page
from stages.evaluation.benchmarks.replica_goi import read_replica_goi
from stages.evaluation.benchmarks.scoring import (
    PROTOCOLS,
    SCORE_MAP_BENCHMARKS,
    goi_scores,
    gt_bool,
    json_figures,
    protocol_scores,
)
from stages.evaluation.benchmarks.three_d_ovs import read_three_d_ovs
from stages.evaluation.pipeline import (
    WORK_FILES,
    EvalParams,
    EvalResult,
    EvalRun,
    _check_entries,
    _check_work,
    _chosen_variants,
    _fit_models,
    _res_bundle,
    _Timer,
)
from stages.evaluation.report import overlay_pair, page_files_dir
from stages.evaluation.room import Prompt, Room
from stages.evaluation.variants import Answerers, Question, TfccModel
from stages.query.hyperplanes import HyperplaneRun
from stages.query.lift_math import LiftParams
from stages.query.osh import HyperplaneParams
from stages.query.prompts import load_text_embeddings
from stages.query.res import ResFiles, ResModel, ResSource
from stages.render.lift import score_map
from stages.scene.cameras import Camera
from stages.scene.formats import load_cameras
from stages.scene.scene import Scene, _find_ply, load_scene
from stages.semantics.extract import feature_files
from stages.semantics.feature_files import load_feature_file

Reader = Callable[[Path, str, list[Camera]], BenchmarkScene]
READERS: dict[str, Reader] = {
    "lerf-ovs": read_lerf_ovs,
    "lerf-mask": read_lerf_mask,
    "3d-ovs": read_three_d_ovs,
    "goi-m360": read_goi_m360,
    "replica-goi": read_replica_goi,
}
BENCHMARKS = tuple(READERS)
#: each benchmark's released scene names (a name outside them has no published figure)
SCENES: dict[str, tuple[str, ...]] = {
    "lerf-ovs": lerf_ovs.SCENES,
    "lerf-mask": lerf_mask.SCENES,
    "3d-ovs": three_d_ovs.SCENES,
    "goi-m360": goi_m360.SCENES,
    "replica-goi": replica_goi.SCENES,
}
#: the variant whose spread over --seeds is measured (the paper's method)
SEEDED = "full"


@dataclass
class BenchScene:
    """One scene of the run: its annotations, the goi scene with the frames as test views, and
    where its features and RES masks are."""

    bench: BenchmarkScene
    room: Room
    features: Path
    res: Path | None


def parse_seeds(text: str | None, seed: int) -> list[int]:
    """--seeds: 2 or 3 distinct seeds (comma-separated integers), [] when not asked for."""
    if text is None:
        return []
    try:
        seeds = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise GoiError(f"--seeds: {text!r} is not a comma-separated list of integers") from None
    if not 2 <= len(seeds) <= 3 or len(set(seeds)) != len(seeds):
        raise GoiError(f"--seeds: {text!r}; give 2 or 3 distinct seeds (e.g. {seed},{seed + 1})")
    if any(not 0 <= x < 2**31 for x in seeds):
        raise GoiError(f"--seeds: {text!r}; each seed is an integer from 0 to 2^31 - 1")
    return seeds


def parse_scenes(specs: list[str] | tuple[str, ...]) -> list[tuple[str, Path]]:
    """--scene NAME=DIR or DIR (the name is the directory's): the benchmark's scene names."""
    if not specs:
        raise GoiError("--scene: give the trained 3DGS scene (NAME=DIR, repeatable)")
    out: list[tuple[str, Path]] = []
    for s in specs:
        name, _, path = s.rpartition("=") if "=" in s else ("", "", s)
        p = Path(path)
        name = name or p.resolve().name
        if not name or "/" in name or name in (".", ".."):
            raise GoiError(f"--scene: {s!r}: give NAME=DIR, NAME being the benchmark's scene")
        if name in {n for n, _ in out}:
            raise GoiError(f"--scene: scene {name!r} given twice")
        if not p.is_dir():
            raise GoiError(f"--scene: {p} is not a directory (a trained 3DGS scene)")
        out.append((name, p))
    return out


def per_scene(root: Path | None, name: str, n_scenes: int, option: str) -> Path | None:
    """ROOT/<scene> when it is a directory, else ROOT itself (one scene only)."""
    if root is None:
        return None
    if (root / name).is_dir():
        return root / name
    if n_scenes > 1:
        raise GoiError(f"{option}: {root / name} is missing (several scenes: one folder each)")
    return root


def _cameras(bench_dir: Path, trained: Path) -> tuple[Path, list[Camera], list[Path]]:
    """The PLY and the cameras: the benchmark scene's COLMAP model when it ships one, else the
    trained directory's cameras (goi's usual rules)."""
    ply = _find_ply(trained)
    for sub in (bench_dir / "sparse" / "0", bench_dir / "sparse"):
        if (sub / "images.bin").is_file() or (sub / "images.txt").is_file():
            files = sorted(p for p in sub.iterdir() if p.name.startswith(("cameras", "images")))
            return ply, load_cameras(sub), files
    s = load_scene(trained)
    return s.ply_path, s.cameras, s.camera_files


def load_bench_scene(
    benchmark: str,
    root: Path,
    name: str,
    trained: Path,
    embeddings: dict[str, np.ndarray],
    emb_path: Path,
) -> tuple[BenchmarkScene, Room]:
    """The annotations read and matched, and a Room whose test views are the frames."""
    bench_dir = root / name
    ply, cams, files = _cameras(bench_dir, trained)
    bench = READERS[benchmark](root, name, cams)
    if not bench.frames:
        raise GoiError(f"{bench.dir}: no annotated frame has a camera; nothing to score")
    missing = [q.text for q in bench.queries if q.text not in embeddings]
    if missing:
        raise GoiError(
            f"{emb_path}: no text embedding for {', '.join(map(repr, missing[:3]))} "
            f"({len(missing)} of scene {name!r}'s queries)"
        )
    tests: dict[str, Camera] = {}
    for f in bench.frames:
        tests.setdefault(f.camera.name, f.camera)
    extra = [c for n, c in tests.items() if n not in {c.name for c in cams}]
    train = [c.name for c in cams if c.name not in bench.held_out]
    if not train:
        raise GoiError(f"{bench.dir}: every camera is a held-out test view; nothing to train on")
    images = bench_dir / "images"
    scene = Scene(ply, cams + extra, files, images if images.is_dir() else None, train, list(tests))
    prompts = [
        Prompt(q.id, q.text, [], [f.camera.name for f in bench.frames if q.id in f.gts], benchmark)
        for q in bench.queries
    ]
    return bench, Room(bench_dir, scene, prompts, embeddings, None, emb_path)


def run_benchmark(
    benchmark: str,
    root: Path,
    scene_specs: list[str] | tuple[str, ...],
    features: Path,
    res: Path | None,
    p: EvalParams,
    run: EvalRun,
    report: Report = SILENT,
) -> EvalResult:
    """Every scene read and checked, then fitted, answered and scored; report.json and the page."""
    check_params(p)
    if benchmark not in READERS:
        raise GoiError(f"--benchmark: {benchmark!r} is not one of {', '.join(BENCHMARKS)}")
    variants = _chosen_variants(run.variants)
    root = Path(root)
    if not root.is_dir():
        raise GoiError(f"{root}: not a directory (the benchmark's downloaded copy)")
    for option, path in (("--out", run.out), ("--html", run.html)):
        if path is not None:
            check_writable(Path(path), run.force, option)
    if run.text_embeddings is None:
        raise GoiError("--text-embeddings: required with --benchmark (JSON {query: [floats]})")
    if run.res_index is not None:
        raise GoiError(
            "--res-index: not used with --benchmark (a RES index belongs to one room's "
            "photos); give the benchmark's RES masks with --res-masks or a RES with --bundle"
        )
    seeds = parse_seeds(run.seeds, p.seed)
    specs = parse_scenes(scene_specs)
    for name, _ in specs:
        if name not in SCENES[benchmark]:
            warn(
                f"--scene {name}: not one of {benchmark}'s released scenes "
                f"({', '.join(SCENES[benchmark])}); no published figure is set beside it"
            )
    bundle = _res_bundle(res, run.bundle)
    emb_path = Path(run.text_embeddings)
    embeddings = load_text_embeddings(emb_path)
    timer = _Timer()
    scenes: list[BenchScene] = []
    for name, trained in specs:  # everything read and checked before any heavy work
        with timer("read_annotations"):
            bench, room = load_bench_scene(benchmark, root, name, trained, embeddings, emb_path)
        feats = per_scene(Path(features), name, len(specs), "--features")
        assert feats is not None
        files = feature_files(room.scene, feats, "train", "--features")
        first = next(iter(files.values()))
        dim, text_dim = load_feature_file(first).shape[0], next(iter(embeddings.values())).size
        if dim != text_dim:
            raise GoiError(
                f"{first}: the features have {dim} dimensions but the text embeddings "
                f"({emb_path}) {text_dim}; image and text features must share one space"
            )
        _check_entries(p, files)  # --entries against the cells k-means will sample
        n_train = len(room.scene.views("train"))
        if p.res_views is not None and p.res_views > n_train:
            raise GoiError(
                f"--res-views: {p.res_views} is more than scene {name!r}'s {n_train} training views"
            )
        scenes.append(
            BenchScene(bench, room, feats, per_scene(res, name, len(specs), "--res-masks"))
        )
    sources_of: list[dict[str, ResSource]] = []
    for s in scenes:
        if s.res is not None:
            sources_of.append({p.id: ResFiles(s.res, p.query) for p in s.room.prompts})
        else:
            sources_of.append({})
    work = Path(run.work or Path(run.out).with_suffix(".work"))
    # the --seeds fitted on their own (WORK/<scene>/seed-<s>/): all but the run's own seed
    # when its `full` is among the variants (that answer is reused)
    own_fits = [x for x in seeds if not (x == p.seed and SEEDED in variants)]
    inputs = [root, *(t for _, t in specs), features, res, emb_path, run.bundle]
    outputs = {
        "--out": run.out,
        "--html": [run.html, page_files_dir(run.html)] if run.html is not None else None,
        "--work": [
            work / s.bench.name / sub / f
            for s in scenes
            for sub in ["", *(f"seed-{x}" for x in own_fits)]
            for f in WORK_FILES
        ],
    }
    refuse_inputs(outputs, inputs)
    for s in scenes:  # every --work directory a fit may write, checked before the first fit
        _check_work(work / s.bench.name)
        for x in own_fits:
            _check_work(work / s.bench.name / f"seed-{x}")
    doc: dict = {
        "schema": "goi.eval",
        "schema_version": current_version("goi.eval"),
        "goi_version": __version__,
        "command": command_line(),
        "room": str(root),
        "threshold": p.threshold,
        "metric_notes": {
            "goi": "the paper's per-image IoU, mPA, mP as goi computes them "
            "(stages.evaluation.metrics): mean over a query's frames, then over queries",
            "protocol": PROTOCOLS[benchmark][0],
            "how_goi_enters": _HOW[benchmark],
            "mean": "the mean over scenes of each scene's figure",
            "full_noise": "full's figures move with its fit's seed and with numerical noise (on "
            "the dev room a refit from cameras moved by 2e-7 moved LERF-Mask mIoU by -0.033 and "
            "one prompt from 0.66 to 0.18, lifted under 0.008 on every prompt): "
            + ("benchmark.seeds gives their spread" if seeds else "--seeds gives their spread"),
        },
        "variants": {v: {"prompts": {}} for v in variants},
        "benchmark": {"name": benchmark, "protocol": PROTOCOLS[benchmark][0], "scenes": {}},
        "timings_s": timer.t,
    }
    thumbs: dict[tuple[str, str], dict[str, tuple[str, np.ndarray]]] = {}
    for s, sources in zip(scenes, sources_of, strict=True):
        name = s.bench.name
        report.log(
            f"eval: {benchmark} scene {name} ({len(s.bench.frames)} frames, "
            f"{len(s.bench.queries)} queries"
            + (f"; test_mask/ holds {s.bench.layout}" if s.bench.layout else "")
            + ")"
        )
        wdir = work / name
        tfcc, direct = _fit_models(s.room, s.features, wdir, variants, p, timer, report)
        models = Answerers.of(s.room.scene, tfcc, direct)
        if bundle is not None:
            sources = {q.id: ResModel(bundle, q.text, models.rast) for q in s.bench.queries}
        entry: dict = {
            "n_frames": len(s.bench.frames),
            "n_queries": len(s.bench.queries),
            "skipped": s.bench.skipped,
            **({"layout": s.bench.layout} if s.bench.layout else {}),
            "frames": {f.key: f.camera.name for f in s.bench.frames},
            "variants": {},
        }
        for variant in variants:
            entry["variants"][variant], preds = _answer(
                benchmark, s, models, sources, variant, wdir, p, timer, report
            )
            if run.html is not None:
                thumbs[(name, variant)] = thumbnails(s.bench, preds, tfcc)
        if seeds:
            runs = {}
            for seed in seeds:
                if seed not in own_fits:
                    runs[seed] = entry["variants"][SEEDED]
                    continue
                sp = replace(p, seed=seed)
                sdir = wdir / f"seed-{seed}"
                report.log(f"eval: {name}: {SEEDED} with seed {seed} (--seeds)")
                tf, _ = _fit_models(s.room, s.features, sdir, [SEEDED], sp, timer, report)
                m = Answerers.of(s.room.scene, tf, None)
                runs[seed], _ = _answer(benchmark, s, m, sources, SEEDED, sdir, sp, timer, report)
            entry["seeds"] = seed_spread(runs)
        doc["benchmark"]["scenes"][name] = entry
    if seeds:
        doc["benchmark"]["seeds"] = {
            "seeds": seeds,
            "variant": SEEDED,
            "what": "the codebook's, field's and hyperplanes' seed; per seed the figures of "
            f"{SEEDED}, and over the seeds their min, max, range (max - min) and sample sd",
            "mean": mean_spread([e["seeds"] for e in doc["benchmark"]["scenes"].values()]),
        }
    _means(doc, variants)
    with staged_outputs():
        if run.html is not None:
            with timer("html"):
                benchmark_page(Path(run.html), doc, scenes_of(scenes), thumbs)
        validate_json(doc, "goi.eval", str(run.out))
        write_json(run.out, doc, force=True)
    return EvalResult(doc, Path(run.out), run.html)


def _answer(
    benchmark: str,
    s: BenchScene,
    models: Answerers,
    sources: dict[str, ResSource],
    variant: str,
    wdir: Path,
    p: EvalParams,
    timer: _Timer,
    report: Report,
) -> tuple[dict, dict[str, dict[str, np.ndarray]]]:
    """One variant's answers to every query of a scene, scored: (its figures, its masks)."""
    train = s.room.scene.views("train")
    hp = HyperplaneParams(threshold=p.threshold)
    planes = HyperplaneRun(wdir / "hyperplanes.h5", refit=True)
    lp = LiftParams(lift=True, res_views=p.res_views, min_evidence=p.min_evidence, clean=p.clean)
    preds: dict[str, dict[str, np.ndarray]] = {}
    scores: dict[str, np.ndarray] = {}  # query id -> [G] the answer's scores
    maps: dict[str, dict[str, np.ndarray]] | None = None
    for prompt in report.progress(s.room.prompts, f"{s.bench.name} {variant}", show=_pid):
        text = s.room.embeddings[prompt.text]
        t0 = time.perf_counter()
        q = Question(
            prompt.query, text, sources[prompt.id], prompt.test_views, train, hp, lp, planes, p.seed
        )
        pred = models.predict(variant, q)
        timer.add(f"query_{variant}", time.perf_counter() - t0)
        preds[prompt.id] = pred.masks
        if pred.scores is not None:
            scores[prompt.id] = pred.scores
    if benchmark in SCORE_MAP_BENCHMARKS and len(scores) == len(preds):
        with timer(f"score_map_{variant}"):
            maps = frame_score_maps(models, s.room.prompts, scores)
    with timer("metrics"):
        proto, detail = protocol_scores(benchmark, s.bench, preds, maps)
        own = goi_scores(s.bench, preds)
    return json_figures({"protocol": proto, "goi": own, "queries": detail}), preds


def _spread(values: list[float | None]) -> dict:
    """{values, min, max, range, sd} of one figure over the seeds (None where a seed's is)."""
    xs = [x for x in values if x is not None]
    whole = len(xs) == len(values) and len(xs) > 1
    return {
        "values": values,
        "min": min(xs) if whole else None,
        "max": max(xs) if whole else None,
        "range": max(xs) - min(xs) if whole else None,
        "sd": float(np.std(xs, ddof=1)) if whole else None,
    }


def _query_iou(figs: dict, qid: str) -> float | None:
    ious = [d.get("iou") for d in figs["queries"].get(qid, {}).values()]
    ious = [x for x in ious if x is not None]
    return float(np.mean(ious)) if ious else None


def seed_spread(runs: dict[int, dict]) -> dict:
    """A scene's figures of one variant per seed ({seed: figures}) -> the spread of each
    protocol figure, of goi's mIoU, and of each query's IoU (protocol, mean over its frames),
    the widest query first."""
    seeds = list(runs)
    first = runs[seeds[0]]
    out: dict = {
        "protocol": {
            k: _spread([runs[x]["protocol"][k] for x in seeds]) for k in first["protocol"]
        },
        "goi_miou": _spread([runs[x]["goi"]["miou"] for x in seeds]),
    }
    queries = {q: _spread([_query_iou(runs[x], q) for x in seeds]) for q in first["queries"]}
    out["queries"] = dict(sorted(queries.items(), key=lambda kv: -(kv[1]["range"] or 0.0)))
    return out


def mean_spread(per_scene: list[dict]) -> dict:
    """The spread of the mean over scenes: per seed the mean of the scenes' figures."""

    def mean_of(values: list[list[float | None]]) -> list[float | None]:
        return [
            None if any(v is None for v in col) else float(np.mean(col))  # type: ignore[arg-type]
            for col in zip(*values, strict=True)
        ]

    keys = per_scene[0]["protocol"].keys()
    return {
        "protocol": {
            k: _spread(mean_of([sc["protocol"][k]["values"] for sc in per_scene])) for k in keys
        },
        "goi_miou": _spread(mean_of([sc["goi_miou"]["values"] for sc in per_scene])),
    }


def frame_score_maps(
    models: Answerers, prompts: list[Prompt], scores: dict[str, np.ndarray]
) -> dict[str, dict[str, np.ndarray]]:
    """{query id: {frame: [H, W] float32}}: the queries' per-Gaussian scores rendered as
    continuous maps, all the queries of a frame in one tile walk ([G, K] channels)."""
    out: dict[str, dict[str, np.ndarray]] = {q: {} for q in scores}
    frames: dict[str, list[str]] = {}
    for p in prompts:
        if p.id in scores:
            for v in p.test_views:
                frames.setdefault(v, []).append(p.id)
    for v, ids in frames.items():
        cam = models.cams[v]
        proj, bins = models.rast.prepare(cam)
        stack = np.stack([scores[q] for q in ids], axis=1)  # [G, K]
        img = score_map(proj, bins, stack, cam.width, cam.height)  # [H, W, K]
        for k, q in enumerate(ids):
            out[q][v] = np.ascontiguousarray(img[:, :, k])
    return out


def thumbnails(
    bench: BenchmarkScene, preds: dict[str, dict[str, np.ndarray]], tfcc: TfccModel | None
) -> dict[str, tuple[str, np.ndarray]]:
    """For the page: each query's first frame, its prediction (red) on goi's rendering against
    the ground truth (green outline), at most THUMB px wide ({query id: (frame, [h, w, 3])});
    small, so that a benchmark's many frames are not held in memory."""
    import cv2

    out = {}
    for q in bench.queries:
        f = next((f for f in bench.frames if q.id in f.gts), None)
        if f is None:
            continue
        cam = f.camera
        view = tfcc.views.get(cam.name) if tfcc is not None else None
        rgb = view.rgb if view is not None and view.rgb is not None else None
        if rgb is None:
            rgb = np.full((cam.height, cam.width, 3), 0.2, np.float32)
        img = overlay_pair(rgb, preds[q.id][cam.name], gt_bool(f.gts[q.id]))
        if img.shape[1] > THUMB:
            h = max(1, round(img.shape[0] * THUMB / img.shape[1]))
            img = cv2.resize(img, (THUMB, h), interpolation=cv2.INTER_AREA)
        out[q.id] = (f.key, img)
    return out


#: the page's figures' width in pixels
THUMB = 320


def scenes_of(scenes: list[BenchScene]) -> dict[str, BenchmarkScene]:
    return {s.bench.name: s.bench for s in scenes}


def _means(doc: dict, variants: list[str]) -> None:
    """variants[v]: the mean over scenes of each protocol and goi figure (null when a scene's
    figure is null: NaN propagates, as the references' np.mean does)."""
    scenes = doc["benchmark"]["scenes"].values()
    for v in variants:
        out: dict = {"prompts": {}}
        for part in ("protocol", "goi"):
            keys = next(iter(scenes))["variants"][v][part].keys()
            vals = {k: [s["variants"][v][part][k] for s in scenes] for k in keys}
            out[part] = {
                k: None if any(x is None for x in xs) else float(np.mean(xs))
                for k, xs in vals.items()
            }
        out.update({k: out["goi"][k] for k in ("miou", "mpa", "mp")})  # the room report's keys
        doc["variants"][v] = out


def _pid(p: Prompt | None) -> str | None:
    return p.id if p else None


_HOW = {
    "lerf-ovs": "two relevancy maps, one level each: miou / localisation_accuracy take goi's "
    "rendered 0/1 mask, miou_score_map / localisation_accuracy_score_map the continuous "
    "score map (each Gaussian's score, the plane's probability s(W x + b) or the lifted "
    "vote's share, composited by the rasteriser: sum of blend weight x score); the "
    "protocol's filter, normalisation, 0.4 threshold and 7x7 majority filter run on each, "
    "and localisation takes its 30x30 mean's maxima; goi_binary_miou is the raw mask's IoU "
    "on the same pairs",
    "lerf-mask": "goi's binary mask, as 0/255",
    "3d-ovs": "miou / accuracy: the per-pixel argmax over the classes' 0/1 masks (sorted "
    "class order; a pixel claimed by none or several goes to the first of them); "
    "miou_score_map / accuracy_score_map: the argmax over the classes' continuous score "
    "maps (each Gaussian's score composited by the rasteriser; ties to the first class)",
    "goi-m360": "goi's binary mask, rendered at the ground truth's size",
    "replica-goi": "goi's binary mask, rendered at the ground truth's size",
}

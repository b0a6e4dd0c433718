"""`goi eval`: the whole pipeline on a benchmark room, scored as the paper scores it.

A room (layout: ../shared/dev-room/README.md) has cameras with a train/test split, a PLY,
prompts.json, eval/masks/<prompt id>/<test view>.png and gaussian_ids.npy. The features and RES
masks come from any directories (the room's simulated ones, or a real model's). Every stage is
the function the other commands use; the field never sees a test view.

Variants (the paper's ablation table):
  full          TFCC field + hyperplane fitted on the RES masks
  without_osh   TFCC field + the fixed cosine threshold
  without_tfcc  field decoded straight to the feature space (no codebook) + hyperplane
  baseline      field decoded straight to the feature space + the fixed threshold
The fixed threshold is goi's one documented default (stages.hyperplane.THRESHOLD) for every
prompt and room; it is never tuned on test masks.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stages import __version__
from stages.artifacts import command_line, read_json, write_json
from stages.cameras import Camera
from stages.codebook import CodebookOptions, init_codebook
from stages.errors import GoiError
from stages.extract import ExtractOptions, import_features
from stages.field import Field, FieldOptions, fit_field, load_field
from stages.hyperplane import (
    THRESHOLD,
    Counts,
    HyperplaneOptions,
    ResFiles,
    choose_views,
    fit_hyperplane,
    fit_osh,
    threshold_plane,
)
from stages.masks import mask_of
from stages.metrics import Scores, image_scores, iou_3d, mean_scores
from stages.progress import progress
from stages.prompts import load_text_embeddings
from stages.scene import Scene, load_scene, read_mask
from stages.selection import select
from stages.semantic_render import COVERED_ALPHA, SemanticRenderer

VARIANTS = ("full", "without_osh", "without_tfcc", "baseline")
#: Pixels per fitting view the per-pixel (without-TFCC) hyperplane is fitted on.
DIRECT_FIT_PIXELS = 20_000


@dataclass
class EvalOptions:
    out: Path
    """report.json to write (schema goi.eval)."""
    html: Path | None = None
    """Also write an HTML report (overlays per prompt and view, metrics, timings)."""
    work: Path | None = None
    """Directory for the intermediate artifacts (default: <out without .json>.work)."""
    text_embeddings: Path | None = None
    """Prompt embeddings JSON (default: the room's text_embeddings.json)."""
    iterations: int = 1500
    """fit-field iterations for each field (paper: 1500)."""
    entries: int = 300
    """Codebook entries (paper: 300)."""
    threshold: float = THRESHOLD
    """The fixed cosine threshold (goi's default; not to be tuned on test masks)."""
    variants: str = ",".join(VARIANTS)
    """Comma-separated variants to run."""
    seed: int = 0
    """Random seed of every stage."""
    force: bool = False
    """Overwrite existing report files."""


@dataclass
class Prompt:
    id: str
    text: str
    targets: list[int]
    test_views: list[str]
    kind: str


def load_prompts(room: Path) -> list[Prompt]:
    path = room / "prompts.json"
    raw = read_json(path, "missing; a room lists its prompts there")
    if not isinstance(raw, list) or not raw:
        raise GoiError(f"{path}: expected a non-empty list of prompts")
    out = []
    for i, p in enumerate(raw):
        try:
            out.append(
                Prompt(
                    str(p["id"]),
                    str(p["text"]),
                    [int(t) for t in p["targets"]],
                    [str(v) for v in p.get("test_views", [])],
                    str(p.get("kind", "")),
                )
            )
        except (KeyError, TypeError, ValueError) as e:
            raise GoiError(f"{path}: prompt {i} lacks a valid field ({e})") from None
    return out


class _Timer:
    def __init__(self) -> None:
        self.t: dict[str, float] = {}

    @contextmanager
    def __call__(self, stage: str):  # noqa: ANN204
        t0 = time.perf_counter()
        yield
        self.t[stage] = round(self.t.get(stage, 0.0) + time.perf_counter() - t0, 2)


@dataclass
class DirectView:
    """A test or fitting view of a --no-tfcc field: rendered features, decoded per prompt."""

    f_hat: np.ndarray  # [M, S] covered pixels only
    covered: np.ndarray  # [H, W] bool

    def scores(self, field: Field, W: np.ndarray, b: float) -> np.ndarray:
        """[H, W] W x + b of each covered pixel's decoded feature (-inf elsewhere)."""
        out = np.full(self.covered.shape, -np.inf, np.float32)
        out[self.covered] = field.decode_direct(self.f_hat) @ W.astype(np.float32) + b
        return out


def render_direct(renderer: SemanticRenderer, cam: Camera) -> DirectView:
    r = renderer.rast.render_features(cam, renderer.field.features)
    covered = r.alpha > COVERED_ALPHA
    return DirectView(r.image[covered], covered)


def fit_direct_plane(
    renderer: SemanticRenderer,
    chosen: list[tuple[Camera, np.ndarray]],
    text: np.ndarray,
    o: HyperplaneOptions,
    seed: int,
) -> tuple[np.ndarray, float, dict]:
    """The OSH on a field without codebook: every sampled pixel is its own point."""
    rng = np.random.default_rng(seed)
    xs, ys = [], []
    for cam, m in chosen:
        v = render_direct(renderer, cam)
        y = m[v.covered]
        take = rng.permutation(len(y))[:DIRECT_FIT_PIXELS]
        xs.append(renderer.field.decode_direct(v.f_hat[take]))
        ys.append(y[take])
    x, y = np.concatenate(xs), np.concatenate(ys)
    return fit_osh(Counts(y.astype(np.float64), (~y).astype(np.float64)), x, text, o)


def _contribution(scene: Scene) -> np.ndarray:
    """[G] each Gaussian's blending weight summed over the training views."""
    from stages.rasterizer import Rasterizer

    rast = Rasterizer.from_gaussians(scene.gaussians)
    return sum(
        (rast.contribution(c) for c in scene.views("train")), np.zeros(scene.gaussians.count)
    )


def run_eval(
    room: Path, features: Path, res: Path, o: EvalOptions, say: Callable[[str], None] = print
) -> dict:
    """Run every variant on the room and write report.json (and the HTML page)."""
    variants = [v.strip() for v in o.variants.split(",") if v.strip()]
    bad = [v for v in variants if v not in VARIANTS]
    if bad or not variants:
        raise GoiError(
            f"--variants: {', '.join(bad) or '(none)'}; choose from {', '.join(VARIANTS)}"
        )
    room, res = Path(room), Path(res)
    for path, force in ((o.out, o.force), (o.html, o.force)):
        if path is not None and Path(path).exists() and not force:
            raise GoiError(f"{path}: already exists; pass --force to overwrite it")
    scene = load_scene(room)
    prompts = load_prompts(room)
    emb = load_text_embeddings(o.text_embeddings or room / "text_embeddings.json")
    missing = [p.text for p in prompts if p.text not in emb]
    if missing:
        raise GoiError(f"no text embedding for prompt(s) {', '.join(map(repr, missing[:3]))}")
    ids_path = room / "gaussian_ids.npy"
    gaussian_ids = np.load(ids_path, allow_pickle=False) if ids_path.is_file() else None
    if gaussian_ids is not None and gaussian_ids.shape != (scene.gaussians.count,):
        raise GoiError(
            f"{ids_path}: {gaussian_ids.shape} ids for {scene.gaussians.count} Gaussians"
        )
    work = Path(o.work or Path(o.out).with_suffix(".work"))
    work.mkdir(parents=True, exist_ok=True)
    timer = _Timer()

    say(f"eval: room {room} ({scene.gaussians.count} Gaussians, {len(prompts)} prompts)")
    with timer("extract"):
        feats = import_features(scene, features, ExtractOptions(work / "features.h5", force=True))
    with timer("init_codebook"):
        cb = init_codebook(
            feats, CodebookOptions(work / "codebook.h5", entries=o.entries, seed=o.seed, force=True)
        )
    fields: dict[str, Field] = {}
    paths: dict[str, Path] = {}
    need = {"tfcc": {"full", "without_osh"}, "direct": {"without_tfcc", "baseline"}}
    for kind, users in need.items():
        if not users & set(variants):
            continue
        fo = FieldOptions(
            work / f"field_{kind}.h5",
            cache=work / "blend_cache.h5",
            iterations=o.iterations,
            no_tfcc=kind == "direct",
            seed=o.seed,
            checkpoint_every=0,
            force=True,
        )
        say(f"eval: fit-field ({kind}, {o.iterations} iterations)")
        with timer(f"fit_field_{kind}"):
            paths[kind] = fit_field(scene, feats, cb, fo)
        fields[kind] = load_field(paths[kind])

    with timer("contribution_3d"):
        weight = _contribution(scene) if gaussian_ids is not None else None
    test = {c.name: c for c in scene.views("test")}
    renderers = {k: SemanticRenderer(scene.gaussians, f) for k, f in fields.items()}
    with timer("render_test_views"):
        tfcc_views = (
            {n: renderers["tfcc"].render(c, with_rgb=True) for n, c in test.items()}
            if "tfcc" in renderers
            else {}
        )
        direct_views = (
            {n: render_direct(renderers["direct"], c) for n, c in test.items()}
            if "direct" in renderers
            else {}
        )
    hp = HyperplaneOptions(out=work / "hyperplanes.h5", threshold=o.threshold, refit=True)
    report: dict = {
        "schema": "goi.eval",
        "schema_version": "1.0",
        "goi_version": __version__,
        "command": command_line(),
        "room": str(room),
        "threshold": o.threshold,
        "metric_notes": {
            "2d": "per test image IoU, mPA, mP; mean over a prompt's images, then over prompts",
            "miou_3d": "IoU of selected vs target Gaussians, each Gaussian counted once",
            "miou_3d_visible": "the same, each Gaussian weighted by its blending weight summed "
            "over the training views (hidden Gaussians count for nothing)",
        },
        "variants": {v: {"prompts": {}} for v in variants},
        "timings_s": timer.t,
    }
    figures: dict[str, dict[str, list]] = {v: {} for v in variants}
    train = scene.views("train")
    if "direct" in fields:  # every prompt scores the same decoded Gaussians
        direct_gaussians = fields["direct"].decode_direct(fields["direct"].features)  # [G, D]
    for p in progress(prompts, "eval prompts", show=lambda p: p.id if p else None):
        text = emb[p.text]
        source = ResFiles(res, p.id, p.text)
        views = [v for v in p.test_views if v in test]
        gts = {v: read_mask(room / "eval" / "masks" / p.id / f"{v}.png") for v in views}
        target = None if gaussian_ids is None else np.isin(gaussian_ids, p.targets)
        for variant in variants:
            t0 = time.perf_counter()
            info: dict = {}
            if variant in ("full", "without_osh"):
                field, renderer = fields["tfcc"], renderers["tfcc"]
                if variant == "full":
                    plane, _ = fit_hyperplane(
                        renderer, paths["tfcc"], train, p.text, text, "eval", source, hp
                    )
                    info = {k: plane.info[k] for k in ("res_iou_init", "res_iou", "steps_run")}
                    info["fit_views"] = json.loads(plane.info["views"])
                else:
                    plane = threshold_plane(p.text, text, field, o.threshold)
                preds = {v: mask_of(plane, tfcc_views[v]) for v in views}
                sel = select(field, plane)
            else:
                field, renderer = fields["direct"], renderers["direct"]
                W, b = text.astype(np.float64), -o.threshold
                if variant == "without_tfcc":
                    chosen = choose_views(source, train, hp)
                    W, b, rec = fit_direct_plane(renderer, chosen, text, hp, o.seed)
                    info = {k: rec[k] for k in ("res_iou_init", "res_iou", "steps_run")}
                    info["fit_views"] = [c.name for c, _ in chosen]
                preds = {v: direct_views[v].scores(field, W, b) > 0 for v in views}
                sel = field.seen & (direct_gaussians @ W.astype(np.float32) + b > 0)
            scores = {v: image_scores(preds[v], gts[v]) for v in views}
            entry: dict = {
                "text": p.text,
                "kind": p.kind,
                "n_test_views": len(views),
                **(mean_scores(list(scores.values())).as_dict() if views else {}),
                "views": {v: s.as_dict() for v, s in scores.items()},
                "n_selected": int(sel.sum()),
                "seconds": round(time.perf_counter() - t0, 3),
                **info,
            }
            if target is not None:
                entry["iou_3d"] = iou_3d(sel, target)
                entry["iou_3d_visible"] = iou_3d(sel, target, weight)
            report["variants"][variant]["prompts"][p.id] = entry
            timer.t[f"query_{variant}"] = round(
                timer.t.get(f"query_{variant}", 0) + entry["seconds"], 2
            )
            figures[variant][p.id] = [preds, gts]
    for variant in variants:
        ps = report["variants"][variant]["prompts"].values()
        scored = [e for e in ps if e["n_test_views"]]  # a prompt with no test view: listed only
        agg = mean_scores([Scores(e["iou"], e["mpa"], e["mp"]) for e in scored]) if scored else None
        summary = report["variants"][variant]
        summary.update(
            {
                "miou": agg.iou if agg else None,
                "mpa": agg.mpa if agg else None,
                "mp": agg.mp if agg else None,
            }
        )
        if gaussian_ids is not None:
            summary["miou_3d"] = float(np.mean([e["iou_3d"] for e in ps]))
            summary["miou_3d_visible"] = float(np.mean([e["iou_3d_visible"] for e in ps]))
        summary["prompts"] = summary.pop("prompts")
    from schemas import validate_json

    if o.html is not None:
        from stages.report import eval_page

        with timer("html"):  # report["timings_s"] is timer.t: the page's own time lands too
            eval_page(Path(o.html), report, prompts, figures, tfcc_views, room, scene)
    validate_json(report, "goi.eval", str(o.out))  # what we write, our reader must accept
    write_json(o.out, report, force=True)
    return report

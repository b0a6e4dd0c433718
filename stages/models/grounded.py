"""Grounded-SAM as a bundle's RES: an open-set box detector prompted with the text, then SAM
prompted with its boxes (docs/models.md).

Per image: the detector (Grounding DINO, `detector.onnx`) scores its queries against the
prompt's tokens; the boxes scoring above `box_threshold`, best first and at most `max_boxes`,
go to SAM: its encoder (`sam_encoder.onnx`) embeds the image once, its decoder
(`sam_decoder.onnx`) gives one mask per box, and the union of the masks is the image's RES
mask. An image where the detector finds nothing gets an empty mask (SAM does not run). The
pre- and post-processing is `res_processing`'s, the transformers processors' own arithmetic.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from stages.core.errors import GoiError
from stages.models import res_processing as rp
from stages.models.onnx_io import Tokens, check_inputs_named, check_io, inside, session

#: The models of a grounded pipeline, as manifest keys.
PARTS = ("detector", "sam_encoder", "sam_decoder")


@dataclass
class Grounding:
    """What the pipeline found on one image."""

    mask: np.ndarray  # [H, W] bool, the union of the boxes' masks
    boxes: np.ndarray  # [K, 4] x0, y0, x1, y1 in pixels, best first
    scores: np.ndarray  # [K]


def _size(spec: dict, key: str, where: str) -> tuple[int, int]:
    """A manifest [width, height] -> (height, width)."""
    v = spec["size"]
    if len(v) != 2 or not all(isinstance(x, int) and not isinstance(x, bool) for x in v):
        raise GoiError(f"{where}: field '{key}.size' needs [width, height] as two integers")
    if min(v) < 16:
        raise GoiError(f"{where}: field '{key}.size' {v} is below 16 pixels")
    return int(v[1]), int(v[0])


def _stats(spec: dict, key: str, where: str) -> None:
    for stat in ("mean", "std"):
        v = spec[stat]
        if len(v) != 3 or not all(isinstance(x, int | float) for x in v):
            raise GoiError(f"{where}: field '{key}.{stat}' needs 3 numbers")
    if not all(s > 0 for s in spec["std"]):
        raise GoiError(f"{where}: field '{key}.std' needs positive numbers")


def check_spec(root: Path, spec: dict, where: str) -> None:
    """The manifest's 'grounded' section makes sense and names files that are there (no
    model is loaded)."""
    for part in PARTS:
        inside(root, spec[part]["file"], f"{where}: grounded.{part}")
    det, enc = spec["detector"], spec["sam_encoder"]
    _size(det, "grounded.detector", where)
    h, w = _size(enc, "grounded.sam_encoder", where)
    if h != w:
        raise GoiError(f"{where}: field 'grounded.sam_encoder.size' must be square, not {[w, h]}")
    _stats(det, "grounded.detector", where)
    _stats(enc, "grounded.sam_encoder", where)
    tok = det["tokenizer"]
    if tok["kind"] != "huggingface":
        raise GoiError(f"{where}: tokenizer kind {tok['kind']!r} is not supported (huggingface)")
    inside(root, tok["file"], f"{where}: grounded.detector.tokenizer")
    for key, lo, hi in (("box_threshold", 0, 1), ("mask_threshold", -math.inf, math.inf)):
        v = float(spec[key])
        if not (math.isfinite(v) and lo <= v <= hi):
            raise GoiError(f"{where}: field 'grounded.{key}' is {v}, not a number in [{lo}, {hi}]")
    if spec["max_boxes"] < 1:
        raise GoiError(f"{where}: field 'grounded.max_boxes' must be at least 1")


class GroundedSam:
    """The grounded pipeline of a bundle. The three models are opened, and every tensor the
    manifest names is checked, on the first image, before any of them runs."""

    def __init__(self, root: Path, spec: dict, where: str):
        self.root = root
        self.spec = spec
        self.where = where
        self.canvas = _size(spec["detector"], "grounded.detector", where)
        self.sam_size = _size(spec["sam_encoder"], "grounded.sam_encoder", where)[0]

    @cached_property
    def _models(self) -> tuple[Any, Any, Any, Tokens]:
        det, enc, dec = (self.spec[p] for p in PARTS)
        paths = [
            inside(self.root, s["file"], f"{self.where}: grounded.{p}")
            for p, s in zip(PARTS, (det, enc, dec), strict=True)
        ]
        tok = det["tokenizer"]
        where = f"{self.where}: grounded.detector.tokenizer"
        tokens = Tokens(inside(self.root, tok["file"], where), int(tok["max_length"]), where)
        d = session(paths[0], low_memory=True)
        ch, cw = self.canvas
        check_io(d, paths[0], "input", det["pixel_values"], 4, {0: 1, 1: 3, 2: ch, 3: cw})
        check_io(d, paths[0], "input", det["pixel_mask"], 3, {0: 1, 1: ch, 2: cw})
        text = [det["input_ids"], det["attention_mask"]]
        text += [det["token_type_ids"]] if det.get("token_type_ids") else []
        for name in text:
            check_io(d, paths[0], "input", name, 2, {0: 1})
        check_inputs_named(d, paths[0], [det["pixel_values"], det["pixel_mask"], *text])
        check_io(d, paths[0], "output", det["logits"], 3, {0: 1})
        check_io(d, paths[0], "output", det["boxes"], 3, {0: 1, 2: 4})
        s = self.sam_size
        e = session(paths[1], low_memory=True)
        check_io(e, paths[1], "input", enc["input"], 4, {0: 1, 1: 3, 2: s, 3: s})
        emb = check_io(e, paths[1], "output", enc["output"], 4, {0: 1})
        m = session(paths[2])
        fixed = {i: v for i, v in enumerate(emb) if isinstance(v, int)}
        check_io(m, paths[2], "input", dec["image_embeddings"], 4, fixed)
        check_io(m, paths[2], "input", dec["boxes"], 3, {0: 1, 2: 4})
        check_inputs_named(m, paths[2], [dec["image_embeddings"], dec["boxes"]])
        check_io(m, paths[2], "output", dec["masks"], 5, {0: 1, 2: 1})
        return d, e, m, tokens

    def check(self) -> None:
        """Open the models and check their tensors (done anyway on the first image)."""
        _ = self._models

    def detect(self, rgb: np.ndarray, prompt: str) -> tuple[np.ndarray, np.ndarray]:
        """The kept boxes [K, 4] (pixels of `rgb`) and their scores [K], best first."""
        d, _, _, tokens = self._models
        det = self.spec["detector"]
        ids, att = tokens.encode(rp.detector_caption(prompt))
        pixels, pmask = rp.detector_inputs(rgb, self.canvas, tuple(det["mean"]), tuple(det["std"]))
        feed = {
            det["pixel_values"]: pixels,
            det["pixel_mask"]: pmask,
            det["input_ids"]: ids,
            det["attention_mask"]: att,
        }
        if det.get("token_type_ids"):
            feed[det["token_type_ids"]] = np.zeros_like(ids)
        logits, boxes = d.run([det["logits"], det["boxes"]], feed)
        if logits.shape[-1] != ids.shape[1] or boxes.shape[:2] != logits.shape[:2]:
            raise GoiError(
                f"{self.root / det['file']}: returned logits {list(logits.shape)} and boxes "
                f"{list(boxes.shape)} for {ids.shape[1]} tokens; expected [1, Q, "
                f"{ids.shape[1]}] and [1, Q, 4]"
            )
        thr, k = float(self.spec["box_threshold"]), int(self.spec["max_boxes"])
        return rp.detections(logits[0], boxes[0], rgb.shape[:2], thr, k)

    def run(self, rgb: np.ndarray, prompt: str) -> Grounding:
        """[H, W, 3] uint8 RGB and a prompt -> the RES mask and the boxes it came from."""
        boxes, scores = self.detect(rgb, prompt)
        hw = (int(rgb.shape[0]), int(rgb.shape[1]))
        mask = np.zeros(hw, bool)
        if len(boxes) == 0:
            return Grounding(mask, boxes, scores)
        _, e, m, _ = self._models
        enc, dec = self.spec["sam_encoder"], self.spec["sam_decoder"]
        pixels = rp.sam_inputs(rgb, self.sam_size, tuple(enc["mean"]), tuple(enc["std"]))
        emb = e.run([enc["output"]], {enc["input"]: pixels})[0]
        thr = float(self.spec["mask_threshold"])
        for box in boxes:
            feed = {
                dec["image_embeddings"]: emb,
                dec["boxes"]: rp.sam_boxes(box[None], hw, self.sam_size),
            }
            low = m.run([dec["masks"]], feed)[0]  # [1, 1, 1, s, s] mask logits
            mask |= rp.sam_mask_logits(low[0, 0, 0], hw, self.sam_size) > thr
        return Grounding(mask, boxes, scores)

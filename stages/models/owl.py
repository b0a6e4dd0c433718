"""OWLv2 + SAM as a bundle's RES, split for the RES index (docs/models.md, "The RES split").

Image side, once per image, prompt-independent: OWLv2's image graph (`owl_image.onnx`: the
per-patch class embeddings, logit shift and scale, boxes and objectness) and SAM's image
embedding. Prompt side: the text graph (`owl_text.onnx`) once per prompt, then per image a dot
product (`res_processing.owl_logits`), the boxes above `box_threshold` (best first, at most
`max_boxes`) and SAM's decoder once per box; the union of the masks is the RES mask. No box:
an empty mask. SAM is either layout (`grounded.Sam`).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from stages.core.errors import GoiError
from stages.models import res_processing as rp
from stages.models.grounded import (
    SIDE_DTYPE,
    Grounding,
    ResPrompt,
    Sam,
    _size,
    _stats,
    check_detection,
    check_sam_spec,
    check_tokenizer,
)
from stages.models.onnx_io import Tokens, check_inputs_named, check_io, inside, session

IMAGE_OUTPUTS = ("class_embeds", "logit_shift", "logit_scale", "pred_boxes", "objectness")
#: image-side key -> (the image graph's output, stored dtype). The class embeddings are the
#: bulk (P x D); float16 moves a logit by ~1e-3 x its scale. The rest is small and float32.
SIDE = {
    "owl_class_embeds": ("class_embeds", SIDE_DTYPE),
    "owl_logit_shift": ("logit_shift", "float32"),
    "owl_logit_scale": ("logit_scale", "float32"),
    "owl_boxes": ("pred_boxes", "float32"),
    "owl_objectness": ("objectness", "float32"),
}


def check_owl_spec(root: Path, spec: dict, where: str) -> None:
    """The manifest's 'owl_sam' section makes sense and names files that are there."""
    img, txt = spec["image"], spec["text"]
    inside(root, img["file"], f"{where}: owl_sam.image")
    inside(root, txt["file"], f"{where}: owl_sam.text")
    h, w = _size(img, "owl_sam.image", where)
    if h != w:
        raise GoiError(f"{where}: field 'owl_sam.image.size' must be square, not {[w, h]}")
    _stats(img, "owl_sam.image", where)
    check_tokenizer(root, txt["tokenizer"], "owl_sam.text", where)
    check_sam_spec(root, spec["sam_encoder"], spec["sam_decoder"], "owl_sam", where)
    check_detection(spec, "owl_sam", where)


class OwlSam:
    """The OWLv2 + SAM pipeline of a bundle; graphs opened and checked on first use."""

    def __init__(self, root: Path, spec: dict, where: str):
        self.root, self.spec, self.where = root, spec, where
        self.size = _size(spec["image"], "owl_sam.image", where)[0]
        self.sam = Sam(root, spec["sam_encoder"], spec["sam_decoder"], "owl_sam", where)

    @cached_property
    def _graphs(self) -> tuple[Any, Any, Tokens, tuple[int, int]]:
        """(image graph, text graph, tokenizer, (P, D))."""
        img, txt = self.spec["image"], self.spec["text"]
        pi = inside(self.root, img["file"], f"{self.where}: owl_sam.image")
        pt = inside(self.root, txt["file"], f"{self.where}: owl_sam.text")
        tok = txt["tokenizer"]
        where = f"{self.where}: owl_sam.text.tokenizer"
        tokens = Tokens(inside(self.root, tok["file"], where), int(tok["max_length"]), where)
        s = self.size
        i = session(pi, low_memory=True)
        check_io(i, pi, "input", "pixel_values", 4, {0: 1, 1: 3, 2: s, 3: s})
        check_inputs_named(i, pi, ["pixel_values"])
        cls = check_io(i, pi, "output", "class_embeds", 3, {0: 1})
        p, d = cls[1], cls[2]
        if not (isinstance(p, int) and isinstance(d, int)):
            raise GoiError(f"{pi}: output 'class_embeds' needs fixed sizes, found {cls}")
        for name in ("logit_shift", "logit_scale", "objectness"):
            check_io(i, pi, "output", name, 2, {0: 1, 1: p})
        check_io(i, pi, "output", "pred_boxes", 3, {0: 1, 1: p, 2: 4})
        t = session(pt)
        for name in ("input_ids", "attention_mask"):
            check_io(t, pt, "input", name, 2, {0: 1})
        check_inputs_named(t, pt, ["input_ids", "attention_mask"])
        check_io(t, pt, "output", "query_embeds", 2, {0: 1, 1: d})
        return i, t, tokens, (p, d)

    def check(self) -> None:
        # setting up a graph is mostly one core's work: SAM's two beside OWLv2's two (OWLv2-B/16
        # and SAM 2.1-T on 2 cores: 1.2 s, against 1.5-2.0 s one after the other)
        with ThreadPoolExecutor(1) as pool:
            sam = pool.submit(lambda: self.sam.sessions)
            _ = self._graphs
            sam.result()

    def prompt(self, text: str) -> ResPrompt:
        """The query embedding [D] of the prompt, once."""
        _, t, tokens, _ = self._graphs
        ids, att = tokens.encode(text)
        q = t.run(["query_embeds"], {"input_ids": ids, "attention_mask": att})[0][0]
        return ResPrompt(text, ids, att, np.asarray(q, np.float32))

    def image_side_spec(self) -> dict[str, tuple[tuple[int, ...], str]]:
        p, d = self._graphs[3]
        shapes: dict[str, tuple[int, ...]] = {"owl_class_embeds": (p, d), "owl_boxes": (p, 4)}
        spec: dict[str, tuple[tuple[int, ...], str]] = {
            k: (shapes.get(k, (p,)), dtype) for k, (_, dtype) in SIDE.items()
        }
        spec.update(self.sam.side_spec())
        return spec

    def _owl(self, rgb: np.ndarray) -> dict[str, np.ndarray]:
        """OWLv2's image graph on an image -> its outputs without the batch axis, float32."""
        i = self._graphs[0]
        img = self.spec["image"]
        pixels = rp.owl_inputs(rgb, self.size, tuple(img["mean"]), tuple(img["std"]))
        outs = i.run([SIDE[k][0] for k in SIDE], {"pixel_values": pixels})
        return {k: np.asarray(v[0], np.float32) for k, v in zip(SIDE, outs, strict=True)}

    def image_side(self, rgb: np.ndarray) -> dict[str, np.ndarray]:
        side = {k: v.astype(SIDE[k][1]) for k, v in self._owl(rgb).items()}
        side.update(self.sam.image_side(rgb))
        return side

    def detect(
        self, side: dict[str, np.ndarray], hw: tuple[int, int], prompt: ResPrompt
    ) -> tuple[np.ndarray, np.ndarray]:
        assert prompt.embedding is not None
        logits = rp.owl_logits(
            np.asarray(side["owl_class_embeds"], np.float32),
            side["owl_logit_shift"],
            side["owl_logit_scale"],
            prompt.embedding,
        )
        thr, k = float(self.spec["box_threshold"]), int(self.spec["max_boxes"])
        return rp.owl_detections(logits, np.asarray(side["owl_boxes"]), hw, thr, k)

    def from_image_side(
        self, side: dict[str, np.ndarray], hw: tuple[int, int], prompt: ResPrompt
    ) -> Grounding:
        boxes, scores = self.detect(side, hw, prompt)
        if len(boxes) == 0:
            return Grounding(np.zeros(hw, bool), boxes, scores)
        emb = self.sam.from_side(side)
        return self.sam.union(emb, boxes, scores, hw, float(self.spec["mask_threshold"]))

    def run(self, rgb: np.ndarray, text: str) -> Grounding:
        """The whole pipeline on one image, in float32 (SAM only when a box is kept)."""
        hw = (int(rgb.shape[0]), int(rgb.shape[1]))
        boxes, scores = self.detect(self._owl(rgb), hw, self.prompt(text))
        if len(boxes) == 0:
            return Grounding(np.zeros(hw, bool), boxes, scores)
        return self.sam.union(
            self.sam.embed(rgb), boxes, scores, hw, float(self.spec["mask_threshold"])
        )

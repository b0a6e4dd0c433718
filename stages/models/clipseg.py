"""CLIPSeg split as a bundle's RES (`clipseg`, docs/models.md "The RES split"): the frozen CLIP
vision activations its decoder reads are the image side (once per image, about 90 % of the
cost); the conditional embedding of the prompt (once per prompt) and the light decoder are the
prompt side. The mask: the decoder's probabilities resized to the image (bilinear), above
`threshold`, as the whole-graph `res` does.
"""

from __future__ import annotations

import math
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from stages.core.errors import GoiError
from stages.models import res_processing as rp
from stages.models.grounded import SIDE_DTYPE, Grounding, ResPrompt, _size, _stats
from stages.models.onnx_io import Tokens, check_inputs_named, check_io, inside, session


def check_clipseg_spec(root: Path, spec: dict, where: str) -> None:
    """The manifest's 'clipseg' section makes sense and names files that are there."""
    for part in ("image", "text", "decoder"):
        inside(root, spec[part]["file"], f"{where}: clipseg.{part}")
    _size(spec["image"], "clipseg.image", where)
    _stats(spec["image"], "clipseg.image", where)
    tok = spec["text"]["tokenizer"]
    if tok["kind"] != "huggingface":
        raise GoiError(f"{where}: tokenizer kind {tok['kind']!r} is not supported (huggingface)")
    inside(root, tok["file"], f"{where}: clipseg.text.tokenizer")
    v = float(spec["threshold"])
    if not (math.isfinite(v) and 0 <= v <= 1):
        raise GoiError(f"{where}: field 'clipseg.threshold' is {v}, not a number in [0, 1]")


class ClipSegSplit:
    """The three CLIPSeg graphs of a bundle, opened and checked on first use."""

    def __init__(self, root: Path, spec: dict, where: str):
        self.root, self.spec, self.where = root, spec, where
        self.hw = _size(spec["image"], "clipseg.image", where)

    @cached_property
    def _graphs(self) -> tuple[Any, Any, Any, Tokens, tuple[int, ...]]:
        """(image, text, decoder, tokenizer, the activations' shape [n, 1, T, C])."""
        paths = {
            k: inside(self.root, self.spec[k]["file"], f"{self.where}: clipseg.{k}")
            for k in ("image", "text", "decoder")
        }
        tok = self.spec["text"]["tokenizer"]
        where = f"{self.where}: clipseg.text.tokenizer"
        tokens = Tokens(inside(self.root, tok["file"], where), int(tok["max_length"]), where)
        h, w = self.hw
        i = session(paths["image"], low_memory=True)
        check_io(i, paths["image"], "input", "pixel_values", 4, {0: 1, 1: 3, 2: h, 3: w})
        check_inputs_named(i, paths["image"], ["pixel_values"])
        acts = check_io(i, paths["image"], "output", "activations", 4, {1: 1})
        if not all(isinstance(v, int) for v in acts):
            raise GoiError(f"{paths['image']}: output 'activations' needs fixed sizes: {acts}")
        t = session(paths["text"])
        for name in ("input_ids", "attention_mask"):
            check_io(t, paths["text"], "input", name, 2, {0: 1})
        check_inputs_named(t, paths["text"], ["input_ids", "attention_mask"])
        cond = check_io(t, paths["text"], "output", "conditional", 2, {0: 1})
        d = session(paths["decoder"])
        fixed = {i: int(v) for i, v in enumerate(acts)}
        check_io(d, paths["decoder"], "input", "activations", 4, fixed)
        fixed = {i: v for i, v in enumerate(cond) if isinstance(v, int)}
        check_io(d, paths["decoder"], "input", "conditional", 2, fixed)
        check_inputs_named(d, paths["decoder"], ["activations", "conditional"])
        check_io(d, paths["decoder"], "output", "probs", 4, {0: 1, 1: 1})
        return i, t, d, tokens, tuple(int(v) for v in acts)

    def check(self) -> None:
        _ = self._graphs

    def prompt(self, text: str) -> ResPrompt:
        _, t, _, tokens, _ = self._graphs
        ids, att = tokens.encode(text)
        cond = t.run(["conditional"], {"input_ids": ids, "attention_mask": att})[0][0]
        return ResPrompt(text, ids, att, np.asarray(cond, np.float32))

    def image_side_spec(self) -> dict[str, tuple[tuple[int, ...], str]]:
        return {"clipseg_activations": (self._graphs[4], SIDE_DTYPE)}

    def activations(self, rgb: np.ndarray) -> np.ndarray:
        """[H, W, 3] uint8 RGB -> the vision activations [n, 1, T, C] float32."""
        img = self.spec["image"]
        pixels = rp.square_inputs(rgb, self.hw, tuple(img["mean"]), tuple(img["std"]))
        out = self._graphs[0].run(["activations"], {"pixel_values": pixels})[0]
        return np.asarray(out, np.float32)

    def image_side(self, rgb: np.ndarray) -> dict[str, np.ndarray]:
        return {"clipseg_activations": self.activations(rgb).astype(SIDE_DTYPE)}

    def from_image_side(
        self, side: dict[str, np.ndarray], hw: tuple[int, int], prompt: ResPrompt
    ) -> Grounding:
        assert prompt.embedding is not None
        feed = {
            "activations": np.asarray(side["clipseg_activations"], np.float32),
            "conditional": prompt.embedding[None],
        }
        probs = self._graphs[2].run(["probs"], feed)[0]  # [1, 1, S, S]
        mask = rp.scores_to_mask(probs[0, 0], hw, float(self.spec["threshold"]))
        return Grounding(mask, np.zeros((0, 4), np.float32), np.zeros(0, np.float32))

    def run(self, rgb: np.ndarray, text: str) -> Grounding:
        hw = (int(rgb.shape[0]), int(rgb.shape[1]))
        side = {"clipseg_activations": self.activations(rgb)}
        return self.from_image_side(side, hw, self.prompt(text))

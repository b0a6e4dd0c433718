"""Model bundles: a directory with manifest.json naming ONNX models, run with onnxruntime.

The I/O contract (docs/models.md): the image encoder takes [1, 3, H, W] float32 (normalised as
the manifest says) and returns dense features [1, D, h, w]; the text encoder takes token ids
[1, L] int64 (and optionally an attention mask) and returns [1, D]. A bundle's RES is either a
single model (`res`: image + prompt -> mask scores, e.g. CLIPSeg), a Grounded-SAM pipeline
(`grounded`: Grounding DINO + SAM, `stages.models.grounded`) or OWLv2 + SAM (`owl_sam`,
`stages.models.owl`), the last split into an image side and a prompt side; or a SAM alone
(`sam`: no detector, so no text: it answers clicks and boxes). goi checks each
model's inputs and outputs against the manifest before running it. No custom-operator library
is ever registered, and manifest paths may not leave the bundle directory.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from schemas import validate_json
from stages.core.artifacts import sha256_files
from stages.core.errors import GoiError
from stages.core.files import read_json
from stages.models import res_processing as rp
from stages.models.clipseg import ClipSegSplit, check_clipseg_spec
from stages.models.grounded import (
    GroundedSam,
    Grounding,
    ResPrompt,
    Sam,
    check_sam_spec,
    check_spec,
)
from stages.models.manifest import check_values
from stages.models.onnx_io import (
    Tokens,
    check_inputs_named,
    check_io,
    checked_embedding,
    inside,
    session,
)
from stages.models.owl import OwlSam, check_owl_spec

#: The manifest's RES sections; a bundle has at most one of them and `sam`.
RES_KINDS = ("res", "grounded", "owl_sam", "clipseg")
#: A SAM alone: point and box prompts, no text (clicks and boxes, stages.query.pointing).
SAM_ALONE = "sam"
#: The RES kinds split into an image side and a prompt side, and their pipelines' attributes.
SPLIT = {"grounded": "_grounded", "owl_sam": "_owl_sam", "clipseg": "_clipseg"}

MANIFEST = "manifest.json"
#: How an image is resized to a model's `size`: OpenCV's area filter (schema 1.0's only way),
#: or Pillow's bilinear filter, bit for bit, as the transformers image processors do it.
RESIZE = ("area", "pil-bilinear")


def _prepare(spec: dict, rgb: np.ndarray) -> np.ndarray:
    """[H, W, 3] uint8 RGB -> the model input [1, 3, H', W'] as the spec says."""
    import cv2

    img = rgb if spec["channel_order"].upper() == "RGB" else rgb[:, :, ::-1]
    size = [int(v) for v in spec["size"]] if spec.get("size") else None
    if spec.get("resize", "area") == "pil-bilinear":
        hw = (size[1], size[0]) if size else img.shape[:2]
        return rp.square_inputs(np.ascontiguousarray(img), hw, spec["mean"], spec["std"])
    if size:
        img = cv2.resize(img, (size[0], size[1]), interpolation=cv2.INTER_AREA)
    x = (img.astype(np.float32) / 255.0 - np.asarray(spec["mean"], np.float32)) / np.asarray(
        spec["std"], np.float32
    )
    return np.ascontiguousarray(x.transpose(2, 0, 1)[None])


def _tokens(root: Path, spec: dict, where: str) -> Tokens:
    if spec["kind"] != "huggingface":
        raise GoiError(f"{where}: tokenizer kind {spec['kind']!r} is not supported (huggingface)")
    return Tokens(inside(root, spec["file"], where), int(spec["max_length"]), where)


@dataclass
class Bundle:
    root: Path
    manifest: dict

    @property
    def name(self) -> str:
        return str(self.manifest["name"])

    @property
    def dim(self) -> int:
        return int(self.manifest["feature_dim"])

    @property
    def where(self) -> str:
        return str(self.root / MANIFEST)

    def digest(self) -> str:
        """SHA-256 of the bundle's files, hashed once per load: a long-lived process (goi view,
        a batch's prompts) asks for it on every prompt, and the files are hundreds of MB."""
        return self._digest

    @cached_property
    def _digest(self) -> str:
        return sha256_files([p for p in self.root.rglob("*") if p.is_file()])

    @cached_property
    def _image_session(self) -> Any:
        spec = self._spec("image_encoder", "needed to encode images")
        path = inside(self.root, spec["file"], self.where)
        sess = session(path)
        check_io(sess, path, "input", spec["input"], 4, {1: 3})
        check_io(sess, path, "output", spec["output"], 4, {1: self.dim})
        return sess

    @cached_property
    def _text(self) -> tuple[Tokens, Any]:
        """The tokenizer and the checked text-encoder session."""
        spec = self._spec("text_encoder", "its tokenizer is needed for prompts")
        tok = _tokens(self.root, spec["tokenizer"], self.where)
        path = inside(self.root, spec["file"], self.where)
        sess = session(path)
        check_io(sess, path, "input", spec["input_ids"], 2, {0: 1})
        if spec.get("attention_mask"):
            check_io(sess, path, "input", spec["attention_mask"], 2, {0: 1})
        check_io(sess, path, "output", spec["output"], 2, {1: self.dim})
        return tok, sess

    def _spec(self, key: str, what: str) -> dict:
        spec = self.manifest.get(key)
        if spec is None:
            raise GoiError(f"{self.where}: this bundle has no {key} ({what})")
        return spec

    def encode_image(self, rgb: np.ndarray) -> np.ndarray:
        """[H, W, 3] uint8 RGB -> dense features [D, h, w] float32."""
        spec = self._spec("image_encoder", "needed to encode images")
        out = self._image_session.run([spec["output"]], {spec["input"]: _prepare(spec, rgb)})[0]
        if out.ndim != 4 or out.shape[0] != 1 or out.shape[1] != self.dim:
            raise GoiError(
                f"{self.root}: image encoder returned {list(out.shape)}, expected "
                f"[1, {self.dim}, h, w]"
            )
        return out[0].astype(np.float32)

    @cached_property
    def _res(self) -> tuple[Any, Tokens]:
        """The checked single RES model and its tokenizer (its own, else the text encoder's)."""
        spec = self.manifest["res"]
        if spec.get("tokenizer"):
            tok = _tokens(self.root, spec["tokenizer"], f"{self.where}: res.tokenizer")
        else:
            tok = self._text[0]
        path = inside(self.root, spec["file"], self.where)
        sess = session(path, low_memory=True)
        check_io(sess, path, "input", spec["image_input"], 4, {1: 3})
        named = [spec["image_input"], spec["input_ids"]]
        check_io(sess, path, "input", spec["input_ids"], 2, {0: 1})
        if spec.get("attention_mask"):
            check_io(sess, path, "input", spec["attention_mask"], 2, {0: 1})
            named.append(spec["attention_mask"])
        check_inputs_named(sess, path, named)
        check_io(sess, path, "output", spec["output"], 4, {1: 1})
        return sess, tok

    @cached_property
    def _grounded(self) -> GroundedSam:
        return GroundedSam(self.root, self.manifest["grounded"], self.where)

    @cached_property
    def _owl_sam(self) -> OwlSam:
        return OwlSam(self.root, self.manifest["owl_sam"], self.where)

    @cached_property
    def _clipseg(self) -> ClipSegSplit:
        return ClipSegSplit(self.root, self.manifest["clipseg"], self.where)

    @property
    def has_res(self) -> bool:
        return any(k in self.manifest for k in RES_KINDS)

    @property
    def has_sam(self) -> bool:
        """Whether the bundle has a SAM to answer clicks and boxes: a SAM alone, or the SAM of
        a Grounded-SAM or OWLv2 + SAM pipeline."""
        return any(k in self.manifest for k in (SAM_ALONE, "grounded", "owl_sam"))

    @cached_property
    def sam(self) -> Sam:
        """The bundle's SAM (see `has_sam`); refused, saying what is needed, when it has none."""
        if SAM_ALONE in self.manifest:
            spec = self.manifest[SAM_ALONE]
            return Sam(self.root, spec["sam_encoder"], spec["sam_decoder"], SAM_ALONE, self.where)
        if "grounded" in self.manifest:
            return self._grounded.sam
        if "owl_sam" in self.manifest:
            return self._owl_sam.sam
        raise GoiError(
            f"{self.where}: this bundle has no SAM to answer clicks and boxes; give a bundle with "
            "one (a SAM alone from `goi export-model DIR` on a SAM in segment-anything's ONNX "
            "layout, Grounded-SAM or OWLv2 + SAM)"
        )

    # --- what a RES index keeps of an image: the RES's image side (the RES split, below), or a
    # SAM alone's image embedding.
    @property
    def indexable(self) -> bool:
        return self.res_indexable or SAM_ALONE in self.manifest

    @property
    def index_kind(self) -> str:
        """What a RES index of this bundle keeps: the RES kind, or 'sam' for a SAM alone."""
        return str(self.res_kind) if self.has_res else SAM_ALONE

    def check_index(self) -> None:
        """Open the models an index of this bundle runs and check their tensors."""
        if self.has_res:
            self.check_res()
        else:
            _ = self.sam.sessions

    def image_side_spec(self) -> dict[str, tuple[tuple[int, ...], str]]:
        """key -> (shape, dtype name) of what `image_side` returns."""
        if self.has_res:
            return self.res_image_side_spec()
        return self.sam.side_spec()

    def image_side(self, rgb: np.ndarray) -> dict[str, np.ndarray]:
        """[H, W, 3] uint8 RGB -> the arrays a RES index keeps of it (see `indexable`)."""
        if self.has_res:
            return self.res_image_side(rgb)
        return self.sam.image_side(rgb)

    @property
    def res_kind(self) -> str | None:
        """'grounded' (Grounding DINO + SAM), 'owl_sam' (OWLv2 + SAM), 'clipseg' (CLIPSeg,
        split), 'model' (a single whole RES model) or None."""
        for kind in SPLIT:
            if kind in self.manifest:
                return kind
        return "model" if self.has_res else None

    def check_res(self) -> None:
        """Open the RES models and check every tensor the manifest names (cheap next to a
        run; done anyway before the first image)."""
        if not self.has_res:
            self._spec("res", "a referring-segmentation model; pass --res-masks DIR")
        if self.res_kind in SPLIT:
            getattr(self, SPLIT[self.res_kind]).check()
        else:
            _ = self._res

    def ground(self, rgb: np.ndarray, text: str) -> Grounding:
        """The RES mask of a prompt on an image, with the detector's boxes when the bundle's
        RES is a grounded pipeline (none for a single model)."""
        if not self.has_res:
            self._spec("res", "a referring-segmentation model; pass --res-masks DIR")
        if self.res_kind in SPLIT:
            found: Grounding = getattr(self, SPLIT[self.res_kind]).run(rgb, text)
            return found
        spec = self.manifest["res"]
        sess, tok = self._res
        ids, att = tok.encode(text)
        feed = {spec["image_input"]: _prepare(spec, rgb), spec["input_ids"]: ids}
        if spec.get("attention_mask"):
            feed[spec["attention_mask"]] = att
        out = sess.run([spec["output"]], feed)[0]
        if out.ndim != 4 or out.shape[:2] != (1, 1):
            raise GoiError(
                f"{self.root / spec['file']}: returned {list(out.shape)}, expected [1, 1, h, w]"
            )
        mask = rp.scores_to_mask(out[0, 0], rgb.shape[:2], float(spec["threshold"]))
        return Grounding(mask, np.zeros((0, 4), np.float32), np.zeros(0, np.float32))

    # --- the RES split (docs/models.md "The RES split"): the prompt-independent image side,
    # computed once per image (the RES index caches it), and the prompt side run on it.
    @property
    def res_indexable(self) -> bool:
        """True when the bundle's RES has a prompt-independent image side worth caching per
        image. A single-model RES (CLIPSeg exported whole) has none: its text enters the graph
        with the image."""
        return self.res_kind in SPLIT

    def res_image_side_spec(self) -> dict[str, tuple[tuple[int, ...], str]]:
        """key -> (shape, numpy dtype name) of every array `res_image_side` returns, fixed per
        bundle ({} when the RES has no image side)."""
        self.check_res()
        if self.res_kind in SPLIT:
            spec: dict[str, tuple[tuple[int, ...], str]]
            spec = getattr(self, SPLIT[self.res_kind]).image_side_spec()
            return spec
        return {}

    def res_image_side(self, rgb: np.ndarray) -> dict[str, np.ndarray]:
        """[H, W, 3] uint8 RGB -> the named prompt-independent arrays of this image, as
        `res_image_side_spec` says (Grounded-SAM: SAM's image embedding)."""
        self.check_res()
        if self.res_kind in SPLIT:
            side: dict[str, np.ndarray] = getattr(self, SPLIT[self.res_kind]).image_side(rgb)
            return side
        return {}

    def res_prompt(self, text: str) -> ResPrompt:
        """The prompt side's per-prompt work, done once (the tokens; the text encoding)."""
        self.check_res()
        if self.res_kind in SPLIT:
            prompt: ResPrompt = getattr(self, SPLIT[self.res_kind]).prompt(text)
            return prompt
        ids, att = self._res[1].encode(text)
        return ResPrompt(text, ids, att)

    def res_from_image_side(
        self,
        image_side: dict[str, np.ndarray],
        hw: tuple[int, int],
        prompt: ResPrompt,
        rgb: np.ndarray | None = None,
    ) -> Grounding:
        """The RES answer from the cached image side, equal to `ground(rgb, prompt.text)`
        (tested; the float16 image side moves a few pixels at the mask threshold).
        hw = (H, W) of the original image. OWLv2 + SAM and the split CLIPSeg need nothing
        else; Grounding DINO and a whole single RES model run on the image itself and need
        `rgb`."""
        self.check_res()
        hw = (int(hw[0]), int(hw[1]))
        want = self.res_image_side_spec()
        for key, (shape, _) in want.items():
            got = image_side.get(key)
            if got is None or tuple(got.shape) != shape:
                found = "missing" if got is None else f"{list(got.shape)}"
                raise GoiError(
                    f"{self.where}: the RES image side's '{key}' is {found}, expected "
                    f"{list(shape)} (an index made with another bundle?)"
                )
        if self.res_kind == "owl_sam":
            return self._owl_sam.from_image_side(image_side, hw, prompt)
        if self.res_kind == "clipseg":
            return self._clipseg.from_image_side(image_side, hw, prompt)
        if rgb is None:
            raise GoiError(
                f"{self.where}: this bundle's RES ({self.res_kind}) runs on the image itself; "
                "its rgb is needed"
            )
        if tuple(rgb.shape[:2]) != hw:
            raise GoiError(f"rgb is {list(rgb.shape[:2])}, but hw says {list(hw)}")
        if self.res_kind == "grounded":
            return self._grounded.from_image_side(image_side, hw, prompt, rgb)
        return self.ground(rgb, prompt.text)

    def segment(self, rgb: np.ndarray, text: str) -> np.ndarray:
        """The RES mask of a prompt on an image: [H, W, 3] uint8 RGB -> [H, W] bool."""
        return self.ground(rgb, text).mask

    def encode_text(self, text: str) -> np.ndarray:
        """A prompt -> its unit embedding [D]."""
        spec = self._spec("text_encoder", "pass --text-embeddings FILE instead")
        tok, sess = self._text
        ids, att = tok.encode(text)
        feed = {spec["input_ids"]: ids}
        if spec.get("attention_mask"):
            feed[spec["attention_mask"]] = att
        out = sess.run([spec["output"]], feed)[0][0].astype(np.float32)
        return checked_embedding(out, f"{self.root / spec['file']}: output '{spec['output']}'")


def _check_image_spec(mf: Path, key: str, spec: dict) -> None:
    for stat in ("mean", "std"):
        if len(spec[stat]) != 3:
            raise GoiError(f"{mf}: field '{key}.{stat}' needs 3 numbers")
    if spec["channel_order"].upper() not in ("RGB", "BGR"):
        raise GoiError(f"{mf}: field '{key}.channel_order' must be RGB or BGR")
    if spec.get("resize", "area") not in RESIZE:
        raise GoiError(f"{mf}: field '{key}.resize' must be one of {', '.join(RESIZE)}")
    size = spec.get("size")
    if size is not None and (len(size) != 2 or not all(isinstance(v, int) and v > 0 for v in size)):
        raise GoiError(f"{mf}: field '{key}.size' needs [width, height] as two positive integers")


def load_bundle(path: str | os.PathLike[str]) -> Bundle:
    """Read and check a bundle's manifest: its fields, and that every file it names is in the
    bundle. The models themselves are opened (and their tensors checked) when first used."""
    root = Path(path)
    mf = root / MANIFEST
    if not mf.is_file():
        what = (
            "a Hugging Face checkpoint, not a model bundle"
            if (root / "config.json").is_file()
            else "not a model bundle"
        )
        raise GoiError(
            f"--bundle: {root} has no {MANIFEST}: {what}; `goi export-model CHECKPOINT... "
            "--out BUNDLE` makes a bundle from Hugging Face checkpoints (docs/models.md)"
        )
    manifest = read_json(mf)
    validate_json(manifest, "goi.bundle", str(mf))
    check_values(manifest, str(mf))  # every value typed, finite, in range: before any model
    encoders = [k for k in ("image_encoder", "text_encoder") if k in manifest]
    res_kinds = [k for k in (*RES_KINDS, SAM_ALONE) if k in manifest]
    if not encoders and not res_kinds:
        raise GoiError(
            f"{mf}: needs at least one of 'image_encoder', 'text_encoder', 'res', 'grounded', "
            "'owl_sam', 'clipseg' and 'sam'"
        )
    if encoders and "feature_dim" not in manifest:
        raise GoiError(f"{mf}: field 'feature_dim' is missing (needed with '{encoders[0]}')")
    if len(res_kinds) > 1:
        raise GoiError(
            f"{mf}: a bundle has one RES or SAM: one of 'res', 'grounded', 'owl_sam', 'clipseg' "
            f"and 'sam', not {' and '.join(repr(k) for k in res_kinds)}"
        )
    res = manifest.get("res")
    if res is not None and not res.get("tokenizer") and "text_encoder" not in manifest:
        raise GoiError(
            f"{mf}: 'res' uses the text encoder's tokenizer; add 'text_encoder' or 'res.tokenizer'"
        )
    for key in ("image_encoder", "text_encoder", "res"):
        spec = manifest.get(key)
        if spec is None:
            continue
        inside(root, spec["file"], f"{mf}: {key}")
        if key != "text_encoder":
            _check_image_spec(mf, key, spec)
        tok = spec.get("tokenizer")
        if tok is not None:
            _tokens_spec(root, tok, f"{mf}: {key}.tokenizer")
    if "grounded" in manifest:
        check_spec(root, manifest["grounded"], str(mf))
    if "owl_sam" in manifest:
        check_owl_spec(root, manifest["owl_sam"], str(mf))
    if "clipseg" in manifest:
        check_clipseg_spec(root, manifest["clipseg"], str(mf))
    if SAM_ALONE in manifest:
        sam = manifest[SAM_ALONE]
        check_sam_spec(root, sam["sam_encoder"], sam["sam_decoder"], SAM_ALONE, str(mf))
    return Bundle(root, manifest)


def _tokens_spec(root: Path, spec: dict, where: str) -> None:
    if spec["kind"] != "huggingface":
        raise GoiError(f"{where}: tokenizer kind {spec['kind']!r} is not supported (huggingface)")
    inside(root, spec["file"], where)

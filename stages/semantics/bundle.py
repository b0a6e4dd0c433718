"""Model bundles: a directory with manifest.json naming ONNX encoders, run with onnxruntime.

The I/O contract (docs/models.md): the image encoder takes [1, 3, H, W] float32 (normalised as
the manifest says) and returns dense features [1, D, h, w]; the text encoder takes token ids
[1, L] int64 (and optionally an attention mask) and returns [1, D]. goi checks each model's
inputs and outputs against the manifest before running it. No custom-operator library is ever
registered, and manifest paths may not leave the bundle directory.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from schemas import validate_json
from stages.core.arrays import normalise
from stages.core.artifacts import sha256_files
from stages.core.errors import GoiError
from stages.core.files import read_json

MANIFEST = "manifest.json"


def _providers() -> list[str]:
    import onnxruntime as ort

    have = ort.get_available_providers()
    return [p for p in ("CUDAExecutionProvider", "CPUExecutionProvider") if p in have]


def _inside(root: Path, rel: str, where: str) -> Path:
    p = (root / rel).resolve()
    if not p.is_relative_to(root.resolve()):
        raise GoiError(f"{where}: path {rel!r} points outside the bundle directory")
    if not p.is_file():
        raise GoiError(f"{where}: {rel} is missing from the bundle")
    return p


def _session(path: Path):  # noqa: ANN202
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.log_severity_level = 3
    try:
        return ort.InferenceSession(str(path), sess_options=opts, providers=_providers())
    except Exception as e:  # onnxruntime raises its own exception types for bad models
        raise GoiError(
            f"{path}: not a loadable ONNX model ({str(e).splitlines()[0][:200]})"
        ) from None


def _check_io(
    sess: Any, path: Path, kind: str, name: str, rank: int, fixed: dict[int, int]
) -> None:
    """The named input or output exists with the expected rank and fixed dimensions."""
    items = sess.get_inputs() if kind == "input" else sess.get_outputs()
    found = {i.name: i for i in items}
    if name not in found:
        raise GoiError(f"{path}: no {kind} named '{name}' (it has: {', '.join(found)})")
    shape = found[name].shape
    if len(shape) != rank:
        raise GoiError(f"{path}: {kind} '{name}' has rank {len(shape)} {shape}, expected {rank}")
    for axis, size in fixed.items():
        if isinstance(shape[axis], int) and shape[axis] != size:
            raise GoiError(
                f"{path}: {kind} '{name}' has size {shape[axis]} on axis {axis}, expected {size}"
            )


def _prepare(spec: dict, rgb: np.ndarray) -> np.ndarray:
    """[H, W, 3] uint8 RGB -> the model input [1, 3, H', W'] as the spec says."""
    import cv2

    img = rgb if spec["channel_order"].upper() == "RGB" else rgb[:, :, ::-1]
    if spec.get("size"):
        w, h = (int(v) for v in spec["size"])
        img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
    x = (img.astype(np.float32) / 255.0 - np.asarray(spec["mean"], np.float32)) / np.asarray(
        spec["std"], np.float32
    )
    return np.ascontiguousarray(x.transpose(2, 0, 1)[None])


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

    def digest(self) -> str:
        return sha256_files([p for p in self.root.rglob("*") if p.is_file()])

    @cached_property
    def _image_session(self) -> Any:
        spec = self._spec("image_encoder", "needed to encode images")
        path = _inside(self.root, spec["file"], str(self.root / MANIFEST))
        sess = _session(path)
        _check_io(sess, path, "input", spec["input"], 4, {1: 3})
        _check_io(sess, path, "output", spec["output"], 4, {1: self.dim})
        return sess

    @cached_property
    def _text(self) -> tuple[Any, Any]:
        """The tokenizer and the checked text-encoder session."""
        spec = self._spec("text_encoder", "its tokenizer is needed for prompts")
        where = str(self.root / MANIFEST)
        tok_spec = spec["tokenizer"]
        if tok_spec["kind"] != "huggingface":
            raise GoiError(
                f"{where}: tokenizer kind {tok_spec['kind']!r} is not supported (huggingface)"
            )
        from tokenizers import Tokenizer

        tok = Tokenizer.from_file(str(_inside(self.root, tok_spec["file"], where)))
        tok.enable_truncation(int(tok_spec["max_length"]))
        path = _inside(self.root, spec["file"], where)
        sess = _session(path)
        _check_io(sess, path, "input", spec["input_ids"], 2, {0: 1})
        if spec.get("attention_mask"):
            _check_io(sess, path, "input", spec["attention_mask"], 2, {0: 1})
        _check_io(sess, path, "output", spec["output"], 2, {1: self.dim})
        return tok, sess

    def _spec(self, key: str, what: str) -> dict:
        spec = self.manifest.get(key)
        if spec is None:
            raise GoiError(f"{self.root / MANIFEST}: this bundle has no {key} ({what})")
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
    def _res_session(self) -> Any:
        spec = self.manifest["res"]
        path = _inside(self.root, spec["file"], str(self.root / MANIFEST))
        sess = _session(path)
        _check_io(sess, path, "input", spec["image_input"], 4, {1: 3})
        _check_io(sess, path, "input", spec["input_ids"], 2, {0: 1})
        if spec.get("attention_mask"):
            _check_io(sess, path, "input", spec["attention_mask"], 2, {0: 1})
        _check_io(sess, path, "output", spec["output"], 4, {1: 1})
        return sess

    @property
    def has_res(self) -> bool:
        return "res" in self.manifest

    def segment(self, rgb: np.ndarray, text: str) -> np.ndarray:
        """The RES mask of a prompt on an image: [H, W] uint8 RGB -> [H, W] bool."""
        import cv2

        spec = self._spec("res", "a referring-segmentation model; pass --res-masks DIR")
        tok, _ = self._text
        enc = tok.encode(text)
        feed = {
            spec["image_input"]: _prepare(spec, rgb),
            spec["input_ids"]: np.asarray([enc.ids], np.int64),
        }
        if spec.get("attention_mask"):
            feed[spec["attention_mask"]] = np.asarray([enc.attention_mask], np.int64)
        score = self._res_session.run([spec["output"]], feed)[0][0, 0].astype(np.float32)
        h, w = rgb.shape[:2]
        score = cv2.resize(score, (w, h), interpolation=cv2.INTER_LINEAR)
        return score > float(spec["threshold"])

    def encode_text(self, text: str) -> np.ndarray:
        """A prompt -> its unit embedding [D]."""
        spec = self._spec("text_encoder", "pass --text-embeddings FILE instead")
        tok, sess = self._text
        enc = tok.encode(text)
        feed = {spec["input_ids"]: np.asarray([enc.ids], np.int64)}
        if spec.get("attention_mask"):
            feed[spec["attention_mask"]] = np.asarray([enc.attention_mask], np.int64)
        out = sess.run([spec["output"]], feed)[0][0].astype(np.float32)
        return normalise(out)


def load_bundle(path: str | os.PathLike[str]) -> Bundle:
    root = Path(path)
    mf = root / MANIFEST
    if not mf.is_file():
        raise GoiError(f"--bundle: {root} has no {MANIFEST}")
    manifest = read_json(mf)
    validate_json(manifest, "goi.bundle", str(mf))
    if "image_encoder" not in manifest and "text_encoder" not in manifest:
        raise GoiError(f"{mf}: needs at least one of 'image_encoder' and 'text_encoder'")
    if "res" in manifest and "text_encoder" not in manifest:
        raise GoiError(f"{mf}: 'res' uses the text encoder's tokenizer; add 'text_encoder'")
    for key in ("image_encoder", "res"):
        spec = manifest.get(key)
        if spec is None:
            continue
        for stat in ("mean", "std"):
            if len(spec[stat]) != 3:
                raise GoiError(f"{mf}: field '{key}.{stat}' needs 3 numbers")
        if spec["channel_order"].upper() not in ("RGB", "BGR"):
            raise GoiError(f"{mf}: field '{key}.channel_order' must be RGB or BGR")
    return Bundle(root, manifest)

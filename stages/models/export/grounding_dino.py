"""A Grounding DINO checkpoint (transformers GroundingDinoForObjectDetection) -> detector.onnx.

The graph: pixel_values [1, 3, H, W] float32 and pixel_mask [1, H, W] int64 on a canvas fixed
at export; input_ids, attention_mask, token_type_ids [1, L] int64 (L dynamic) -> logits
[1, Q, L] (pre-sigmoid token scores of the Q queries) and pred_boxes [1, Q, 4] (cx, cy, w, h
relative to the unpadded image).

Two parts of transformers' model do not export as they are; during the export only, they are
replaced by equivalents:
- the phrase-wise text attention mask and position ids
  (`generate_masks_with_special_tokens_and_transfer_map`) use torch.isin, cummax and cummin,
  which the TorchScript exporter cannot convert: `text_masks` computes the same from an L x L
  comparison (tested equal on random id sequences);
- traced sizes make `get_reference_points` compute in float64, and onnxruntime has no float64
  GridSample: the reference points are cast back to the model's dtype.
The canvas must be fixed: with traced sizes the per-level feature-map shapes are baked into the
graph (a dynamic H, W exports but is silently wrong at any other size).
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from stages.models import res_processing as rp
from stages.models.export.common import (
    check_detections,
    image_spec,
    image_stats,
    onnx_export,
    write_tokenizer,
)

INPUTS = ("pixel_values", "pixel_mask", "input_ids", "attention_mask", "token_type_ids")
OUTPUTS = ("logits", "pred_boxes")


def text_masks(input_ids: Any, special_tokens: Any) -> tuple[Any, Any]:
    """transformers' generate_masks_with_special_tokens_and_transfer_map without isin, cummax
    and cummin: input_ids [B, L] -> (attention mask [B, L, L] bool, position ids [B, L]).

    Token i attends to token j when both lie in the same phrase (the same next delimiter, which
    is neither the first nor the last token), or i == j; position ids count from the previous
    delimiter."""
    import torch

    b, n = input_ids.shape
    special = (input_ids.unsqueeze(-1) == special_tokens.view(1, 1, -1)).any(-1)
    idx = torch.arange(n, device=input_ids.device)
    i, j = idx.view(1, n, 1), idx.view(1, 1, n)
    sp_j = special.unsqueeze(1)
    jj = j.expand(b, n, n)
    prev = torch.where(sp_j & (j < i), jj, torch.full_like(jj, -1)).amax(-1)
    nxt = torch.where(sp_j & (j >= i), jj, torch.full_like(jj, n)).amin(-1)
    valid = (nxt != 0) & (nxt != n - 1) & (nxt != n)
    att = (nxt.unsqueeze(2) == nxt.unsqueeze(1)) & valid.unsqueeze(1)
    # i == j, without torch.eye(dtype=bool): it exports to a bool EyeLike onnxruntime lacks
    att = att | (i == j)
    pos = idx.view(1, n) - prev - 1
    pos = torch.where(valid, pos, torch.zeros_like(pos)).clamp(min=0).to(torch.long)
    return att, pos


@contextlib.contextmanager
def export_patches() -> Iterator[None]:
    """Swap in the export-friendly text masks and float32 reference points while tracing."""
    from transformers.models.grounding_dino import modeling_grounding_dino as mg

    masks = mg.generate_masks_with_special_tokens_and_transfer_map
    ref = mg.GroundingDinoEncoder.get_reference_points

    def ref_points(shapes: Any, valid_ratios: Any, device: Any) -> Any:
        return ref(shapes, valid_ratios, device).to(valid_ratios.dtype)

    old_env = os.environ.get("TRANSFORMERS_DISABLE_TORCH_CHECK")
    os.environ["TRANSFORMERS_DISABLE_TORCH_CHECK"] = "1"
    mg.generate_masks_with_special_tokens_and_transfer_map = text_masks
    setattr(mg.GroundingDinoEncoder, "get_reference_points", staticmethod(ref_points))  # noqa: B010
    try:
        yield
    finally:
        mg.generate_masks_with_special_tokens_and_transfer_map = masks
        setattr(mg.GroundingDinoEncoder, "get_reference_points", staticmethod(ref))  # noqa: B010
        if old_env is None:
            os.environ.pop("TRANSFORMERS_DISABLE_TORCH_CHECK", None)
        else:
            os.environ["TRANSFORMERS_DISABLE_TORCH_CHECK"] = old_env


def detector_module(model: Any) -> Any:
    """The exported module: the optional arguments fixed, the logits cut from transformers'
    -inf-padded max_text_len columns back to the prompt's L tokens."""
    import torch

    class Detector(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.model = model

        def forward(
            self,
            pixel_values: torch.Tensor,
            pixel_mask: torch.Tensor,
            input_ids: torch.Tensor,
            attention_mask: torch.Tensor,
            token_type_ids: torch.Tensor,
        ) -> tuple[torch.Tensor, torch.Tensor]:
            out = self.model(
                pixel_values=pixel_values,
                input_ids=input_ids,
                token_type_ids=token_type_ids,
                attention_mask=attention_mask,
                pixel_mask=pixel_mask,
                return_dict=True,
            )
            return out.logits[:, :, : input_ids.shape[1]], out.pred_boxes

    return Detector().eval()


def check_image(h: int, w: int, seed: int = 0) -> np.ndarray:
    """A deterministic test card [h, w, 3] uint8: smooth gradients and a few solid blocks."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w]
    img = np.stack([x * 255 // max(w - 1, 1), y * 255 // max(h - 1, 1), (x + y) % 256], -1)
    for _ in range(6):
        y0, x0 = rng.integers(0, h * 3 // 4), rng.integers(0, w * 3 // 4)
        img[y0 : y0 + h // 4, x0 : x0 + w // 4] = rng.integers(0, 256, 3)
    return img.astype(np.uint8)


def export_detector(
    model: Any, src: Path, tmp: Path, tokenizer: str, canvas_hw: tuple[int, int], opset: int
) -> tuple[dict, dict]:
    """detector.onnx and its tokenizer; returns the manifest entry and the check's figures."""
    import torch

    max_length = int(model.config.max_text_len)
    tok, tokens = write_tokenizer(tokenizer, tmp, "detector_tokenizer.json", max_length, src)
    stats = image_stats(src, rp.IMAGENET_MEAN, rp.IMAGENET_STD)
    # the check's image has another aspect ratio than the canvas, so the padding is exercised
    ch, cw = canvas_hw
    rgb = check_image(max(16, ch * 3 // 4), cw)
    pixels, pmask = rp.detector_inputs(rgb, canvas_hw, stats["mean"], stats["std"])
    ids, att = tokens.encode(rp.detector_caption("a red chair. the green sofa"))
    feed = {
        "pixel_values": pixels,
        "pixel_mask": pmask,
        "input_ids": ids,
        "attention_mask": att,
        "token_type_ids": np.zeros_like(ids),
    }
    module = detector_module(model)
    args = tuple(torch.from_numpy(feed[k]) for k in INPUTS)
    with torch.no_grad():
        want = [t.numpy() for t in module(*args)]
    text_axes = {k: {1: "length"} for k in INPUTS[2:]}
    path = tmp / "detector.onnx"
    with export_patches():
        onnx_export(
            module, args, path, (INPUTS, OUTPUTS), {**text_axes, "logits": {2: "length"}}, opset
        )
    found = check_detections(path, feed, want)
    names = {k: k for k in INPUTS}
    spec = image_spec(
        "detector.onnx", [cw, ch], stats, **names, logits="logits", boxes="pred_boxes"
    )
    spec["tokenizer"] = tok
    return spec, found

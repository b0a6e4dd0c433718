"""A CLIPSeg checkpoint (transformers CLIPSegForImageSegmentation) -> res.onnx, a single-model
RES in the bundle's `res` slot.

The graph: pixel_values [1, 3, S, S] (S fixed at export: the checkpoint's processor size, 352
for CIDAS/clipseg-rd64-refined; the vision position embeddings are resampled to it inside the
graph) and input_ids, attention_mask [1, L] (CLIP's tokenizer, L dynamic) -> probs [1, 1, S, S],
the sigmoid of CLIPSeg's mask logits. goi resizes them to the image (bilinear) and keeps the
pixels above the manifest's threshold.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from stages.models import res_processing as rp
from stages.models.export.common import TEXT_AXES, export_checked, image_stats, write_tokenizer
from stages.models.export.grounding_dino import check_image
from stages.models.onnx_io import Tokens

#: CLIPSeg's processor size when preprocessor_config.json does not say.
DEFAULT_SIZE = 352


def res_module(model: Any) -> Any:
    import torch

    class Res(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.model = model

        def forward(
            self, pixel_values: torch.Tensor, input_ids: torch.Tensor, attention_mask: torch.Tensor
        ) -> torch.Tensor:
            logits = self.model(
                pixel_values=pixel_values, input_ids=input_ids, attention_mask=attention_mask
            ).logits
            b, _, h, w = pixel_values.shape
            return logits.reshape(b, 1, h, w).sigmoid()

    return Res().eval()


def processor_size(cfg: dict) -> int:
    size = cfg.get("size", DEFAULT_SIZE)
    if isinstance(size, dict):
        size = size.get("height") or size.get("shortest_edge") or DEFAULT_SIZE
    return int(size)


def export_clipseg(
    model: Any, src: Path, tmp: Path, tokenizer: str, threshold: float, opset: int
) -> dict:
    """res.onnx and its tokenizer; returns the manifest's `res` entry and the check."""
    tok, tokens, stats, size, pixels = export_inputs(model, src, tmp, tokenizer, "res")
    ids, att = tokens.encode("a red chair")
    feed = {"pixel_values": pixels, "input_ids": ids, "attention_mask": att}
    _, found = export_checked(
        res_module(model), [feed], tmp / "res.onnx", ["probs"], TEXT_AXES, opset
    )
    spec = {
        "file": "res.onnx",
        "image_input": "pixel_values",
        "input_ids": "input_ids",
        "attention_mask": "attention_mask",
        "output": "probs",
        "size": [size, size],
        "resize": "pil-bilinear",
        "mean": stats["mean"],
        "std": stats["std"],
        "channel_order": "RGB",
        "threshold": float(threshold),
        "tokenizer": tok,
    }
    return {"res": spec, "export_checks": {"res.onnx": found}}


def export_inputs(
    model: Any, src: Path, tmp: Path, tokenizer: str, prefix: str
) -> tuple[dict, Tokens, dict, int, np.ndarray]:
    """What a CLIPSeg export (whole or split) starts from: the tokenizer written as
    <prefix>_tokenizer.json (its manifest entry, and loaded), the image statistics, the input
    size S and the check's pixels [1, 3, S, S]."""
    max_length = int(model.config.text_config.max_position_embeddings)
    name = f"{prefix}_tokenizer.json"
    tok, tokens = write_tokenizer(tokenizer, tmp, name, max_length, src)
    # CIDAS's checkpoints list ImageNet's statistics in their preprocessor_config.json
    stats = image_stats(src, rp.IMAGENET_MEAN, rp.IMAGENET_STD)
    size = processor_size(stats["config"])
    mean, std = tuple(stats["mean"]), tuple(stats["std"])
    pixels = rp.square_inputs(check_image(size * 3 // 4, size), (size, size), mean, std)
    return tok, tokens, stats, size, pixels

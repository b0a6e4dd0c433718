"""A SAM checkpoint (transformers SamModel) -> sam_encoder.onnx + sam_decoder.onnx, the split
SAM's own release uses.

sam_encoder.onnx: pixel_values [1, 3, S, S] -> image_embeddings [1, 256, S/16, S/16], once per
image. sam_decoder.onnx: image_embeddings and input_boxes [1, B, 4] (x0, y0, x1, y1 in the
resized S frame; B dynamic) -> pred_masks [1, B, 1, S/4, S/4] mask logits, with
multimask_output=False (one mask per box, SAM's advice for box prompts). The prompt encoder is
inside the decoder graph; upscaling the masks to the image is numpy (res_processing), so the
graph does not depend on the image size. Points and mask prompts are not exported.

At an input S other than the checkpoint's own (1024), the absolute position embeddings are
resampled (bicubic) to the S/16 grid; the relative position tables of the global-attention
blocks are resampled by the model itself (linear, as in SAM's code). SAM was not trained at
other sizes: this trades mask quality, unmeasured here, for speed.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from stages.core.errors import GoiError
from stages.models import res_processing as rp
from stages.models.export.common import export_checked, image_spec, image_stats
from stages.models.export.grounding_dino import check_image


def resize_input(model: Any, size: int) -> None:
    """Make a SamModel take S x S images (S a multiple of the patch size), in place."""
    import torch
    import torch.nn.functional as F

    vcfg = model.config.vision_config
    patch = int(vcfg.patch_size)
    if size % patch:
        raise GoiError(f"--sam-size: {size} is not a multiple of SAM's patch size {patch}")
    grid = size // patch
    enc = model.vision_encoder
    if enc.pos_embed is not None:
        pos = enc.pos_embed.detach().permute(0, 3, 1, 2)  # [1, C, g, g]
        pos = F.interpolate(pos, size=(grid, grid), mode="bicubic", align_corners=False)
        enc.pos_embed = torch.nn.Parameter(pos.permute(0, 2, 3, 1).contiguous(), False)
    enc.image_size = size
    enc.patch_embed.image_size = (size, size)
    vcfg.image_size = size
    pcfg = model.config.prompt_encoder_config
    pcfg.image_size = size
    pcfg.image_embedding_size = grid
    model.prompt_encoder.input_image_size = size
    model.prompt_encoder.image_embedding_size = (grid, grid)


def modules(model: Any) -> tuple[Any, Any]:
    import torch

    class Encoder(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.model = model

        def forward(self, pixel_values: torch.Tensor) -> torch.Tensor:
            out: torch.Tensor = self.model.get_image_embeddings(pixel_values)
            return out

    class Decoder(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.model = model

        def forward(
            self, image_embeddings: torch.Tensor, input_boxes: torch.Tensor
        ) -> tuple[torch.Tensor, torch.Tensor]:
            out = self.model(
                image_embeddings=image_embeddings, input_boxes=input_boxes, multimask_output=False
            )
            return out.pred_masks, out.iou_scores

    return Encoder().eval(), Decoder().eval()


def export_split(
    encoder: Any,
    decoder: Any,
    pixels: np.ndarray,
    image_hw: tuple[int, int],
    to_frame: Callable[[np.ndarray, tuple[int, int], int], np.ndarray],
    maps: tuple[str, ...],
    tmp: Path,
    opset: int,
    fuse_encoder: Callable[[Path], int] | None = None,
) -> dict:
    """sam_encoder.onnx (pixel_values -> the image-side `maps`) and sam_decoder.onnx (the maps
    and input_boxes [1, B, 4], B dynamic -> pred_masks, iou_scores), each run in onnxruntime
    against torch on a test card (`pixels`, of an image `image_hw`) and on 2 and 1 boxes put in
    the encoder's frame by `to_frame`; returns the checks. SAM's and SAM 2's split.
    `fuse_encoder`: the encoder's attention rewrite (`export_checked`'s `fuse`)."""
    size = int(pixels.shape[-1])
    checks = {}
    (image_side,), checks["sam_encoder.onnx"] = export_checked(
        encoder, [{"pixel_values": pixels}], tmp / "sam_encoder.onnx", maps, {}, opset, fuse_encoder
    )
    boxes = np.asarray([[10, 20, 300, 240], [200, 100, 620, 470]], np.float32) * (size / 1024)
    feed_maps = dict(zip(maps, image_side, strict=True))
    feeds = [{**feed_maps, "input_boxes": to_frame(boxes[:n], image_hw, size)} for n in (2, 1)]
    axes = {"input_boxes": {1: "boxes"}, "pred_masks": {1: "boxes"}, "iou_scores": {1: "boxes"}}
    _, checks["sam_decoder.onnx"] = export_checked(
        decoder, feeds, tmp / "sam_decoder.onnx", ["pred_masks", "iou_scores"], axes, opset
    )
    return checks


def export_sam(model: Any, src: Path, tmp: Path, size: int, opset: int) -> tuple[dict, dict, dict]:
    """sam_encoder.onnx and sam_decoder.onnx; returns their manifest entries and the checks."""

    native = int(model.config.vision_config.image_size)
    size = size or native
    if size != native:
        resize_input(model, size)
    stats = image_stats(src, rp.IMAGENET_MEAN, rp.IMAGENET_STD)
    encoder, decoder = modules(model)
    rgb = check_image(size * 3 // 4, size, seed=1)
    pixels = rp.sam_inputs(rgb, size, stats["mean"], stats["std"])
    checks = export_split(
        encoder, decoder, pixels, rgb.shape[:2], rp.sam_boxes, ("image_embeddings",), tmp, opset
    )
    enc_spec = image_spec(
        "sam_encoder.onnx", [size, size], stats, input="pixel_values", output="image_embeddings"
    )
    dec_spec = {
        "file": "sam_decoder.onnx",
        "image_embeddings": "image_embeddings",
        "boxes": "input_boxes",
        "masks": "pred_masks",
    }
    return enc_spec, dec_spec, checks

"""A SAM 2 checkpoint (transformers Sam2Model, e.g. facebook/sam2.1-hiera-tiny) ->
sam_encoder.onnx + sam_decoder.onnx, split like SAM's (layout `sam2`).

sam_encoder.onnx: pixel_values [1, 3, S, S] (S = 1024; the image squashed to the square, see
`res_processing.sam2_inputs`) -> image_embeddings [1, 256, S/16, S/16] (the no-memory embedding
already added, as Sam2Model.get_image_embeddings does for a single image) and the two
high-resolution maps its mask decoder adds back while upscaling, high_res_feat_s0
[1, 32, S/4, S/4] and high_res_feat_s1 [1, 64, S/8, S/8]. Once per image: the image side.
sam_decoder.onnx: those three maps and input_boxes [1, B, 4] (x0, y0, x1, y1 in the S x S
frame; B dynamic) -> pred_masks [1, B, 1, S/4, S/4] mask logits and iou_scores [1, B, 1], with
multimask_output=False: SAM 2's single-mask answer, which falls back to the most stable of its
three other masks when the single one is unstable (`dynamic_multimask_via_stability`, as the
checkpoint configures it). Upscaling to the image is numpy (`res_processing.sam2_mask_logits`).

SAM 2's input size is fixed: its Hiera backbone's window position embeddings and the feature
map sizes are tied to it, so --sam-size does not apply.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from stages.models import res_processing as rp
from stages.models.export.attention import fuse_hiera_attention
from stages.models.export.common import image_spec, image_stats
from stages.models.export.grounding_dino import check_image
from stages.models.export.sam import export_split

#: The encoder's outputs, the embedding first, then the high-resolution maps, finer first.
ENCODER_OUTPUTS = ("image_embeddings", "high_res_feat_s0", "high_res_feat_s1")


def input_size(config: dict) -> int:
    """The square input side S of a Sam2Model config.json."""
    bb = (config.get("vision_config") or {}).get("backbone_config") or {}
    size = bb.get("image_size", 1024)
    return int(size[0] if isinstance(size, list) else size)


def modules(model: Any) -> tuple[Any, Any]:
    import torch

    class Encoder(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.model = model

        def forward(self, pixel_values: torch.Tensor) -> tuple[torch.Tensor, ...]:
            s0, s1, emb = self.model.get_image_embeddings(pixel_values)
            return emb, s0, s1

    class Decoder(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.model = model

        def forward(
            self,
            image_embeddings: torch.Tensor,
            high_res_feat_s0: torch.Tensor,
            high_res_feat_s1: torch.Tensor,
            input_boxes: torch.Tensor,
        ) -> tuple[torch.Tensor, torch.Tensor]:
            out = self.model(
                image_embeddings=[high_res_feat_s0, high_res_feat_s1, image_embeddings],
                input_boxes=input_boxes,
                multimask_output=False,
            )
            return out.pred_masks, out.iou_scores

    return Encoder().eval(), Decoder().eval()


def export_sam2(model: Any, src: Path, tmp: Path, opset: int) -> tuple[dict, dict, dict]:
    """sam_encoder.onnx and sam_decoder.onnx; returns their manifest entries and the checks."""
    size = input_size(model.config.to_dict())
    stats = image_stats(src, rp.IMAGENET_MEAN, rp.IMAGENET_STD)
    encoder, decoder = modules(model)
    rgb = check_image(size * 3 // 4, size, seed=1)
    pixels = rp.sam2_inputs(rgb, size, stats["mean"], stats["std"])
    checks = export_split(
        encoder,
        decoder,
        pixels,
        rgb.shape[:2],
        rp.sam2_boxes,
        ENCODER_OUTPUTS,
        tmp,
        opset,
        fuse_encoder=fuse_hiera_attention,
    )
    enc_spec = image_spec(
        "sam_encoder.onnx",
        [size, size],
        stats,
        input="pixel_values",
        output=ENCODER_OUTPUTS[0],
        high_res=list(ENCODER_OUTPUTS[1:]),
    )
    dec_spec = {
        "file": "sam_decoder.onnx",
        "layout": "sam2",
        "image_embeddings": ENCODER_OUTPUTS[0],
        "high_res": list(ENCODER_OUTPUTS[1:]),
        "boxes": "input_boxes",
        "masks": "pred_masks",
    }
    return enc_spec, dec_spec, checks

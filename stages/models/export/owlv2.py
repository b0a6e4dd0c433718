"""An OWLv2 checkpoint (transformers Owlv2ForObjectDetection, e.g.
google/owlv2-base-patch16-ensemble) -> owl_image.onnx + owl_text.onnx: the detector split at the
one place its text meets the image, a dot product after the ViT and the heads.

owl_image.onnx (the image side, once per image): pixel_values [1, 3, S, S] (S = 960 for the
base checkpoints) -> class_embeds [1, P, D] (the class head's per-patch embeddings, already
divided by their norm + 1e-6, as the head does), logit_shift [1, P], logit_scale [1, P] (the
head's elu(.) + 1), pred_boxes [1, P, 4] (cx, cy, w, h relative to the padded square image) and
objectness [1, P] (logits), with P = (S/16)^2 patches.
owl_text.onnx (the prompt side, once per prompt): input_ids, attention_mask [1, L] (CLIP's
tokenizer, at most 16 tokens) -> query_embeds [1, D], the query embedding as the class head
uses it (projected, normalised, then divided by its norm + 1e-6).
The class logits, (class_embeds . query + shift) x scale, and their sigmoid are numpy
(`res_processing.owl_logits`), tested equal to transformers' post-processing.
"""

from __future__ import annotations

from functools import partial
from pathlib import Path
from typing import Any

from stages.models import res_processing as rp
from stages.models.export.attention import fuse_attention
from stages.models.export.common import (
    export_checked,
    export_text_graph,
    image_spec,
    image_stats,
    write_tokenizer,
)
from stages.models.export.grounding_dino import check_image

IMAGE_OUTPUTS = ("class_embeds", "logit_shift", "logit_scale", "pred_boxes", "objectness")
#: OWLv2's processor statistics (CLIP's), when preprocessor_config.json does not say.
CLIP_MEAN = (0.48145466, 0.4578275, 0.40821073)
CLIP_STD = (0.26862954, 0.26130258, 0.27577711)


def modules(model: Any) -> tuple[Any, Any]:
    import torch

    class Image(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.model = model

        def forward(self, pixel_values: torch.Tensor) -> tuple[torch.Tensor, ...]:
            m = self.model
            feature_map = m.image_embedder(pixel_values=pixel_values)[0]  # [1, g, g, C]
            b, gh, gw, c = feature_map.shape
            feats = feature_map.reshape(b, gh * gw, c)
            head = m.class_head
            cls = head.dense0(feats)
            cls = cls / (torch.linalg.norm(cls, dim=-1, keepdim=True) + 1e-6)
            shift = head.logit_shift(feats)[..., 0]
            scale = (head.elu(head.logit_scale(feats)) + 1)[..., 0]
            boxes = m.box_predictor(feats, feature_map)
            objectness = m.objectness_predictor(feats)
            return cls, shift, scale, boxes, objectness

    class Text(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.model = model

        def forward(self, input_ids: torch.Tensor, attention_mask: torch.Tensor) -> torch.Tensor:
            owl = self.model.owlv2
            pooled = owl.text_model(input_ids=input_ids, attention_mask=attention_mask)
            q = owl.text_projection(pooled.pooler_output)
            q = q / torch.linalg.norm(q, ord=2, dim=-1, keepdim=True)  # Owlv2Model's text_embeds
            out: torch.Tensor = q / (torch.linalg.norm(q, dim=-1, keepdim=True) + 1e-6)
            return out

    return Image().eval(), Text().eval()


def export_owlv2(model: Any, src: Path, tmp: Path, tokenizer: str, opset: int) -> tuple[dict, dict]:
    """owl_image.onnx, owl_text.onnx and the tokenizer; returns the manifest's `owl` entry
    and the checks."""
    size = int(model.config.vision_config.image_size)
    max_length = int(model.config.text_config.max_position_embeddings)
    tok, tokens = write_tokenizer(tokenizer, tmp, "owl_tokenizer.json", max_length, src)
    stats = image_stats(src, CLIP_MEAN, CLIP_STD)
    image, text = modules(model)
    pixels = rp.owl_inputs(check_image(size * 3 // 4, size), size, stats["mean"], stats["std"])
    checks = {}
    vision = model.config.vision_config
    heads, width = int(vision.num_attention_heads), int(vision.hidden_size)
    (want,), checks["owl_image.onnx"] = export_checked(
        image,
        [{"pixel_values": pixels}],
        tmp / "owl_image.onnx",
        IMAGE_OUTPUTS,
        {},
        opset,
        fuse=partial(fuse_attention, num_heads=heads, hidden=width),
    )
    _, checks["owl_text.onnx"] = export_text_graph(
        text, tokens, tmp / "owl_text.onnx", "query_embeds", opset
    )
    spec = {
        "image": image_spec("owl_image.onnx", [size, size], stats),
        "text": {"file": "owl_text.onnx", "tokenizer": tok},
        "dim": int(want[0].shape[-1]),
        "patches": int(want[0].shape[1]),
    }
    return spec, checks

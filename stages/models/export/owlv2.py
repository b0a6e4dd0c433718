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

from pathlib import Path
from typing import Any

from stages.models import res_processing as rp
from stages.models.export.common import check, image_stats, onnx_export, write_tokenizer
from stages.models.export.grounding_dino import check_image
from stages.models.onnx_io import Tokens

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
    import torch

    size = int(model.config.vision_config.image_size)
    max_length = int(model.config.text_config.max_position_embeddings)
    tok = write_tokenizer(tokenizer, tmp, "owl_tokenizer.json", max_length)
    tokens = Tokens(tmp / "owl_tokenizer.json", max_length, str(src))
    stats = image_stats(src, CLIP_MEAN, CLIP_STD)
    image, text = modules(model)
    pixels = rp.owl_inputs(check_image(size * 3 // 4, size), size, stats["mean"], stats["std"])
    with torch.no_grad():
        want = [t.numpy() for t in image(torch.from_numpy(pixels))]
    img_path = tmp / "owl_image.onnx"
    onnx_export(image, (torch.from_numpy(pixels),), img_path, (["pixel_values"], IMAGE_OUTPUTS),
                {}, opset)  # fmt: skip
    checks = {"owl_image.onnx": check(img_path, {"pixel_values": pixels}, want)}
    feeds = [tokens.encode(t) for t in ("a red chair", "the lamp")]
    with torch.no_grad():
        wants = [[text(*map(torch.from_numpy, f)).numpy()] for f in feeds]
    txt_path = tmp / "owl_text.onnx"
    axes = {"input_ids": {1: "length"}, "attention_mask": {1: "length"}}
    onnx_export(text, tuple(map(torch.from_numpy, feeds[0])), txt_path,
                (["input_ids", "attention_mask"], ["query_embeds"]), axes, opset)  # fmt: skip
    found = [
        check(txt_path, {"input_ids": f[0], "attention_mask": f[1]}, w)
        for f, w in zip(feeds, wants, strict=True)
    ]
    checks["owl_text.onnx"] = {k: max(f[k] for f in found) for k in found[0]}
    spec = {
        "image": {"file": "owl_image.onnx", "size": [size, size], "mean": stats["mean"],
                  "std": stats["std"]},
        "text": {"file": "owl_text.onnx", "tokenizer": tok},
        "dim": int(want[0].shape[-1]),
        "patches": int(want[0].shape[1]),
    }  # fmt: skip
    return spec, checks

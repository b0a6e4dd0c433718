"""A CLIP checkpoint -> a dense MaskCLIP image encoder and the text encoder.

MaskCLIP keeps, in the last transformer block, only the value path of every token (q and k are
dropped, so each token attends to itself), then the final layer norm and the projection. That
turns the class-token head into a per-patch head whose features live in the text space, which
is what pixel-aligned language features need.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from stages.core.errors import GoiError
from stages.models.export.common import (
    check,
    export_text_graph,
    image_stats,
    onnx_export,
    write_tokenizer,
)
from stages.models.onnx_io import Tokens

# OpenAI CLIP's preprocessing, used when the checkpoint has no preprocessor_config.json.
CLIP_MEAN = [0.48145466, 0.4578275, 0.40821073]
CLIP_STD = [0.26862954, 0.26130258, 0.27577711]


class DenseCLIP:
    """Builds the torch module of the MaskCLIP image encoder from a transformers CLIPModel."""

    @staticmethod
    def build(model: Any, image_size: int) -> Any:
        import torch
        import torch.nn.functional as F

        vm = model.vision_model

        class Dense(torch.nn.Module):
            def __init__(self) -> None:
                super().__init__()
                self.emb = vm.embeddings
                self.pre = vm.pre_layrnorm
                self.blocks = torch.nn.ModuleList(vm.encoder.layers[:-1])
                self.last = vm.encoder.layers[-1]
                self.post = vm.post_layernorm
                self.proj = model.visual_projection
                self.patch = int(vm.embeddings.patch_size)
                self.grid = image_size // self.patch
                pos = vm.embeddings.position_embedding.weight.detach()  # [1 + g0*g0, C]
                g0 = int(round((pos.shape[0] - 1) ** 0.5))
                grid = pos[1:].reshape(1, g0, g0, -1).permute(0, 3, 1, 2)
                if g0 != self.grid:
                    grid = F.interpolate(
                        grid, size=(self.grid, self.grid), mode="bicubic", align_corners=False
                    )
                grid = grid.permute(0, 2, 3, 1).reshape(self.grid * self.grid, -1)
                self.register_buffer("pos", torch.cat([pos[:1], grid])[None])  # [1, 1+g*g, C]

            def tokens(self, image: torch.Tensor) -> torch.Tensor:
                """[1, 3, H, W] -> the tokens entering the last block [1, 1+g*g, C]."""
                x = self.emb.patch_embedding(image).flatten(2).transpose(1, 2)
                cls = self.emb.class_embedding.reshape(1, 1, -1).expand(x.shape[0], 1, -1)
                pos: torch.Tensor = self.pos  # type: ignore[assignment]
                x = self.pre(torch.cat([cls, x], 1) + pos)
                for block in self.blocks:
                    x = block(x, None)
                return x

            def last_block(self, x: torch.Tensor, value_only: bool) -> torch.Tensor:
                attn = self.last.self_attn
                h = self.last.layer_norm1(x)
                a = attn.out_proj(attn.v_proj(h)) if value_only else attn(h, None)[0]
                x = x + a
                mlp: torch.Tensor = self.last.mlp(self.last.layer_norm2(x))
                return x + mlp

            def head(self, x: torch.Tensor) -> torch.Tensor:
                return self.proj(self.post(x))

            def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
                x = self.tokens(image)
                dense = self.head(self.last_block(x, True)[:, 1:])  # [1, g*g, D]
                pooled = self.head(self.last_block(x, False)[:, 0])  # [1, D]
                d = dense.transpose(1, 2).reshape(x.shape[0], -1, self.grid, self.grid)
                return d, pooled

        return Dense().eval()


def text_spec(tokenizer: dict) -> dict:
    return {
        "file": "text_encoder.onnx",
        "input_ids": "input_ids",
        "attention_mask": "attention_mask",
        "output": "text_embeds",
        "tokenizer": tokenizer,
    }


def export_text(module: Any, tmp: Path, tokens: Tokens, opset: int) -> dict:
    """text_encoder.onnx from a torch module (input_ids, attention_mask) -> [1, D]."""
    path = tmp / "text_encoder.onnx"
    texts = ["a small red chair by the sofa"]
    return export_text_graph(module, tokens, path, "text_embeds", opset, texts)[1]


def export_clip(
    model: Any, src: Path, tmp: Path, tokenizer: str, image_size: int, opset: int
) -> dict:
    """The manifest entries (image_encoder, text_encoder, feature_dim) of a CLIP model."""
    import torch

    vcfg = model.config.vision_config
    size = image_size or int(vcfg.image_size)
    if size % int(vcfg.patch_size):
        raise GoiError(
            f"--image-size: {size} is not a multiple of the patch size {vcfg.patch_size}"
        )
    dense = DenseCLIP.build(model, size)
    image = torch.randn(1, 3, size, size, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        want = [t.numpy() for t in dense(image)]
    path = tmp / "image_encoder.onnx"
    onnx_export(dense, (image,), path, (["image"], ["features", "image_embeds"]), {}, opset)
    checks = {"image_encoder.onnx": check(path, {"image": image.numpy()}, want)}

    class Text(torch.nn.Module):
        def forward(self, input_ids: torch.Tensor, attention_mask: torch.Tensor) -> torch.Tensor:
            out = model.get_text_features(input_ids=input_ids, attention_mask=attention_mask)
            return out if isinstance(out, torch.Tensor) else out.pooler_output

    max_length = int(model.config.text_config.max_position_embeddings)
    tok, tokens = write_tokenizer(tokenizer, tmp, "tokenizer.json", max_length, src)
    checks["text_encoder.onnx"] = export_text(Text().eval(), tmp, tokens, opset)
    stats = image_stats(src, CLIP_MEAN, CLIP_STD)
    return {
        "feature_dim": int(model.config.projection_dim),
        "image_encoder": {
            "file": "image_encoder.onnx",
            "input": "image",
            "output": "features",
            "size": [size, size],
            "mean": stats["mean"],
            "std": stats["std"],
            "channel_order": "RGB",
        },
        "text_encoder": text_spec(tok),
        "export_checks": checks,
    }

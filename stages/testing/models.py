"""Randomly initialised RES checkpoints for tests and benchmarks: Grounding DINO, OWLv2, SAM,
SAM 2 and CLIPSeg, tiny (seconds to export) or at the real checkpoints' configurations (the
real cost).

    python -m stages.testing.models --bundle OUT

writes the tests' tiny Grounded-SAM as a model bundle with RANDOM weights (about a minute, no
download), for trying `goi index-res` and the `--bundle` / `--res-index` paths on a scene: its
masks mean nothing.

Checkpoints are written as Hugging Face directories (config.json, model.safetensors,
tokenizer.json, preprocessor_config.json), so they go through `goi export-model` exactly as a
downloaded one does. Weights are redrawn by `realistic_init`: transformers' own initialisation
makes some models numerically degenerate (SAM's image embeddings come out near 1e-21), which
would make any comparison of outputs meaningless. Needs torch, transformers and tokenizers.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path
from typing import Any

from stages.core.errors import GoiError
from stages.core.report import Lines

#: The tiny Grounded-SAM bundle's export settings (the tests' and the random bundle's).
GROUNDED: dict[str, Any] = {
    "canvas": (96, 128),
    "box_threshold": 0.5,
    "max_boxes": 3,
    "mask_threshold": 0.0,
}
#: OWLv2's processor statistics (CLIP's).
OWL_STATS = {
    "image_mean": [0.48145466, 0.4578275, 0.40821073],
    "image_std": [0.26862954, 0.26130258, 0.27577711],
}
IMAGENET = {"image_mean": [0.485, 0.456, 0.406], "image_std": [0.229, 0.224, 0.225]}
#: The words of the test tokenizers; the detector's sit at bert-base-uncased's special ids.
WORDS = ["a", "the", "red", "green", "blue", "chair", "sofa", "box", "table", "lamp", "on", "of"]
BERT_SPECIAL = {"[PAD]": 0, "[UNK]": 100, "[CLS]": 101, "[SEP]": 102, ".": 1012, "?": 1029}


def realistic_init(model: Any, seed: int = 0, skip: tuple[str, ...] = ()) -> Any:
    """Redraw every weight so activations stay O(1): matrices and kernels N(0, 1/fan_in),
    embeddings N(0, 1), norm scales 1 + N(0, 0.1), other vectors N(0, 0.1). Parameters whose
    name contains one of `skip` keep their values."""
    import torch

    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in model.named_parameters():
            if any(s in name for s in skip):
                continue
            if p.ndim >= 2:
                embedding = "embed" in name and p.ndim == 2 and "proj" not in name
                std = 1.0 if embedding else (1.0 / max(p[0].numel(), 1)) ** 0.5
                p.copy_(torch.randn(p.shape, generator=g) * std)
            elif "norm" in name.lower() and name.endswith("weight"):
                p.copy_(1.0 + 0.1 * torch.randn(p.shape, generator=g))
            else:
                p.copy_(0.1 * torch.randn(p.shape, generator=g))
    return model


def _tokenizer(vocab: dict[str, int], bos: str, eos: str, lower: bool) -> Any:
    from tokenizers import Tokenizer, models, normalizers, pre_tokenizers, processors

    tok = Tokenizer(models.WordLevel(vocab, unk_token="[UNK]" if "[UNK]" in vocab else "<unk>"))
    if lower:
        tok.normalizer = normalizers.Lowercase()
    tok.pre_tokenizer = pre_tokenizers.BertPreTokenizer()
    tok.post_processor = processors.TemplateProcessing(
        single=f"{bos} $A {eos}", special_tokens=[(bos, vocab[bos]), (eos, vocab[eos])]
    )
    return tok


def bert_tokenizer() -> Any:
    """A word-level stand-in for bert-base-uncased: [CLS] ... [SEP], '.' at id 1012."""
    vocab = dict(BERT_SPECIAL)
    vocab.update({w: 200 + i for i, w in enumerate(WORDS)})
    return _tokenizer(vocab, "[CLS]", "[SEP]", lower=True)


def clip_tokenizer(vocab_size: int) -> Any:
    """A word-level stand-in for CLIP's tokenizer: <bos> ... <eos> at the vocabulary's end."""
    vocab = {"<pad>": 0, "<unk>": 1, ".": 2}
    vocab.update({w: 3 + i for i, w in enumerate(WORDS)})
    vocab.update({"<bos>": vocab_size - 2, "<eos>": vocab_size - 1})
    return _tokenizer(vocab, "<bos>", "<eos>", lower=True)


def grounding_dino(real: bool = False, seed: int = 0) -> Any:
    """GroundingDinoForObjectDetection: tiny, or IDEA-Research/grounding-dino-tiny's config
    (Swin-T + BERT-base, d_model 256, 900 queries, 6 + 6 layers; transformers' defaults)."""
    import torch
    from transformers import (
        BertConfig,
        GroundingDinoConfig,
        GroundingDinoForObjectDetection,
        SwinConfig,
    )

    levels: dict[str, Any] = {
        "out_indices": [2, 3, 4],
        "out_features": ["stage2", "stage3", "stage4"],
    }
    if real:
        swin = SwinConfig(
            embed_dim=96, depths=[2, 2, 6, 2], num_heads=[3, 6, 12, 24], window_size=7,
            image_size=224, **levels,
        )  # fmt: skip
        cfg = GroundingDinoConfig(backbone_config=swin, text_config=BertConfig())
    else:
        swin = SwinConfig(
            embed_dim=16, depths=[1, 1, 1, 1], num_heads=[1, 1, 2, 2], window_size=4,
            image_size=64, **levels,
        )  # fmt: skip
        bert = BertConfig(
            vocab_size=1100, hidden_size=32, num_hidden_layers=1, num_attention_heads=2,
            intermediate_size=64, max_position_embeddings=64,
        )  # fmt: skip
        cfg = GroundingDinoConfig(
            backbone_config=swin, text_config=bert, d_model=32, num_queries=30,
            encoder_layers=1, decoder_layers=2, encoder_ffn_dim=64, decoder_ffn_dim=64,
            encoder_attention_heads=4, decoder_attention_heads=4, max_text_len=32,
        )  # fmt: skip
    torch.manual_seed(seed)
    model = GroundingDinoForObjectDetection._from_config(cfg, attn_implementation="eager").eval()
    realistic_init(model, seed)
    with torch.no_grad():  # small box refinements, as a trained detector has; else all saturate
        for name, p in model.named_parameters():
            if "bbox_embed" in name and ".layers.2." in name:
                p.mul_(0.01)
    return model


def sam(real: bool = False, image_size: int = 128, seed: int = 0) -> Any:
    """SamModel: tiny (at `image_size`), or facebook/sam-vit-base's config (ViT-B, 1024)."""
    import torch
    from transformers import (
        SamConfig,
        SamMaskDecoderConfig,
        SamModel,
        SamPromptEncoderConfig,
        SamVisionConfig,
    )

    if real:
        cfg = SamConfig(
            vision_config=SamVisionConfig(
                hidden_size=768, num_hidden_layers=12, num_attention_heads=12,
                global_attn_indexes=[2, 5, 8, 11],
            )
        )  # fmt: skip
    else:
        vision = SamVisionConfig(
            hidden_size=32, num_hidden_layers=2, num_attention_heads=2, mlp_dim=64,
            image_size=image_size, patch_size=16, window_size=4, global_attn_indexes=[1],
            output_channels=32, num_pos_feats=16,
        )  # fmt: skip
        prompt = SamPromptEncoderConfig(
            hidden_size=32, image_size=image_size, patch_size=16, mask_input_channels=4
        )
        dec = SamMaskDecoderConfig(
            hidden_size=32, mlp_dim=64, num_attention_heads=2, iou_head_hidden_dim=32
        )
        cfg = SamConfig(vision_config=vision, prompt_encoder_config=prompt, mask_decoder_config=dec)
    torch.manual_seed(seed)
    model = SamModel._from_config(cfg, attn_implementation="eager").eval()
    return realistic_init(model, seed, skip=("positional_embedding",))


def sam2(real: bool = False, image_size: int = 128, seed: int = 0) -> Any:
    """Sam2Model: tiny (at `image_size`, a multiple of 32), or facebook/sam2.1-hiera-tiny's
    config (transformers' default Sam2Config: Hiera with 96 channels, blocks [1, 2, 7, 2],
    at 1024)."""
    import torch
    from transformers import Sam2Config, Sam2Model
    from transformers.models.sam2.configuration_sam2 import (
        Sam2HieraDetConfig,
        Sam2MaskDecoderConfig,
        Sam2PromptEncoderConfig,
        Sam2VisionConfig,
    )

    if real:
        cfg = Sam2Config()
    else:
        s = image_size
        hiera = Sam2HieraDetConfig(
            hidden_size=16, image_size=[s, s], blocks_per_stage=[1, 1, 2, 1],
            embed_dim_per_stage=[16, 32, 64, 128], num_attention_heads_per_stage=[1, 1, 2, 2],
            window_size_per_stage=[4, 4, 4, 2], global_attention_blocks=[3],
            window_positional_embedding_background_size=[2, 2],
        )  # fmt: skip
        vision = Sam2VisionConfig(
            backbone_config=hiera, backbone_channel_list=[128, 64, 32, 16],
            backbone_feature_sizes=[[s // 4] * 2, [s // 8] * 2, [s // 16] * 2],
            fpn_hidden_size=32,
        )  # fmt: skip
        prompt = Sam2PromptEncoderConfig(
            hidden_size=32, image_size=s, patch_size=16, mask_input_channels=4
        )
        dec = Sam2MaskDecoderConfig(
            hidden_size=32, mlp_dim=64, num_attention_heads=2, iou_head_hidden_dim=32
        )
        cfg = Sam2Config(
            vision_config=vision, prompt_encoder_config=prompt, mask_decoder_config=dec
        )
    torch.manual_seed(seed)
    model = Sam2Model._from_config(cfg, attn_implementation="eager").eval()
    return realistic_init(model, seed, skip=("positional_embedding",))


def tiny_towers(
    layers: int, image_size: int, patch: int = 16, vocab: int = 100, bos: int = 98, eos: int = 99
) -> tuple[dict, dict]:
    """A tiny CLIP's text and vision tower configs (32 wide, 4 heads, 16 tokens), as CLIP,
    CLIPSeg and OWLv2 configs take them."""
    width = dict(hidden_size=32, intermediate_size=64, num_hidden_layers=layers)
    text = dict(
        vocab_size=vocab, **width, num_attention_heads=4, max_position_embeddings=16,
        bos_token_id=bos, eos_token_id=eos, pad_token_id=0,
    )  # fmt: skip
    vision = dict(**width, num_attention_heads=4, image_size=image_size, patch_size=patch)
    return text, vision


def clipseg(real: bool = False, seed: int = 0) -> Any:
    """CLIPSegForImageSegmentation: tiny, or CIDAS/clipseg-rd64-refined's config (CLIP
    ViT-B/16 + CLIP's text tower, reduce_dim 64, the refined transposed convolution)."""
    import torch
    from transformers import CLIPSegConfig, CLIPSegForImageSegmentation

    if real:
        cfg = CLIPSegConfig(
            vision_config=dict(
                hidden_size=768, intermediate_size=3072, num_hidden_layers=12,
                num_attention_heads=12, image_size=224, patch_size=16,
            ),
            text_config=dict(),
            projection_dim=512, extract_layers=[3, 6, 9], reduce_dim=64,
            use_complex_transposed_convolution=True,
        )  # fmt: skip
    else:
        text, vision = tiny_towers(layers=3, image_size=32)
        cfg = CLIPSegConfig(
            text_config=text, vision_config=vision, projection_dim=16, extract_layers=[0, 1, 2],
            reduce_dim=16,
            decoder_num_attention_heads=2, decoder_intermediate_size=32,
            use_complex_transposed_convolution=True,
        )  # fmt: skip
    torch.manual_seed(seed)
    model = CLIPSegForImageSegmentation._from_config(cfg, attn_implementation="eager").eval()
    return realistic_init(model, seed)


def owlv2(real: bool = False, seed: int = 0) -> Any:
    """Owlv2ForObjectDetection: tiny (64 px, 16 patches), or
    google/owlv2-base-patch16-ensemble's config (ViT-B/16 at 960, CLIP's text tower, 16 tokens)."""
    import torch
    from transformers import Owlv2Config, Owlv2ForObjectDetection

    if real:
        cfg = Owlv2Config(
            text_config=dict(max_position_embeddings=16),
            vision_config=dict(image_size=960, patch_size=16),
        )
    else:
        text, vision = tiny_towers(layers=2, image_size=64)
        cfg = Owlv2Config(text_config=text, vision_config=vision, projection_dim=32)
    torch.manual_seed(seed)
    model = Owlv2ForObjectDetection._from_config(cfg, attn_implementation="eager").eval()
    return realistic_init(model, seed)


def clip_vit_b16(seed: int = 0) -> Any:
    """CLIPModel at openai/clip-vit-base-patch16's configuration (the benchmarks' baseline)."""
    import torch
    from transformers import CLIPConfig, CLIPModel

    cfg = CLIPConfig(vision_config=dict(patch_size=16), projection_dim=512)
    torch.manual_seed(seed)
    return realistic_init(CLIPModel._from_config(cfg, attn_implementation="eager").eval(), seed)


def save_checkpoint(
    model: Any, root: Path, tokenizer: Any = None, preprocessor: dict | None = None
) -> Path:
    """`model` as a Hugging Face checkpoint directory (safetensors), with a tokenizer.json and
    a preprocessor_config.json."""
    from transformers.utils import logging

    logging.disable_progress_bar()
    root = Path(root)
    model.save_pretrained(str(root), safe_serialization=True)
    if tokenizer is not None:
        tokenizer.save(str(root / "tokenizer.json"))
    (root / "preprocessor_config.json").write_text(json.dumps({**IMAGENET, **(preprocessor or {})}))
    return root


def checkpoints(root: Path, real: bool = False, sam_size: int = 128) -> dict[str, Path]:
    """Write the three RES checkpoints under `root`: {"detector", "sam", "clipseg"} -> path."""
    root = Path(root)
    size = 352 if real else 64
    clipseg_vocab = 49408 if real else 100
    return {
        "detector": save_checkpoint(
            grounding_dino(real), root / "grounding-dino", bert_tokenizer()
        ),
        "sam": save_checkpoint(sam(real, sam_size), root / "sam"),
        "clipseg": save_checkpoint(
            clipseg(real), root / "clipseg", clip_tokenizer(clipseg_vocab), {"size": size}
        ),
        "owlv2": save_checkpoint(
            owlv2(real), root / "owlv2", clip_tokenizer(clipseg_vocab), OWL_STATS
        ),
    }


def random_bundle(out: Path, force: bool = False, report: Any = None) -> Path:
    """The tiny Grounded-SAM (Grounding DINO and a 128 px SAM) exported as a bundle at `out`,
    with RANDOM weights: the manifest's name says so (RANDOM-WEIGHTS-...)."""
    from stages.models.export import ModelExportParams, ModelExportRun, export_model

    opts = ModelExportParams(
        detector_height=GROUNDED["canvas"][0],
        detector_width=GROUNDED["canvas"][1],
        box_threshold=GROUNDED["box_threshold"],
        max_boxes=GROUNDED["max_boxes"],
        mask_threshold=GROUNDED["mask_threshold"],
    )
    with tempfile.TemporaryDirectory() as tmp:
        ck = Path(tmp)
        det = save_checkpoint(
            grounding_dino(), ck / "RANDOM-WEIGHTS-grounding-dino", bert_tokenizer()
        )
        seg = save_checkpoint(sam(), ck / "RANDOM-WEIGHTS-sam")
        return export_model(
            [det, seg], opts, ModelExportRun(out=out, force=force), report or Lines()
        )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m stages.testing.models",
        description="Write a small model bundle with RANDOM weights (the tests' tiny "
        "Grounded-SAM), for trying goi index-res and the --bundle / --res-index paths without "
        "downloading a model. Its masks mean nothing.",
    )
    ap.add_argument("--bundle", type=Path, required=True, help="The bundle directory to write.")
    ap.add_argument("--force", action="store_true", help="Replace an existing bundle.")
    a = ap.parse_args(argv)
    try:
        import transformers  # noqa: F401
    except ImportError:
        print(
            "error: the random bundle is made by goi export-model, which needs transformers: "
            "pip install 'goi[export]'",
            file=sys.stderr,
        )
        return 2
    print(
        "goi: RANDOM weights: this bundle is for trying the paths, not for answers", file=sys.stderr
    )
    try:
        out = random_bundle(a.bundle, a.force, Lines(lambda m: print(f"goi: {m}", file=sys.stderr)))
    except GoiError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"bundle (RANDOM weights, its masks mean nothing): {out}")
    print(
        f"try: goi index-res --scene SCENE --bundle {out} --out index.h5, then goi query "
        f"--scene SCENE --prompt TEXT --lift --bundle {out} --res-index index.h5 --out q"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())

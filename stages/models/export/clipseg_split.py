"""A CLIPSeg checkpoint split for the RES index: clipseg_image.onnx (the frozen CLIP vision
activations CLIPSeg's decoder reads, about 90 % of its cost), clipseg_text.onnx (the
conditional embedding) and clipseg_decoder.onnx (the light conditional decoder).

clipseg_image.onnx: pixel_values [1, 3, S, S] -> activations [n, 1, T, C]: the outputs of the
vision layers `extract_layers` (n of them; T = 1 + (S/16)^2 tokens), the layers after the last
one are not run. clipseg_text.onnx: input_ids, attention_mask [1, L] -> conditional [1, P].
clipseg_decoder.onnx: activations, conditional -> probs [1, 1, S, S] (sigmoid of the logits).
Pre- and post-processing are the whole graph's (`clipseg`): Pillow bilinear to S x S,
normalised; probabilities resized to the image and thresholded.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from stages.models.export.clipseg import export_inputs
from stages.models.export.common import (
    export_checked,
    export_text_graph,
    image_spec,
)


def modules(model: Any) -> tuple[Any, Any, Any]:
    import torch

    extract = [int(i) for i in model.config.extract_layers]

    class Image(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.model = model

        def forward(self, pixel_values: torch.Tensor) -> torch.Tensor:
            vm = self.model.clip.vision_model
            h = vm.embeddings(pixel_values, interpolate_pos_encoding=True)
            h = vm.pre_layrnorm(h)
            acts = []
            for i, layer in enumerate(vm.encoder.layers[: max(extract) + 1]):
                h = layer(h, None)
                h = h[0] if isinstance(h, tuple) else h
                if i in extract:
                    acts.append(h)
            return torch.stack(acts)  # [n, 1, T, C]

    class Text(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.model = model

        def forward(self, input_ids: torch.Tensor, attention_mask: torch.Tensor) -> torch.Tensor:
            out = self.model.clip.get_text_features(input_ids, attention_mask=attention_mask)
            return out if isinstance(out, torch.Tensor) else out.pooler_output

    class Decoder(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.model = model

        def forward(self, activations: torch.Tensor, conditional: torch.Tensor) -> torch.Tensor:
            acts = tuple(activations[i] for i in range(activations.shape[0]))
            logits = self.model.decoder(acts, conditional).logits
            return logits.reshape(1, 1, logits.shape[-2], logits.shape[-1]).sigmoid()

    return Image().eval(), Text().eval(), Decoder().eval()


def export_clipseg_split(
    model: Any, src: Path, tmp: Path, tokenizer: str, threshold: float, opset: int
) -> dict:
    """The three graphs and the tokenizer; returns the manifest's `clipseg` entry and checks."""
    tok, tokens, stats, size, pixels = export_inputs(model, src, tmp, tokenizer, "clipseg")
    image, text, decoder = modules(model)
    paths = {k: tmp / f"clipseg_{k}.onnx" for k in ("image", "text", "decoder")}
    checks = {}
    ((acts,),), checks["clipseg_image.onnx"] = export_checked(
        image, [{"pixel_values": pixels}], paths["image"], ["activations"], {}, opset
    )
    conds, checks["clipseg_text.onnx"] = export_text_graph(
        text, tokens, paths["text"], "conditional", opset
    )
    feeds = [{"activations": acts, "conditional": c} for (c,) in conds]
    _, checks["clipseg_decoder.onnx"] = export_checked(
        decoder, feeds, paths["decoder"], ["probs"], {}, opset
    )
    spec = {
        "image": image_spec("clipseg_image.onnx", [size, size], stats),
        "text": {"file": "clipseg_text.onnx", "tokenizer": tok},
        "decoder": {"file": "clipseg_decoder.onnx"},
        "threshold": float(threshold),
    }
    return {"clipseg": spec, "export_checks": checks}

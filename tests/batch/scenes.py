"""Tiny synthetic scenes for the batch tests: a scene, its feature maps, text embeddings and
RES masks (each object's true mask on the training views), and a batch configuration."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from tests.helpers import semantic_scene

#: Two prompts per scene: two of the synthetic room's objects.
PROMPTS = ("object 1", "object 2")


def tiny_scene(root: Path, seed: int) -> dict:
    from stages.render.rasterizer import Rasterizer
    from stages.scene.gaussians import load_ply

    s = semantic_scene(root, n=400, n_views=4, size=(32, 24), stride=4, dim=16, seed=seed)
    emb = {f"object {k}": s["objects"][k].tolist() for k in range(len(s["objects"]))}
    (root / "text.json").write_text(json.dumps(emb))
    rast = Rasterizer.from_gaussians(load_ply(s["scene"] / "point_cloud.ply"))
    for k in (1, 2):
        d = root / "res" / f"o{k}"
        d.mkdir(parents=True)
        for name in s["train"]:
            share = rast.render_features(s["cameras"][name], s["onehot"]).image
            m = (share.argmax(2) == k) & (share.sum(2) > 0.5)
            cv2.imwrite(str(d / f"{name}.png"), m.astype(np.uint8) * 255)
    return s


def write_config(path: Path, scenes: dict[str, Path], fieldfree: tuple[str, ...] = ()) -> None:
    """A YAML batch of `scenes` (name -> the directory tiny_scene made), each with PROMPTS;
    the scenes named in `fieldfree` go the field-free lifted route."""
    lines = [
        "schema: goi.batch",
        'schema_version: "1.0"',
        "defaults:",
        "  options:",
        "    init-codebook: {entries: 8, samples: 2000}",
        "    fit-field: {iterations: 20, cells-per-view: 32}",
        "    query: {export: none, steps: 200}",
        "  prompts:",
        *[f"    - {{text: {p}, id: o{p[-1]}}}" for p in PROMPTS],
        "scenes:",
    ]
    for name, root in scenes.items():
        lines += [
            f"  - name: {name}",
            f"    scene: {root / 'scene'}",
            f"    text_embeddings: {root / 'text.json'}",
            f"    res_masks: {root / 'res'}",
        ]
        lines += ["    lift: true"] if name in fieldfree else [f"    features: {root / 'features'}"]
    path.write_text("\n".join(lines) + "\n")

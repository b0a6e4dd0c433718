"""Tiny synthetic scenes for the batch tests: a scene, its feature maps, text embeddings and
RES masks (each object's true mask on the training views), and a batch configuration."""

from __future__ import annotations

from pathlib import Path

from tests.helpers import semantic_scene, write_true_res

#: Two prompts per scene: two of the synthetic room's objects.
PROMPTS = ("object 1", "object 2")


def tiny_scene(root: Path, seed: int) -> dict:
    s = semantic_scene(root, n=400, n_views=4, size=(32, 24), stride=4, dim=16, seed=seed)
    write_true_res(s, root, (1, 2))
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

"""Benchmark rooms: the layout `goi eval` reads (see ../shared/dev-room/README.md).

A room is a scene directory (PLY, cameras with a train/test split, images) plus prompts.json,
text_embeddings.json, eval/masks/<prompt id>/<test view>.png ground truth and, optionally,
gaussian_ids.npy (the instance of every Gaussian, for the 3D IoU).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stages.core.errors import GoiError
from stages.core.files import read_json, regular_file
from stages.query.prompts import load_text_embeddings
from stages.scene.images import read_mask
from stages.scene.scene import Scene, load_scene


@dataclass
class Prompt:
    id: str
    text: str
    targets: list[int]
    test_views: list[str]
    kind: str


def load_prompts(room: Path) -> list[Prompt]:
    path = room / "prompts.json"
    raw = read_json(path, "missing; a room lists its prompts there")
    if not isinstance(raw, list) or not raw:
        raise GoiError(f"{path}: expected a non-empty list of prompts")
    out = []
    for i, p in enumerate(raw):
        try:
            out.append(
                Prompt(
                    str(p["id"]),
                    str(p["text"]),
                    [int(t) for t in p["targets"]],
                    [str(v) for v in p.get("test_views", [])],
                    str(p.get("kind", "")),
                )
            )
        except (KeyError, TypeError, ValueError) as e:
            raise GoiError(f"{path}: prompt {i} lacks a valid field ({e})") from None
    return out


@dataclass
class Room:
    dir: Path
    scene: Scene
    prompts: list[Prompt]
    embeddings: dict[str, np.ndarray]  # prompt text -> [D] unit embedding
    gaussian_ids: np.ndarray | None  # [G] int instance id, when the room has them

    def ground_truth(self, prompt: Prompt, view: str) -> np.ndarray:
        """[H, W] bool: the prompt's targets on a test view."""
        return read_mask(self.dir / "eval" / "masks" / prompt.id / f"{view}.png")

    def targets(self, prompt: Prompt) -> np.ndarray | None:
        """[G] bool: the prompt's target Gaussians (None without gaussian_ids.npy)."""
        return None if self.gaussian_ids is None else np.isin(self.gaussian_ids, prompt.targets)


def _load_ids(path: Path) -> np.ndarray:
    try:
        ids = np.load(regular_file(path, "instance ids (.npy)"), allow_pickle=False)
    except (ValueError, EOFError, OSError) as e:
        raise GoiError(f"{path}: not a plain .npy array of instance ids ({e})") from None
    if ids.ndim != 1 or ids.dtype.kind not in "iu":
        raise GoiError(f"{path}: expected a 1-d integer array, found {ids.dtype} {ids.shape}")
    return ids


def load_room(room: Path, text_embeddings: Path | None = None) -> Room:
    """The room's parts, checked against each other before any work."""
    room = Path(room)
    scene = load_scene(room)
    prompts = load_prompts(room)
    emb = load_text_embeddings(text_embeddings or room / "text_embeddings.json")
    missing = [p.text for p in prompts if p.text not in emb]
    if missing:
        raise GoiError(f"no text embedding for prompt(s) {', '.join(map(repr, missing[:3]))}")
    ids_path = room / "gaussian_ids.npy"
    gaussian_ids = _load_ids(ids_path) if ids_path.exists() else None
    if gaussian_ids is not None and gaussian_ids.shape != (scene.gaussians.count,):
        raise GoiError(
            f"{ids_path}: {gaussian_ids.shape} ids for {scene.gaussians.count} Gaussians"
        )
    test = {c.name for c in scene.views("test")}
    for p in prompts:  # every ground-truth mask is there before any work
        for v in p.test_views:
            if v in test:
                regular_file(room / "eval" / "masks" / p.id / f"{v}.png", "ground-truth mask")
    dims = {e.size for e in emb.values()}
    if len(dims) != 1:
        raise GoiError(f"text embeddings of several dimensions: {sorted(dims)}")
    return Room(room, scene, prompts, emb, gaussian_ids)

"""Benchmark rooms: the layout `goi eval` reads (see ../shared/dev-room/README.md).

A room is a scene directory (PLY, cameras with a train/test split, images) plus prompts.json,
text_embeddings.json, eval/masks/<prompt id>/<test view>.png ground truth and, optionally,
gaussian_ids.npy (the instance of every Gaussian, for the 3D IoU).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from stages.core.errors import GoiError
from stages.core.files import read_json, regular_file
from stages.query import prompts
from stages.query.prompts import check_plain_name, check_prompt, load_text_embeddings
from stages.scene.images import read_mask
from stages.scene.scene import Scene, load_scene


@dataclass
class Prompt:
    id: str
    text: str
    targets: list[int]
    test_views: list[str]
    kind: str

    @cached_property
    def query(self) -> prompts.Prompt:
        """The prompt as goi query takes it (its text, and its id naming its RES masks)."""
        return prompts.Prompt(self.text, self.id)


def load_prompts(room: Path) -> list[Prompt]:
    """The room's prompts.json, every field checked: ids are plain names (they become
    directory names) and unique, texts are prompts, targets integers, test views names."""
    path = room / "prompts.json"
    raw = read_json(path, "missing; a room lists its prompts there")
    if not isinstance(raw, list) or not raw:
        raise GoiError(f"{path}: expected a non-empty list of prompts")
    out: list[Prompt] = []
    for i, p in enumerate(raw):
        where = f"{path}: prompt {i}"
        if not isinstance(p, dict):
            raise GoiError(f"{where} is not an object {{id, text, targets, test_views, kind}}")
        pid = _prompt_id(p, where)
        where = f"{path}: prompt {pid!r}"
        if pid in {q.id for q in out}:
            raise GoiError(f"{where}: the id appears twice")
        text = p.get("text")
        if not isinstance(text, str):
            raise GoiError(f"{where}: field 'text' is missing or not a string")
        text = check_prompt(text, f"{where}: field 'text'")
        targets = p.get("targets")
        if not isinstance(targets, list) or not all(_is_int(t) for t in targets):
            raise GoiError(f"{where}: field 'targets' must be a list of integer instance ids")
        views = p.get("test_views", [])
        if not isinstance(views, list) or not all(isinstance(v, str) for v in views):
            raise GoiError(f"{where}: field 'test_views' must be a list of view names")
        if len(set(views)) != len(views):
            raise GoiError(f"{where}: field 'test_views' names a view twice")
        kind = p.get("kind", "")
        if not isinstance(kind, str):
            raise GoiError(f"{where}: field 'kind' must be a string")
        out.append(Prompt(pid, text, [int(t) for t in targets], views, kind))
    return out


def _is_int(x: object) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def _prompt_id(p: dict, where: str) -> str:
    """A prompt id names directories (eval/masks/<id>, the RES masks' <id>): a plain name."""
    pid = p.get("id")
    if not (isinstance(pid, str) or _is_int(pid)):
        raise GoiError(f"{where}: field 'id' is missing or not a string")
    return check_plain_name(str(pid), f"{where}: field 'id'", "eval/masks/<id> and <RES dir>/<id>")


@dataclass
class Room:
    dir: Path
    scene: Scene
    prompts: list[Prompt]
    embeddings: dict[str, np.ndarray]  # prompt text -> [D] unit embedding
    gaussian_ids: np.ndarray | None  # [G] int instance id, when the room has them
    embeddings_path: Path | None = None  # where the embeddings came from

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
    test = {c.name for c in scene.views("test")}
    if not test:
        raise GoiError(
            f"{room}: the room has no test views (split.json with a 'test' list, or "
            "transforms_test.json); eval scores the masks on them"
        )
    prompts = load_prompts(room)
    for p in prompts:
        bad = [v for v in p.test_views if v not in test]
        if bad:
            raise GoiError(
                f"{room / 'prompts.json'}: prompt {p.id!r} lists test view(s) "
                f"{', '.join(repr(v[:40]) for v in bad[:3])} that are not test views of the room"
            )
    emb_path = Path(text_embeddings or room / "text_embeddings.json")
    emb = load_text_embeddings(emb_path)
    missing = [p.text for p in prompts if p.text not in emb]
    if missing:
        raise GoiError(
            f"{emb_path}: no text embedding for prompt(s) {', '.join(map(repr, missing[:3]))} "
            f"of {room / 'prompts.json'}"
        )
    ids_path = room / "gaussian_ids.npy"
    gaussian_ids = _load_ids(ids_path) if ids_path.exists() else None
    if gaussian_ids is not None and gaussian_ids.shape != (scene.gaussians.count,):
        raise GoiError(
            f"{ids_path}: {gaussian_ids.shape} ids for {scene.gaussians.count} Gaussians"
        )
    if gaussian_ids is not None:  # a 3D score needs targets that are the room's instances
        known = set(np.unique(gaussian_ids).tolist())
        for p in prompts:
            unknown = [t for t in p.targets if t not in known]
            if not p.targets or unknown:
                what = f"target(s) {unknown[:5]}" if unknown else "no target"
                raise GoiError(
                    f"{room / 'prompts.json'}: prompt {p.id!r} names {what} that is not an "
                    f"instance id of {ids_path} (its 3D score would mean nothing)"
                )
    for p in prompts:  # every ground-truth mask is there and readable before any work
        for v in p.test_views:
            path = room / "eval" / "masks" / p.id / f"{v}.png"
            cam = scene.camera(v)
            m = read_mask(regular_file(path, "ground-truth mask"))
            if m.shape != (cam.height, cam.width):
                raise GoiError(
                    f"{path}: ground-truth mask is {m.shape[1]}x{m.shape[0]}, the view "
                    f"{v!r} is {cam.width}x{cam.height}"
                )
    dims = {e.size for e in emb.values()}
    if len(dims) != 1:
        raise GoiError(f"{emb_path}: text embeddings of several dimensions: {sorted(dims)}")
    return Room(room, scene, prompts, emb, gaussian_ids, emb_path)

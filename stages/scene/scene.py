"""One scene description: a 3DGS PLY, its cameras, its images and a train/test split.

Later stages are given either a scene directory, in which the parts are found by their usual
names, or explicit paths. The split comes from split.json, from separate transforms_train/test
files, or else every view is a training view.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from stages.core.artifacts import sha256_file, sha256_files
from stages.core.errors import GoiError
from stages.core.files import read_json
from stages.scene.cameras import IMAGE_EXTS, Camera
from stages.scene.formats import load_cameras
from stages.scene.gaussians import Gaussians, load_ply
from stages.scene.images import read_rgb


@dataclass
class Scene:
    ply_path: Path
    cameras: list[Camera]
    camera_files: list[Path]  # what the cameras were read from, for the checksum
    images_dir: Path | None
    train: list[str]
    test: list[str] = field(default_factory=list)

    @cached_property
    def gaussians(self) -> Gaussians:
        return load_ply(self.ply_path)

    @cached_property
    def by_name(self) -> dict[str, Camera]:
        return {c.name: c for c in self.cameras}

    def camera(self, name: str) -> Camera:
        try:
            return self.by_name[name]
        except KeyError:
            raise GoiError(
                f"view '{name}' is not among the scene's cameras ({_preview(list(self.by_name))})"
            ) from None

    def views(self, split: str) -> list[Camera]:
        names = {"train": self.train, "test": self.test, "all": [c.name for c in self.cameras]}
        if split not in names:
            raise GoiError(f"--split: unknown split {split!r} (train, test or all)")
        return [self.camera(n) for n in names[split]]

    @cached_property
    def _ply_sha(self) -> str:
        return sha256_file(self.ply_path)

    def ply_digest(self) -> str:
        """SHA-256 of the PLY, hashed once per Scene (several artifacts record it)."""
        return self._ply_sha

    @cached_property
    def _cameras_sha(self) -> str:
        return sha256_files(self.camera_files)

    def cameras_digest(self) -> str:
        return self._cameras_sha

    def image_path(self, cam: Camera) -> Path:
        roots = [self.images_dir] if self.images_dir else []
        candidates: list[Path] = []
        for root in roots:
            candidates += [
                root / (cam.image or cam.name),
                root / Path(cam.image or "").name,
                root / cam.name,
            ]
        for c in self.camera_files:
            if cam.image:
                candidates.append(c.parent / cam.image)
        for cand in candidates:
            if cand.is_file() and cand.suffix in IMAGE_EXTS:
                return cand
            for ext in IMAGE_EXTS:
                alt = cand.with_name(cand.name + ext)
                if alt.is_file():
                    return alt
        where = self.images_dir or self.camera_files[0].parent
        raise GoiError(
            f"{where}: image for view '{cam.name}' not found "
            f"(camera file names {cam.image or cam.name!r})"
        )

    def load_image(self, cam: Camera) -> np.ndarray:
        """[H, W, 3] uint8 RGB; its size must be the camera's."""
        return read_rgb(self.image_path(cam), cam.width, cam.height)


def _preview(names: list[str], n: int = 5) -> str:
    return ", ".join(names[:n]) + (f", ... {len(names)} in all" if len(names) > n else "")


def _find_ply(d: Path) -> Path:
    direct = d / "point_cloud.ply"
    if direct.is_file():
        return direct
    # INRIA's training output: point_cloud/iteration_<n>/point_cloud.ply, take the last.
    its = sorted(
        d.glob("point_cloud/iteration_*/point_cloud.ply"),
        key=lambda p: int(re.sub(r"\D", "", p.parent.name) or 0),
    )
    if its:
        return its[-1]
    raise GoiError(
        f"{d}: no point_cloud.ply (nor point_cloud/iteration_*/point_cloud.ply); pass --ply"
    )


def load_scene(
    scene: str | os.PathLike[str] | None = None,
    ply: str | os.PathLike[str] | None = None,
    cameras: str | os.PathLike[str] | None = None,
    images: str | os.PathLike[str] | None = None,
) -> Scene:
    """Find the scene's parts; explicit paths override what the directory holds."""
    d = Path(scene) if scene is not None else None
    if d is not None and not d.is_dir():
        raise GoiError(f"--scene: {d} is not a directory")
    if d is None and (ply is None or cameras is None):
        raise GoiError("give --scene DIR, or both --ply and --cameras")
    ply_path = Path(ply) if ply is not None else _find_ply(d)  # type: ignore[arg-type]
    if not ply_path.is_file():
        raise GoiError(f"--ply: {ply_path}: no such file")
    train: list[str] | None = None
    test: list[str] = []
    if cameras is not None:
        files = [Path(cameras)]
        cams = load_cameras(cameras)
    else:
        assert d is not None
        tt = [d / "transforms_train.json", d / "transforms_test.json"]
        if (d / "cameras.json").is_file():
            files, cams = [d / "cameras.json"], load_cameras(d / "cameras.json")
        elif tt[0].is_file():
            files = [f for f in tt if f.is_file()]
            parts = [load_cameras(f) for f in files]
            cams = [c for part in parts for c in part]
            train = [c.name for c in parts[0]]
            test = [c.name for c in parts[1]] if len(parts) > 1 else []
        elif (d / "transforms.json").is_file():
            files, cams = [d / "transforms.json"], load_cameras(d / "transforms.json")
        elif (d / "sparse").is_dir():
            sub = d / "sparse" / "0" if (d / "sparse" / "0").is_dir() else d / "sparse"
            files = sorted(p for p in sub.iterdir() if p.name.startswith(("cameras", "images")))
            cams = load_cameras(sub)
        else:
            raise GoiError(
                f"{d}: no cameras.json, transforms*.json or sparse/ COLMAP model; pass --cameras"
            )
    names = [c.name for c in cams]
    # a split.json that is there is read (a FIFO or a directory is refused, never skipped)
    if d is not None and ((d / "split.json").exists() or (d / "split.json").is_symlink()):
        split = _read_split(d / "split.json", set(names), files)
        train, test = split["train"], split.get("test", [])
    if train is None:
        train = names
    images_dir: Path | None = None
    if images is not None:
        images_dir = Path(images)
        if not images_dir.is_dir():
            raise GoiError(f"--images: {images_dir} is not a directory")
    elif d is not None and (d / "images").is_dir():
        images_dir = d / "images"
    return Scene(ply_path, cams, files, images_dir, train, test)


def _read_split(path: Path, names: set[str], camera_files: list[Path]) -> dict[str, list[str]]:
    split = read_json(path)
    if not isinstance(split, dict):
        raise GoiError(f'{path}: expected an object {{"train": [views], "test": [views]}}')
    out: dict[str, list[str]] = {}
    for key in ("train", "test"):
        views = split.get(key, [])
        if not isinstance(views, list) or not all(isinstance(v, str) for v in views):
            raise GoiError(f"{path}: '{key}' must be a list of view names (strings)")
        unknown = [n for n in views if n not in names]
        if unknown:
            where = ", ".join(f.name for f in camera_files[:2]) or "the camera files"
            raise GoiError(
                f"{path}: '{key}' names views without a camera in {where}: {_preview(unknown)}"
            )
        if len(set(views)) != len(views):
            raise GoiError(f"{path}: '{key}' names a view more than once")
        out[key] = views
    if not out["train"]:
        raise GoiError(f"{path}: needs a non-empty 'train' list of view names")
    return out

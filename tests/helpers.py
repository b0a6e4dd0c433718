"""Inputs the tests make: random Gaussians, a camera facing them, and a small semantic scene."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from stages.scene.cameras import Camera
from stages.scene.formats.inria import write_inria
from stages.scene.gaussians import save_ply, vertex_fields
from stages.testing.synthetic import look_at

DEV_ROOM = Path(__file__).resolve().parents[1].parent / "shared" / "dev-room"


def random_vertex(
    n: int,
    degree: int = 0,
    normals: bool = True,
    extra: tuple[str, ...] = (),
    seed: int = 0,
    spread: float = 1.0,
) -> np.ndarray:
    """A random INRIA vertex table of `n` Gaussians in front of `front_camera()`."""
    rng = np.random.default_rng(seed)
    k_rest = 3 * ((degree + 1) ** 2 - 1)
    v = np.zeros(n, dtype=[(nm, "<f4") for nm in vertex_fields(degree, normals, extra)])
    v["x"] = rng.uniform(-spread, spread, n)
    v["y"] = rng.uniform(-spread, spread, n)
    v["z"] = rng.uniform(-0.5, 0.5, n)
    for c in range(3):
        v[f"f_dc_{c}"] = rng.normal(0, 1, n)
    for i in range(k_rest):
        v[f"f_rest_{i}"] = rng.normal(0, 0.3, n)
    v["opacity"] = rng.normal(0, 2, n)
    for c in range(3):
        v[f"scale_{c}"] = np.log(rng.uniform(0.02, 0.25, n))
    q = rng.normal(size=(n, 4))
    for c in range(4):
        v[f"rot_{c}"] = q[:, c]
    for nm in extra:
        v[nm] = rng.normal(size=n)
    return v


def front_camera(width: int = 64, height: int = 48, name: str = "c0") -> Camera:
    return look_at(name, np.array([0.3, -3.0, 0.4]), np.zeros(3), width, height, 55.0)


def write_ply(path: Path, v: np.ndarray) -> Path:
    save_ply(path, v, force=True)
    return path


def semantic_scene(
    root: Path,
    n: int = 20000,
    n_views: int = 12,
    size: tuple[int, int] = (128, 96),
    stride: int = 4,
    dim: int = 32,
    noise: float = 0.3,
    seed: int = 0,
) -> dict:
    """A room with 4 objects whose 2D features are constant per object plus noise.

    Writes root/scene (PLY, cameras.json, split.json: even views train, odd views test) and
    root/features/<view>.npy [dim, h, w] for the training views; returns what tests compare to.
    """
    import cv2

    from stages.render.rasterizer import Rasterizer
    from stages.scene.gaussians import load_ply
    from stages.testing.synthetic import ring_cameras, room_vertex

    scene = root / "scene"
    scene.mkdir(parents=True)
    v, ids = room_vertex(n, seed=seed, n_objects=4)
    write_ply(scene / "point_cloud.ply", v)
    cams = ring_cameras(n_views, *size, radius=1.9, height_m=1.5)
    write_inria(scene / "cameras.json", cams)
    train = [c.name for c in cams[0::2]]
    test = [c.name for c in cams[1::2]]
    (scene / "split.json").write_text(json.dumps({"train": train, "test": test}))
    rng = np.random.default_rng(seed)
    objects = rng.normal(size=(ids.max() + 1, dim))
    objects /= np.linalg.norm(objects, axis=1, keepdims=True)
    onehot = np.eye(ids.max() + 1, dtype=np.float32)[ids]
    rast = Rasterizer.from_gaussians(load_ply(scene / "point_cloud.ply"))
    feats = root / "features"
    feats.mkdir()
    for c in cams[0::2]:
        share = rast.render_features(c, onehot).image  # [H, W, K]
        f = share @ objects + rng.normal(0, noise / np.sqrt(dim), (c.height, c.width, dim))
        h, w = c.height // stride, c.width // stride
        small = cv2.resize(f.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA)
        np.save(feats / f"{c.name}.npy", small.transpose(2, 0, 1).astype(np.float16))
    return {
        "scene": scene,
        "features": feats,
        "objects": objects,
        "onehot": onehot,
        "train": train,
        "test": test,
        "cameras": {c.name: c for c in cams},
    }


def build_or_load(path, scene, cameras, k=0, sizes=None, force=False):  # noqa: ANN001, ANN201
    """`ensure_cache` (what fit-field does), then the cache of these views in memory."""
    from stages.semantics.blend_cache import BlendCache, ensure_cache

    cache = BlendCache.load(ensure_cache(path, scene, cameras, k, sizes, force=force))
    cache.views = {c.name: cache.views[c.name] for c in cameras}
    return cache


def write_true_res(s: dict, root: Path, objects: range | tuple[int, ...]) -> None:
    """`root`/text.json (each object's feature as its text embedding) and `root`/res/o<k>/: each
    object's true mask on the training views of `semantic_scene` s, as RES mask files."""
    import cv2

    from stages.render.rasterizer import Rasterizer
    from stages.scene.gaussians import load_ply

    emb = {f"object {k}": s["objects"][k].tolist() for k in range(len(s["objects"]))}
    (root / "text.json").write_text(json.dumps(emb))
    rast = Rasterizer.from_gaussians(load_ply(s["scene"] / "point_cloud.ply"))
    for k in objects:
        d = root / "res" / f"o{k}"
        d.mkdir(parents=True)
        for name in s["train"]:
            share = rast.render_features(s["cameras"][name], s["onehot"]).image
            m = (share.argmax(2) == k) & (share.sum(2) > 0.5)
            cv2.imwrite(str(d / f"{name}.png"), m.astype(np.uint8) * 255)

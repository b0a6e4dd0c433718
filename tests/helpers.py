"""Writers the tests use to make inputs in every format goi reads."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np

from stages.cameras import GL_TO_CV, Camera
from stages.gaussians import save_ply, vertex_fields
from stages.synthetic import look_at

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


def write_inria(path: Path, cams: list[Camera]) -> Path:
    out = []
    for i, c in enumerate(cams):
        out.append(
            {
                "id": i,
                "img_name": c.name,
                "width": c.width,
                "height": c.height,
                "position": c.center.tolist(),
                "rotation": c.R.T.tolist(),
                "fx": c.fx,
                "fy": c.fy,
            }
        )
    path.write_text(json.dumps(out))
    return path


def write_transforms(path: Path, cams: list[Camera], intrinsics: str = "angle") -> Path:
    c0 = cams[0]
    data: dict = {"w": c0.width, "h": c0.height}
    if intrinsics == "angle":
        data["camera_angle_x"] = 2 * np.arctan(0.5 * c0.width / c0.fx)
    elif intrinsics == "focal":
        data.update(fl_x=c0.fx, fl_y=c0.fy, cx=c0.cx, cy=c0.cy)
    frames = []
    for c in cams:
        m = np.eye(4)
        m[:3, :3] = c.R.T @ GL_TO_CV
        m[:3, 3] = c.center
        frames.append({"file_path": f"images/{c.name}.png", "transform_matrix": m.tolist()})
    data["frames"] = frames
    path.write_text(json.dumps(data))
    return path


def rotmat_to_quat(R: np.ndarray) -> np.ndarray:
    w = np.sqrt(max(0.0, 1 + R[0, 0] + R[1, 1] + R[2, 2])) / 2
    x = np.sqrt(max(0.0, 1 + R[0, 0] - R[1, 1] - R[2, 2])) / 2
    y = np.sqrt(max(0.0, 1 - R[0, 0] + R[1, 1] - R[2, 2])) / 2
    z = np.sqrt(max(0.0, 1 - R[0, 0] - R[1, 1] + R[2, 2])) / 2
    x = np.copysign(x, R[2, 1] - R[1, 2])
    y = np.copysign(y, R[0, 2] - R[2, 0])
    z = np.copysign(z, R[1, 0] - R[0, 1])
    return np.array([w, x, y, z])


def write_colmap(d: Path, cams: list[Camera], binary: bool, model: str = "PINHOLE") -> Path:
    d.mkdir(parents=True, exist_ok=True)
    model_ids = {"SIMPLE_PINHOLE": 0, "PINHOLE": 1, "OPENCV": 4}
    if binary:
        with open(d / "cameras.bin", "wb") as f:
            f.write(struct.pack("<Q", len(cams)))
            for i, c in enumerate(cams):
                params = _colmap_params(c, model)
                f.write(struct.pack("<iiQQ", i + 1, model_ids[model], c.width, c.height))
                f.write(struct.pack(f"<{len(params)}d", *params))
        with open(d / "images.bin", "wb") as f:
            f.write(struct.pack("<Q", len(cams)))
            for i, c in enumerate(cams):
                f.write(struct.pack("<i7di", i + 1, *rotmat_to_quat(c.R), *c.t, i + 1))
                f.write(f"{c.name}.png".encode() + b"\0")
                f.write(struct.pack("<Q", 1))
                f.write(struct.pack("<ddq", 1.0, 2.0, -1))
    else:
        lines = [
            "# Camera list",
            *[
                f"{i + 1} {model} {c.width} {c.height} "
                + " ".join(repr(float(v)) for v in _colmap_params(c, model))
                for i, c in enumerate(cams)
            ],
        ]
        (d / "cameras.txt").write_text("\n".join(lines) + "\n")
        lines = ["# Image list"]
        for i, c in enumerate(cams):
            q = rotmat_to_quat(c.R)
            lines.append(f"{i + 1} {_fl(q)} {_fl(c.t)} {i + 1} {c.name}.png")
            lines.append("" if i % 2 else "1.0 2.0 -1")
        (d / "images.txt").write_text("\n".join(lines) + "\n")
    return d


def _colmap_params(c: Camera, model: str) -> list[float]:
    if model == "SIMPLE_PINHOLE":
        return [c.fx, c.cx, c.cy]
    if model == "PINHOLE":
        return [c.fx, c.fy, c.cx, c.cy]
    return [c.fx, c.fy, c.cx, c.cy, 0.01, 0.0, 0.0, 0.0]


def _fl(values) -> str:
    return " ".join(repr(float(v)) for v in values)


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

    from stages.gaussians import load_ply
    from stages.rasterizer import Rasterizer
    from stages.synthetic import ring_cameras, room_vertex

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

"""Synthetic scenes for tests and benchmarks: a box room with objects, and cameras inside it.

Everything is drawn from a seeded generator, so a seed names a scene.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from stages.render.rasterizer import Rasterizer
from stages.scene.cameras import Camera
from stages.scene.gaussians import SH_C0, vertex_fields


def look_at(
    name: str, eye: np.ndarray, target: np.ndarray, width: int, height: int, fov_x_deg: float = 60.0
) -> Camera:
    """A pinhole camera at `eye` looking at `target`, world z up, OpenCV axes."""
    fwd = target - eye
    fwd = fwd / np.linalg.norm(fwd)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right = right / np.linalg.norm(right)
    down = np.cross(fwd, right)
    R = np.stack([right, down, fwd])  # rows: camera axes in world coordinates
    f = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2)
    return Camera(name, width, height, f, f, width / 2, height / 2, R, -R @ eye)


def ring_cameras(
    n: int,
    width: int,
    height: int,
    radius: float = 1.6,
    height_m: float = 1.4,
    target=(0.0, 0.0, 0.6),
    prefix: str = "v",
) -> list[Camera]:
    """`n` cameras on a circle inside the room, each looking across it."""
    cams = []
    for i in range(n):
        a = 2 * math.pi * i / n
        eye = np.array([radius * math.cos(a), radius * math.sin(a), height_m])
        cams.append(look_at(f"{prefix}{i:03d}", eye, np.asarray(target, float), width, height))
    return cams


def room_vertex(
    n: int, seed: int = 0, n_objects: int = 6, sh_degree: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """An INRIA vertex table of `n` Gaussians: 80% on the walls and floor of a 5 x 5 x 2.5 m
    room, 20% on `n_objects` boxy objects standing on the floor, each object a flat colour;
    about even density by area, as an optimised 3DGS scene has.
    Returns the table and the object id of every Gaussian (0 = room shell)."""
    rng = np.random.default_rng(seed)
    n_shell = int(0.8 * n)
    half = 2.5
    pts = rng.uniform(-half, half, (n_shell, 3))
    pts[:, 2] = rng.uniform(0, 2.5, n_shell)
    face = rng.integers(0, 5, n_shell)  # floor, 4 walls
    pts[face == 0, 2] = 0.0
    pts[face == 1, 0] = -half
    pts[face == 2, 0] = half
    pts[face == 3, 1] = -half
    pts[face == 4, 1] = half
    ids = np.zeros(n, np.int32)
    centres = []
    for k in range(n_objects):
        a = 2 * math.pi * k / n_objects
        centres.append((0.9 * math.cos(a), 0.9 * math.sin(a)))
    obj_pts = []
    per = (n - n_shell) // n_objects
    for k, (cx, cy) in enumerate(centres):
        m = per if k < n_objects - 1 else n - n_shell - per * (n_objects - 1)
        size = np.array([0.2, 0.2, 0.25 + 0.05 * k])
        p = rng.uniform(-1, 1, (m, 3))
        # Push samples to the box surface: the largest coordinate goes to +-1.
        axis = np.argmax(np.abs(p), axis=1)
        p[np.arange(m), axis] = np.sign(p[np.arange(m), axis])
        p = p * size + np.array([cx, cy, size[2]])
        obj_pts.append(p)
        start = n_shell + per * k
        ids[start : start + m] = k + 1
    means = np.concatenate([pts, *obj_pts]).astype(np.float32)
    palette = rng.uniform(0.1, 0.9, (n_objects + 1, 3))
    rgb = palette[ids] + rng.normal(0, 0.03, (n, 3))
    spacing = math.sqrt(90.0 / n)  # about the distance between neighbours on the surfaces
    k_rest = 3 * ((sh_degree + 1) ** 2 - 1)
    v = np.zeros(n, dtype=[(nm, "<f4") for nm in vertex_fields(sh_degree)])
    v["x"], v["y"], v["z"] = means.T
    for c in range(3):
        v[f"f_dc_{c}"] = (rgb[:, c] - 0.5) / SH_C0
    for i in range(k_rest):
        v[f"f_rest_{i}"] = rng.normal(0, 0.05, n)
    v["opacity"] = rng.uniform(1.0, 4.0, n)  # logits: opacity 0.73-0.98
    for c in range(3):
        v[f"scale_{c}"] = np.log(spacing * rng.uniform(0.5, 1.2, n))
    q = rng.normal(size=(n, 4))
    for c in range(4):
        v[f"rot_{c}"] = q[:, c]
    return v, ids


def object_features(
    rast: Rasterizer,
    cams: list[Camera],
    ids: np.ndarray,
    out: Path,
    dim: int = 384,
    stride: int = 8,
    noise: float = 0.3,
    seed: int = 0,
) -> np.ndarray:
    """Write `<view>.npy` [dim, H // stride, W // stride] float16 for every camera: each object
    (ids [G], 0 = the room shell) has one random unit feature; a cell holds the blend of the
    objects it shows plus noise, as a dense language encoder's map would. Rendered directly at
    the feature grid's size (a camera scaled down), which is what makes 200 views of a
    3M-Gaussian scene take a minute rather than an hour. Returns the objects' features [K, dim]
    (a stand-in for the text embedding of each object's name)."""
    rng = np.random.default_rng(seed)
    k = int(ids.max()) + 1
    objects = rng.normal(size=(k, dim)).astype(np.float32)
    objects /= np.linalg.norm(objects, axis=1, keepdims=True)
    onehot = np.zeros((len(ids), k), np.float32)  # [G, K]
    onehot[np.arange(len(ids)), ids] = 1.0
    out.mkdir(parents=True, exist_ok=True)
    for cam in cams:
        small = cam.scaled(cam.width // stride, cam.height // stride)
        share = rast.render_features(small, onehot).image  # [h, w, K]
        f = share @ objects + rng.normal(0, noise / np.sqrt(dim), (*share.shape[:2], dim))
        np.save(out / f"{cam.name}.npy", f.transpose(2, 0, 1).astype(np.float16))
    return objects

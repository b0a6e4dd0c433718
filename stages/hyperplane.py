"""`goi fit-hyperplane`: the Optimizable Semantic-space Hyperplane (OSH), paper section 3.5.

A pixel or Gaussian is of interest when its decoded feature x satisfies W x + b > 0. W starts as
the prompt's text embedding and b as minus the fixed cosine threshold, which is exactly the
fixed-threshold query (the baseline); the plane is then fitted against a RES mask of the prompt
on one or more views, with the paper's weighted logistic loss (or the authors' hinge loss),
full batch SGD, and an early stop once the plane's mask agrees with the RES mask.

Why it is cheap: a decoded feature is always one of the N codebook entries, so the loss over all
pixels only depends on how many positive and negative RES pixels decode to each entry. Fitting
works on those N (weighted) points, and the plane's decision is stored as one score per entry:
masks and selections are then a table lookup, and a cached prompt costs no fitting at all.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from pathlib import Path

import h5py
import numpy as np

from stages.artifacts import atomic_path, open_h5, put, sha256_file, stamp
from stages.cameras import Camera
from stages.errors import GoiError, warn
from stages.field import Field
from stages.prompts import safe_name
from stages.semantic_render import SemanticRenderer

SCHEMA = "goi.hyperplanes"
#: The fixed cosine threshold between a decoded feature and the prompt's embedding: the
#: baseline's cut and the hyperplane's starting bias. One value for every prompt and scene,
#: chosen before any evaluation (between the cosines of unrelated texts, ~0.1-0.3, and of a text
#: and its own object's feature, ~0.6-0.9, for sentence-model embeddings); never tuned on test
#: masks.
THRESHOLD = 0.5
LOSSES = ("logistic", "hinge")


@dataclass
class HyperplaneOptions:
    out: Path
    """Hyperplanes artifact (HDF5, schema goi.hyperplanes): created, or the prompt is added to
    it. A prompt already fitted with the same field, masks and options is reused as it is."""
    loss: str = "logistic"
    """logistic: the paper's weighted logistic regression; hinge: the authors' code."""
    positive_weight: float = 0.1
    """w on the positive (target) term of the logistic loss (paper: 1/10)."""
    threshold: float = THRESHOLD
    """Fixed cosine threshold: the starting bias b = -threshold, and the baseline's cut."""
    lr: float = 0.01
    """SGD learning rate (authors: 0.01)."""
    steps: int = 8000
    """At most this many full-batch steps (authors: 8000)."""
    target_iou: float = 0.9
    """Stop once the plane's mask reaches this IoU with the RES mask (authors: 0.9)."""
    fit_views: int = 1
    """Number of views to fit on (paper: 1): those whose RES mask is largest."""
    fit_on: str | None = None
    """Comma-separated views to fit on, instead of choosing them."""
    refit: bool = False
    """Fit again even when the artifact already holds this prompt."""

    def config(self) -> dict:
        return {
            f.name: getattr(self, f.name) for f in fields(self) if f.name not in ("out", "refit")
        }


@dataclass
class Hyperplane:
    prompt: str
    W: np.ndarray  # [D]
    b: float
    scores: np.ndarray  # [N] W T_k + b for each unit codebook entry
    text: np.ndarray  # [D] the prompt's unit embedding
    info: dict = field(default_factory=dict)

    @property
    def positive(self) -> np.ndarray:
        """[N] bool: the codebook entries on the positive side."""
        return self.scores > 0


def threshold_plane(prompt: str, text: np.ndarray, field_: Field, threshold: float) -> Hyperplane:
    """The fixed-threshold query as a plane: cos(T_k, t) > threshold."""
    W = text.astype(np.float64)
    b = -float(threshold)
    scores = field_.unit_codebook().astype(np.float64) @ W + b
    return Hyperplane(prompt, W.astype(np.float32), b, scores.astype(np.float32), text, {})


@dataclass
class Counts:
    """RES pixels per codebook entry: how many decode to entry k inside / outside the mask."""

    pos: np.ndarray  # [N] float64
    neg: np.ndarray  # [N] float64

    def iou(self, decision: np.ndarray) -> float:
        tp = self.pos[decision].sum()
        fp = self.neg[decision].sum()
        fn = self.pos[~decision].sum()
        return float(tp / max(tp + fp + fn, 1))


def count_pixels(index: np.ndarray, covered: np.ndarray, mask: np.ndarray, n: int) -> Counts:
    """Counts over the covered pixels of one view ([H, W] each)."""
    idx = index[covered]
    m = mask[covered]
    return Counts(
        np.bincount(idx[m], minlength=n).astype(np.float64),
        np.bincount(idx[~m], minlength=n).astype(np.float64),
    )


def loss_gradient(counts: Counts, z: np.ndarray, o: HyperplaneOptions) -> np.ndarray:
    """dL/dz_k [N] of the loss summed per entry, z_k = W T_k + b (see fit_osh)."""
    P = max(counts.pos.sum() + counts.neg.sum(), 1.0)
    if o.loss == "logistic":
        p = 1.0 / (1.0 + np.exp(-z))
        return (-o.positive_weight * counts.pos * (1 - p) + counts.neg * p) / P
    return (-counts.pos * (z < 1) + counts.neg * (z > -1)) / P


def fit_osh(
    counts: Counts, unit_codebook: np.ndarray, text: np.ndarray, o: HyperplaneOptions
) -> tuple[np.ndarray, float, dict]:
    """Full-batch SGD on the N weighted codebook points; returns W [D], b and a record.

    The per-pixel loss of the paper,
        -(1/P) sum_i [w m_i log s(z_i) + (1 - m_i) log(1 - s(z_i))],
    summed by entry is (1/P) sum_k [w pos_k softplus(-z_k) + neg_k softplus(z_k)] with
    z_k = W T_k + b, which has the same value and gradient. The hinge loss likewise:
    (1/P) sum_k [pos_k max(0, 1 - z_k) + neg_k max(0, 1 + z_k)].
    The best plane seen (by IoU with the RES mask) is kept, as the early stop would keep it.
    """
    T = unit_codebook.astype(np.float64)  # [N, D]
    W = text.astype(np.float64).copy()
    b = -float(o.threshold)
    z = T @ W + b
    iou0 = counts.iou(z > 0)
    best = (iou0, W.copy(), b, 0)
    step = 0
    while step < o.steps and best[0] < o.target_iou:
        g = loss_gradient(counts, z, o)
        W -= o.lr * (T.T @ g)
        b -= o.lr * float(g.sum())
        z = T @ W + b
        step += 1
        iou = counts.iou(z > 0)
        if iou > best[0]:
            best = (iou, W.copy(), b, step)
    iou, W, b, at = best
    return W, b, {"res_iou_init": iou0, "res_iou": iou, "steps_run": step, "best_step": at}


class ResFiles:
    """RES masks made by any external tool: DIR/<view>.png (a prompt's own directory)."""

    def __init__(self, root: Path, prompt_id: str | None, prompt: str):
        root = Path(root)
        if not root.is_dir():
            raise GoiError(f"--res-masks: {root} is not a directory")
        candidates = [root / prompt_id] if prompt_id else [root / safe_name(prompt), root]
        for c in candidates:
            if c.is_dir() and any(c.glob("*.png")):
                self.dir = c
                break
        else:
            raise GoiError(
                f"--res-masks: no <view>.png masks in {candidates[0]}"
                + ("" if prompt_id else f" nor {root}; pass --prompt-id to name the subdirectory")
            )
        self.source = f"files:{self.dir}"

    def available(self, cams: list[Camera]) -> list[Camera]:
        return [c for c in cams if (self.dir / f"{c.name}.png").is_file()]

    def mask(self, cam: Camera) -> np.ndarray:
        import cv2

        from stages.scene import read_mask

        path = self.dir / f"{cam.name}.png"
        if not path.is_file():
            raise GoiError(f"--res-masks: no mask {path} for view '{cam.name}'")
        m = read_mask(path)
        if m.shape != (cam.height, cam.width):
            warn(
                f"{path}: mask is {m.shape[1]}x{m.shape[0]}, the view {cam.width}x{cam.height}; "
                "resized (nearest)"
            )
            m = cv2.resize(
                m.astype(np.uint8), (cam.width, cam.height), interpolation=cv2.INTER_NEAREST
            ).astype(bool)
        return m

    def digest(self, cams: list[Camera]) -> str:
        h = hashlib.sha256()
        for c in cams:
            h.update(c.name.encode() + sha256_file(self.dir / f"{c.name}.png").encode())
        return h.hexdigest()


class ResModel:
    """RES masks from a bundle's res.onnx, run on the RGB rendered at each view."""

    def __init__(self, bundle_dir: Path, prompt: str, renderer: SemanticRenderer):
        from stages.bundle import load_bundle

        self.bundle = load_bundle(bundle_dir)
        if not self.bundle.has_res:
            raise GoiError(
                f"{bundle_dir}: the bundle has no 'res' model; pass --res-masks DIR instead"
            )
        self.prompt = prompt
        self.renderer = renderer
        self.source = f"bundle:{self.bundle.name}"

    def available(self, cams: list[Camera]) -> list[Camera]:
        return cams

    def mask(self, cam: Camera) -> np.ndarray:
        rgb = self.renderer.rast.render_rgb(cam).image
        return self.bundle.segment((np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8), self.prompt)

    def digest(self, cams: list[Camera]) -> str:
        return hashlib.sha256(
            (self.bundle.digest() + ",".join(c.name for c in cams)).encode()
        ).hexdigest()


def choose_views(
    source: ResFiles | ResModel, cams: list[Camera], o: HyperplaneOptions
) -> list[tuple[Camera, np.ndarray]]:
    """The fitting views and their RES masks: named ones, or the largest non-empty masks."""
    by_name = {c.name: c for c in cams}
    if o.fit_on:
        chosen = []
        for name in [v.strip() for v in o.fit_on.split(",") if v.strip()]:
            if name not in by_name:
                raise GoiError(f"--fit-on: the scene has no training view '{name}'")
            m = source.mask(by_name[name])
            if not m.any():
                raise GoiError(
                    f"--fit-on: the RES mask of view '{name}' is empty ({source.source})"
                )
            chosen.append((by_name[name], m))
        if not chosen:
            raise GoiError("--fit-on: no view named")
        return chosen
    if o.fit_views < 1:
        raise GoiError("--fit-views must be at least 1")
    pool = source.available(cams)
    if isinstance(source, ResModel):
        # a model costs a run per view: try evenly spaced views until enough are non-empty
        step = max(1, len(pool) // (3 * o.fit_views))
        pool = pool[::step][: 3 * o.fit_views]
    masks = [(c, source.mask(c)) for c in pool]
    masks = [(c, m) for c, m in masks if m.any()]
    if not masks:
        raise GoiError(f"{source.source}: every RES mask of this prompt is empty; nothing to fit")
    masks.sort(key=lambda cm: (-int(cm[1].sum()), cm[0].name))
    return masks[: o.fit_views]


def field_key(field_path: Path) -> str:
    return sha256_file(field_path)


def _fit_key(field_sha: str, text: np.ndarray, mask_digest: str, o: HyperplaneOptions) -> str:
    h = hashlib.sha256()
    h.update(field_sha.encode())
    h.update(np.ascontiguousarray(text, np.float32).tobytes())
    h.update(mask_digest.encode())
    h.update(json.dumps(o.config(), sort_keys=True).encode())
    return h.hexdigest()


def read_hyperplanes(path: str | os.PathLike[str]) -> dict[str, Hyperplane]:
    """Every prompt of a hyperplanes artifact, keyed by prompt text."""
    out = {}
    with open_h5(path, SCHEMA) as f:
        for key, g in f.get("prompts", {}).items():
            info = {k: (v.item() if hasattr(v, "item") else v) for k, v in g.attrs.items()}
            info["key"] = key
            out[str(g.attrs["prompt"])] = Hyperplane(
                str(g.attrs["prompt"]),
                g["W"][()],
                float(g.attrs["b"]),
                g["entry_scores"][()],
                g["text_embedding"][()],
                info,
            )
    return out


def _write(path: Path, planes: dict[str, Hyperplane], inputs: dict[str, str]) -> None:
    with atomic_path(path, force=True) as tmp, h5py.File(tmp, "w", track_order=True) as f:
        stamp(f, SCHEMA, inputs)
        root = f.create_group("prompts", track_order=True)
        for prompt in sorted(planes):
            p = planes[prompt]
            g = root.create_group(safe_name(prompt))
            g.attrs["prompt"] = prompt
            g.attrs["b"] = float(p.b)
            for k, v in p.info.items():
                if k not in ("key", "prompt", "b"):
                    g.attrs[k] = v
            put(g, "W", p.W.astype(np.float32))
            put(g, "entry_scores", p.scores.astype(np.float32))
            put(g, "text_embedding", p.text.astype(np.float32))


def fit_hyperplane(
    renderer: SemanticRenderer,
    field_path: Path,
    cams: list[Camera],
    prompt: str,
    text: np.ndarray,
    text_source: str,
    masks: ResFiles | ResModel,
    o: HyperplaneOptions,
    report: Callable[[str], None] = lambda s: None,
) -> tuple[Hyperplane, bool]:
    """Fit (or reuse) the prompt's plane and store it in o.out; returns it and whether cached."""
    if o.loss not in LOSSES:
        raise GoiError(f"--loss: {o.loss!r} is not one of {', '.join(LOSSES)}")
    if o.steps < 0 or o.lr <= 0:
        raise GoiError("--steps must be >= 0 and --lr positive")
    out = Path(o.out)
    existing = read_hyperplanes(out) if out.exists() else {}
    field_sha = field_key(field_path)
    # The key covers every candidate mask file, so a hit needs no mask decoded at all.
    key = _fit_key(field_sha, text, masks.digest(masks.available(cams)), o)
    old = existing.get(prompt)
    if old is not None and old.info.get("fit_key") == key and not o.refit:
        return old, True
    chosen = choose_views(masks, cams, o)
    n = renderer.field.codebook.shape[0]
    counts = Counts(np.zeros(n), np.zeros(n))
    for cam, m in chosen:
        view = renderer.render(cam)
        c = count_pixels(view.index, view.covered, m, n)
        counts.pos += c.pos
        counts.neg += c.neg
    if counts.pos.sum() == 0:
        raise GoiError(
            f"{masks.source}: the RES masks of views {', '.join(c.name for c, _ in chosen)} "
            "cover no rendered pixel of the scene"
        )
    unit = renderer.field.unit_codebook().astype(np.float64)  # [N, D]
    W, b, rec = fit_osh(counts, unit, text, o)
    scores = (unit @ W + b).astype(np.float32)
    info = {
        "text_source": text_source,
        "mask_source": masks.source,
        "views": json.dumps([c.name for c, _ in chosen]),
        "field_sha256": field_sha,
        "fit_key": key,
        "config": json.dumps(o.config(), sort_keys=True),
        **rec,
    }
    plane = Hyperplane(prompt, W.astype(np.float32), b, scores, text.astype(np.float32), info)
    report(
        f"fitted on {', '.join(c.name for c, _ in chosen)}: IoU with the RES mask "
        f"{rec['res_iou_init']:.3f} -> {rec['res_iou']:.3f} in {rec['steps_run']} steps"
    )
    planes = {k: v for k, v in existing.items() if k != prompt}
    planes[prompt] = plane
    _write(out, planes, {"field": field_sha})
    return plane, False


def load_plane(path: Path, prompt: str) -> Hyperplane:
    planes = read_hyperplanes(path)
    if prompt not in planes:
        listed = ", ".join(repr(p[:40]) for p in sorted(planes)[:5])
        raise GoiError(
            f"{path}: no hyperplane for prompt {prompt[:80]!r} (it holds {listed or 'none'}); "
            "run goi fit-hyperplane first"
        )
    return planes[prompt]

"""The hyperplanes artifact (schema goi.hyperplanes) and `goi fit-hyperplane`.

Each prompt's plane is stored with W, b, the text embedding and one score per codebook entry,
keyed by prompt, together with a fit key (field, text, masks, options): the same prompt with
the same field, masks and options is never refitted, and a cache hit decodes no mask.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from stages.core.arrays import require_finite
from stages.core.artifacts import atomic_path, check_writable, open_h5, put, sha256_file, stamp
from stages.core.errors import GoiError
from stages.core.files import refuse_inputs
from stages.core.params import check_params
from stages.core.report import SILENT, Report
from stages.query.osh import Counts, Hyperplane, HyperplaneParams, count_pixels, fit_osh
from stages.query.prompts import Prompt
from stages.query.res import ResIndexed, ResModel, ResSource, choose_views, write_res_masks
from stages.scene.cameras import Camera
from stages.semantics.decode import SemanticRenderer

SCHEMA = "goi.hyperplanes"


@dataclass
class HyperplaneRun:
    out: Path
    """Hyperplanes artifact (HDF5, schema goi.hyperplanes): created, or the prompt is added to
    it. A prompt already fitted with the same field, masks and options is reused as it is."""
    refit: bool = False
    """Fit again even when the artifact already holds this prompt."""


def res_masks_dir(out: Path, prompt: Prompt) -> Path:
    """Where a fit writes the RES masks a model made for it: beside the hyperplanes artifact,
    in the prompt's own directory (the one `goi query` writes the prompt's outputs to)."""
    return Path(out).parent / prompt.name / "res"


def wrote_res_masks(masks: ResSource, cached: bool) -> bool:
    """Whether a fit wrote RES masks: it ran a model (a cached plane needs none)."""
    return isinstance(masks, ResModel | ResIndexed) and not cached


def field_key(field_path: Path) -> str:
    return sha256_file(field_path)


def _fit_key(field_sha: str, text: np.ndarray, mask_digest: str, p: HyperplaneParams) -> str:
    h = hashlib.sha256()
    h.update(field_sha.encode())
    h.update(np.ascontiguousarray(text, np.float32).tobytes())
    h.update(mask_digest.encode())
    h.update(json.dumps(p.config(), sort_keys=True).encode())
    return h.hexdigest()


def read_hyperplanes(path: str | os.PathLike[str]) -> dict[str, Hyperplane]:
    """Every prompt of a hyperplanes artifact, keyed by prompt text."""
    out = {}
    with open_h5(path, SCHEMA) as f:
        for key, g in f.get("prompts", {}).items():
            where = f"{path}: prompts/{key}"
            info = {k: (v.item() if hasattr(v, "item") else v) for k, v in g.attrs.items()}
            info["key"] = key
            plane = Hyperplane(
                str(g.attrs["prompt"]),
                require_finite(g["W"][()], f"{where}/W"),
                float(require_finite(np.asarray(g.attrs["b"], np.float64), f"{where} attribute b")),
                require_finite(g["entry_scores"][()], f"{where}/entry_scores"),
                require_finite(g["text_embedding"][()], f"{where}/text_embedding"),
                info,
            )
            if plane.W.ndim != 1 or plane.W.shape != plane.text.shape:
                raise GoiError(
                    f"{where}: W has shape {plane.W.shape} and text_embedding "
                    f"{plane.text.shape}; both must be one vector of the feature dimension"
                )
            if plane.prompt in out:
                raise GoiError(f"{where}: prompt {plane.prompt[:60]!r} is stored twice")
            out[plane.prompt] = plane
    return out


def _write(path: Path, planes: dict[str, Hyperplane], inputs: dict[str, str]) -> None:
    with atomic_path(path, force=True) as tmp, h5py.File(tmp, "w", track_order=True) as f:
        stamp(f, SCHEMA, inputs)
        root = f.create_group("prompts", track_order=True)
        for prompt in sorted(planes):
            p = planes[prompt]
            g = root.create_group(Prompt(prompt).name)  # the text read back: its stored name
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
    prompt: Prompt,
    text: np.ndarray,
    text_source: str,
    masks: ResSource,
    p: HyperplaneParams,
    run: HyperplaneRun,
    report: Report = SILENT,
) -> tuple[Hyperplane, bool]:
    """Fit (or reuse) the prompt's plane and store it in run.out; returns it and whether it
    came from the artifact. When a RES model made the masks, the ones the fit used are written
    to `res_masks_dir(run.out, prompt)`."""
    check_params(p)
    out = Path(run.out)
    refuse_inputs({"--out": out}, [field_path])
    check_writable(out, True, "--out")  # the prompt is added to an existing artifact
    existing = read_hyperplanes(out) if out.exists() else {}
    field_sha = field_key(field_path)
    # The key covers every candidate mask file, so a hit needs no mask decoded at all.
    key = _fit_key(field_sha, text, masks.digest(masks.available(cams)), p)
    old = existing.get(prompt.text)
    # a stored plane of another shape (a damaged or edited file) is refitted, never used
    n = renderer.field.codebook.shape[0]
    fits = old is not None and old.W.shape == text.shape and old.scores.size == n
    if old is not None and fits and old.info.get("fit_key") == key and not run.refit:
        return old, True
    chosen = choose_views(masks, cams, p)
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
    W, b, rec = fit_osh(counts, unit, text, p)
    scores = (unit @ W + b).astype(np.float32)
    info = {
        "text_source": text_source,
        "mask_source": masks.source,
        "views": json.dumps([c.name for c, _ in chosen]),
        "field_sha256": field_sha,
        "fit_key": key,
        "config": json.dumps(p.config(), sort_keys=True),
        **rec,
    }
    plane = Hyperplane(prompt.text, W.astype(np.float32), b, scores, text.astype(np.float32), info)
    report.log(
        f"fitted on {', '.join(c.name for c, _ in chosen)}: IoU with the RES mask "
        f"{rec['res_iou_init']:.3f} -> {rec['res_iou']:.3f} in {rec['steps_run']} steps"
    )
    planes = {k: v for k, v in existing.items() if k != prompt.text}
    planes[prompt.text] = plane
    write_res_masks(masks, [c.name for c, _ in chosen], res_masks_dir(out, prompt))
    _write(out, planes, {"field": field_sha})
    return plane, False


def load_plane(
    path: Path, prompt: str, field_path: Path, n_entries: int, dim: int | None = None
) -> Hyperplane:
    """The prompt's plane, refused when it was fitted for another field than `field_path`
    (its scores would name another codebook's entries) or, given the field's feature
    dimension `dim`, when its W is of another dimension."""
    planes = read_hyperplanes(path)
    if prompt not in planes:
        listed = ", ".join(repr(p[:40]) for p in sorted(planes)[:5])
        raise GoiError(
            f"{path}: no hyperplane for prompt {prompt[:80]!r} (it holds {listed or 'none'}); "
            "run goi fit-hyperplane first"
        )
    plane = planes[prompt]
    if plane.info.get("field_sha256") != field_key(field_path) or plane.scores.size != n_entries:
        raise GoiError(
            f"{path}: the hyperplane of {prompt[:60]!r} was fitted on another field than "
            f"{field_path}; fit it again with this field (goi fit-hyperplane)"
        )
    if dim is not None and plane.W.shape != (dim,):
        raise GoiError(
            f"{path}: the hyperplane of {prompt[:60]!r} has {plane.W.size} dimensions, the "
            f"field {field_path} {dim}; fit it again with this field (goi fit-hyperplane)"
        )
    return plane


def check_plane_out(out: Path, inputs: list[Path | None]) -> dict[str, Hyperplane]:
    """Preflight of the hyperplanes artifact a plane is added to: never an input, a file goi
    can write, and (when it exists) a readable hyperplanes artifact; returns its planes."""
    out = Path(out)
    refuse_inputs({"--out": out}, inputs)
    check_writable(out, True, "--out")  # the prompt is added to an existing artifact
    return read_hyperplanes(out) if out.exists() else {}


def add_plane(out: Path, plane: Hyperplane, field_path: Path, record: dict) -> Path:
    """Store a plane fitted elsewhere (goi fit-hyperplane --lift: on lifted evidence) in the
    artifact, replacing the prompt's plane; `record` (views, parameters) goes with it."""
    out = Path(out)
    existing = check_plane_out(out, [field_path])
    field_sha = field_key(field_path)
    info = {
        "text_source": "lifted",
        "mask_source": "lifted",
        "views": json.dumps(record.get("views", [])),
        "field_sha256": field_sha,
        "fit_key": "",
        "config": json.dumps(record, sort_keys=True, default=str),
        **{k: v for k, v in plane.info.items() if isinstance(v, int | float | str)},
    }
    planes = {k: v for k, v in existing.items() if k != plane.prompt}
    planes[plane.prompt] = Hyperplane(
        plane.prompt, plane.W, plane.b, plane.scores, plane.text, info
    )
    _write(out, planes, {"field": field_sha})
    return out

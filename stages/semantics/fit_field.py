"""`goi fit-field`: the training loop of the semantic field (geometry frozen).

Each iteration draws a few training views and feature cells, renders the field at those cells
through the blend cache (pooled to the feature maps' grid), and takes one Adam step on the
paper's losses (`field_model`). Checkpoints let an interrupted fit resume bit for bit.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import torch

from stages.core.artifacts import check_writable, input_digest
from stages.core.errors import GoiError
from stages.core.files import refuse_inputs
from stages.core.params import NON_NEGATIVE, check_params
from stages.core.report import SILENT, Report
from stages.scene.scene import Scene
from stages.semantics.blend_cache import build_or_load, cache_target
from stages.semantics.checkpoint import check_checkpoint, load_checkpoint, save_checkpoint
from stages.semantics.codebook import load_codebook
from stages.semantics.feature_renderer import FeatureRenderer
from stages.semantics.features import feature_grid, feature_views, load_features
from stages.semantics.field import save_field
from stages.semantics.field_model import PARAMETERS, FieldModel, FieldParams, field_losses


@dataclass
class FieldRun:
    out: Path
    """Field artifact to write (HDF5, schema goi.field)."""
    cache: Path | None = None
    """Blend cache file; default blend_cache.h5 beside the output. Reused when it matches."""
    checkpoint_every: Annotated[int, NON_NEGATIVE] = 250
    """Write <out>.ckpt every this many iterations (0: never)."""
    resume: bool = False
    """Continue from <out>.ckpt when it exists (and was made from the same inputs)."""
    force: bool = False
    """Replace an existing output."""

    @property
    def checkpoint(self) -> Path:
        return self.out.with_name(self.out.name + ".ckpt")


def field_inputs(scene: Scene, features_path: Path, codebook_path: Path) -> dict[str, str]:
    return {
        "ply": scene.ply_digest(),
        "cameras": scene.cameras_digest(),
        **input_digest("features", features_path),
        **input_digest("codebook", codebook_path),
    }


def _deterministic(fn: Callable[..., Path]) -> Callable[..., Path]:
    """Run with torch's deterministic kernels. The codebook's gradient through T[argmax e] is an
    indexed accumulation, which torch otherwise runs with unordered parallel adds on the CPU, so
    two runs with the same seed would differ in the last bits."""

    @functools.wraps(fn)
    def run(*args: Any, **kwargs: Any) -> Path:
        before = torch.are_deterministic_algorithms_enabled()
        torch.use_deterministic_algorithms(True)
        try:
            return fn(*args, **kwargs)
        finally:
            torch.use_deterministic_algorithms(before)

    return run


@_deterministic
def fit_field(
    scene: Scene,
    features_path: Path,
    codebook_path: Path,
    p: FieldParams,
    run: FieldRun,
    report: Report = SILENT,
) -> Path:
    # Everything is checked before the blend cache is built (minutes on a big scene).
    check_params(p)
    check_params(run)
    check_writable(run.out, run.force)
    cache_path = run.cache or run.out.with_name("blend_cache.h5")
    outputs = {"--out": run.out, "--cache": cache_path}
    refuse_inputs(outputs, [scene.ply_path, *scene.camera_files, features_path, codebook_path])
    if cache_path.resolve() == run.out.resolve():
        raise GoiError(f"--cache: {cache_path} is also --out; give them different paths")
    g = scene.gaussians
    train = scene.views("train")
    views = [c.name for c in train]
    sizes = feature_grid(features_path, views)
    dim, _ = feature_views(features_path)
    codebook = load_codebook(codebook_path)
    if codebook.shape[1] != dim:
        raise GoiError(
            f"{codebook_path}: codebook entries have dimension {codebook.shape[1]}, "
            f"but the features in {features_path} have {dim}"
        )
    inputs = field_inputs(scene, features_path, codebook_path)
    shapes = {
        "features": (g.count, p.sem_dim),
        "decoder_weight": (dim if p.no_tfcc else codebook.shape[0], p.sem_dim),
        "decoder_bias": (dim if p.no_tfcc else codebook.shape[0],),
        "codebook": codebook.shape,
    }
    if run.resume and run.checkpoint.is_file():
        check_checkpoint(run.checkpoint, inputs, p.config(), shapes)
    cache_target(cache_path, scene, train, p.top_k, sizes, run.force)

    fm = load_features(features_path, views)
    cache = build_or_load(cache_path, scene, train, p.top_k, sizes, report, run.force)
    fr = FeatureRenderer(cache, views)
    targets = {v: torch.from_numpy(m.reshape(-1, fm.dim)) for v, m in fm.maps.items()}

    torch.manual_seed(p.seed)
    model = FieldModel(g.count, p.sem_dim, codebook, p.no_tfcc)
    opt = torch.optim.Adam(
        [
            {"params": [model.features], "lr": p.lr_features, "eps": 1e-15},
            {"params": model.decoder.parameters(), "lr": p.lr_decoder},
            {"params": [model.codebook], "lr": p.lr_codebook},
        ]
    )
    rng = np.random.default_rng(p.seed)
    curve: list[list[float]] = []
    start = 0
    if run.resume and run.checkpoint.is_file():
        start, curve = load_checkpoint(run.checkpoint, model, opt, rng, inputs, p.config())
        report.log(f"resuming {run.checkpoint} at iteration {start}")

    def show(_: object) -> str:
        if not curve:
            return ""
        return "loss {:.3f} (ent {:.3f} max {:.3f} joint {:.3f} e2e {:.3f})".format(*curve[-1])

    steps = range(start, p.iterations)
    for it in report.progress(steps, "fit-field", length=len(steps), show=show):
        pick = rng.choice(len(views), min(p.views_per_step, len(views)), replace=False)
        rows, tgt = [], []
        for vi in sorted(pick):
            v = views[vi]
            n_cells = sizes[v][0] * sizes[v][1]
            if 0 < p.cells_per_view < n_cells:
                cells = np.sort(rng.choice(n_cells, p.cells_per_view, replace=False))
            else:
                cells = np.arange(n_cells)
            rows.append(fr.rows(v, cells))
            tgt.append(targets[v][torch.from_numpy(cells)])
        f_hat = fr.render(model.features, np.concatenate(rows))  # [B, S]
        loss, parts = field_losses(model, f_hat, torch.cat(tgt), p.tau(it), p)
        if not np.isfinite(parts[0]):
            raise GoiError(
                f"fit-field diverged at iteration {it} (loss {parts[0]}): lower the learning rates"
            )
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        curve.append(parts)
        done = it + 1
        if run.checkpoint_every and done % run.checkpoint_every == 0 and done < p.iterations:
            save_checkpoint(run.checkpoint, model, opt, rng, done, curve, inputs, p.config())

    tensors = {
        name: t.detach().numpy() for name, t in zip(PARAMETERS, model.parameter_list(), strict=True)
    }
    save_field(run.out, tensors, np.asarray(curve), views, p.config(), inputs, run.force)
    run.checkpoint.unlink(missing_ok=True)
    return run.out

"""fit-field checkpoints (schema goi.field_checkpoint): parameters, Adam moments, the sampler's
state and the loss curve, so that a resumed fit continues bit for bit."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from stages.core.arrays import require_finite
from stages.core.artifacts import open_h5, put, write_h5
from stages.core.errors import GoiError
from stages.semantics.field_model import PARAMETERS, FieldModel

SCHEMA = "goi.field_checkpoint"
SHARD_SCHEMA = "goi.field_checkpoint_shard"


def save_checkpoint(
    path: Path,
    model: FieldModel,
    opt: torch.optim.Optimizer,
    rng: np.random.Generator,
    iteration: int,
    curve: list[list[float]],
    inputs: dict[str, str],
    config: dict,
    schema: str = SCHEMA,
    attrs: dict[str, int] | None = None,
) -> None:
    """`schema` and `attrs`: a distributed fit's per-rank checkpoint (SHARD_SCHEMA) records
    its rank and columns."""
    with write_h5(path, schema, inputs, force=True) as f:
        f.attrs.update(
            iteration=iteration,
            rng_state=json.dumps(rng.bit_generator.state),
            config=json.dumps(config, sort_keys=True),
            **(attrs or {}),
        )
        # Per-Gaussian rows in PLY order, whatever order the model holds them in.
        for name, p in zip(PARAMETERS, model.parameter_list(), strict=True):
            rows = model.ply_rows if name == "features" else _same
            put(f, name, rows(p.detach().numpy()))
            st = opt.state.get(p, {})
            if st:
                grp = f.create_group(f"adam/{name}")
                put(grp, "exp_avg", rows(st["exp_avg"].numpy()))
                put(grp, "exp_avg_sq", rows(st["exp_avg_sq"].numpy()))
                put(grp, "step", np.float32(st["step"]))
        put(f, "loss_curve", np.asarray(curve, np.float32).reshape(-1, 5))


def _same(a: np.ndarray) -> np.ndarray:
    return a


def check_checkpoint(
    path: Path,
    inputs: dict[str, str],
    config: dict,
    shapes: dict[str, tuple[int, ...]],
    schema: str = SCHEMA,
    attrs: dict[str, int] | None = None,
) -> int:
    """Refuse, before any work, a checkpoint that is damaged or was made from other inputs,
    other options, for other tensor shapes (or another rank's columns: `attrs`); returns the
    iteration it reached."""
    with open_h5(path, schema) as f:
        for key, value in (attrs or {}).items():
            if int(f.attrs[key]) != value:
                raise GoiError(
                    f"{path}: checkpoint has {key} {int(f.attrs[key])}, this rank {value}; "
                    "delete it or run without --resume"
                )
        if json.loads(f.attrs["inputs"]) != inputs:
            raise GoiError(
                f"{path}: checkpoint was made from other inputs (scene, features or "
                "codebook); delete it or run without --resume"
            )
        if json.loads(f.attrs["config"]) != json.loads(json.dumps(config, sort_keys=True)):
            raise GoiError(
                f"{path}: checkpoint was made with other fit-field options; use the "
                "same options or run without --resume"
            )
        for name in PARAMETERS:
            if tuple(f[name].shape) != tuple(shapes[name]):
                raise GoiError(
                    f"{path}: '{name}' has shape {f[name].shape}, expected {tuple(shapes[name])}"
                )
            require_finite(f[name][()], f"{path}: dataset '{name}'")
        iteration = int(f.attrs["iteration"])
        if not 0 < iteration or f["loss_curve"].shape[0] != iteration:
            raise GoiError(f"{path}: damaged checkpoint (iteration {iteration})")
        try:
            np.random.default_rng().bit_generator.state = json.loads(f.attrs["rng_state"])
        except (ValueError, TypeError, KeyError) as e:
            raise GoiError(f"{path}: damaged checkpoint (sampler state: {e})") from None
        return iteration


def load_checkpoint(
    path: Path,
    model: FieldModel,
    opt: torch.optim.Optimizer,
    rng: np.random.Generator,
    inputs: dict[str, str],
    config: dict,
    schema: str = SCHEMA,
    attrs: dict[str, int] | None = None,
) -> tuple[int, list[list[float]]]:
    """Restore model, optimiser and sampler from `path`; returns the iteration reached and the
    loss curve so far. Refuses a checkpoint made from other inputs or options."""
    shapes = {n: tuple(t.shape) for n, t in zip(PARAMETERS, model.parameter_list(), strict=True)}
    check_checkpoint(path, inputs, config, shapes, schema, attrs)
    with open_h5(path, schema) as f:
        with torch.no_grad():
            for name, p in zip(PARAMETERS, model.parameter_list(), strict=True):
                rows = model.model_rows if name == "features" else _same
                p.copy_(torch.from_numpy(rows(f[name][()])))
                if f"adam/{name}" in f:
                    grp = f[f"adam/{name}"]
                    opt.state[p] = {
                        "step": torch.tensor(float(grp["step"][()])),
                        "exp_avg": torch.from_numpy(rows(grp["exp_avg"][()])),
                        "exp_avg_sq": torch.from_numpy(rows(grp["exp_avg_sq"][()])),
                    }
        rng.bit_generator.state = json.loads(f.attrs["rng_state"])
        return int(f.attrs["iteration"]), f["loss_curve"][()].tolist()

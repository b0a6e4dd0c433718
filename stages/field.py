"""`goi fit-field`: the 3D Gaussian semantic field with the Trainable Feature Clustering Codebook.

Per Gaussian a 10-d feature f (zero at start), rendered by alpha blending to f_hat; a linear
decoder D: 10 -> N gives logits e; the decoded feature is T[argmax e] with T the codebook.
Losses (paper section 3.4 and appendix; weights and schedule as the authors' code):
  L_ent   = entropy(softmax(tau cos(v_gt, T)))            x 0.3, tau 1 -> 2 after 2/3 of the run
  L_max   = 1 - cos(v_gt, T[d]), d = argmax cos(v_gt, T)   x 1
  L_joint = 50 MSE(softmax(e), onehot(d))                 x 1 (the authors' form of |e - 1_d|^2)
  L_e2e   = 1 - cos(v_gt, T[argmax e])                     x 1 (reaches the codebook only)
Geometry is frozen, so f_hat comes from the blend cache, pooled to the feature maps' grid.
"""

from __future__ import annotations

import functools
import json
import os
from collections.abc import Callable
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from stages.artifacts import check_writable, input_digest, open_h5, put, write_h5
from stages.blend_cache import FeatureRenderer, build_or_load
from stages.codebook import load_codebook
from stages.errors import GoiError
from stages.features import load_features
from stages.progress import progress
from stages.scene import Scene

SCHEMA = "goi.field"
CHECKPOINT = "goi.field_checkpoint"


@dataclass
class FieldOptions:
    out: Path
    """Field artifact to write (HDF5, schema goi.field)."""
    cache: Path | None = None
    """Blend cache file; default blend_cache.h5 beside the output. Reused when it matches."""
    iterations: int = 1500
    """Training iterations (paper: 1500)."""
    sem_dim: int = 10
    """Low-dimensional feature per Gaussian (paper: 10)."""
    views_per_step: int = 4
    """Training views drawn per iteration (the authors use 1 whole view)."""
    cells_per_view: int = 4096
    """Feature cells drawn from each of those views per iteration (0: all of them)."""
    lr_features: float = 0.005
    """Adam learning rate of the per-Gaussian features (authors: 0.005, eps 1e-15)."""
    lr_decoder: float = 0.003
    """Adam learning rate of the decoder (authors: 0.003)."""
    lr_codebook: float = 0.001
    """Adam learning rate of the codebook (authors: 0.001)."""
    w_ent: float = 0.3
    """Weight of L_ent (paper: 0.3)."""
    w_max: float = 1.0
    """Weight of L_max (paper: 1)."""
    w_joint: float = 1.0
    """Weight of L_joint (paper: 1)."""
    w_e2e: float = 1.0
    """Weight of L_e2e (paper: 1)."""
    tau_start: float = 1.0
    """Annealing temperature of L_ent at the start (paper: 1)."""
    tau_end: float = 2.0
    """... and after `anneal_at` of the run (paper: 2 after 1000 of 1500 iterations)."""
    anneal_at: float = 2 / 3
    """Fraction of the run after which tau_end applies."""
    top_k: int = 0
    """Keep only the K largest blending weights per pixel in the cache (0: all)."""
    no_tfcc: bool = False
    """Ablation (paper's 'without TFCC'): decode the low-dimensional features straight to the
    feature space with a linear decoder and a cosine loss, without the codebook. goi query
    needs a TFCC field; goi eval uses this for its without_tfcc and baseline variants."""
    checkpoint_every: int = 250
    """Write <out>.ckpt every this many iterations (0: never)."""
    resume: bool = False
    """Continue from <out>.ckpt when it exists (and was made from the same inputs)."""
    seed: int = 0
    """Random seed; the same seed and inputs give the same field."""
    force: bool = False
    """Replace an existing output."""

    def config(self) -> dict:
        skip = {"out", "cache", "resume", "force", "checkpoint_every"}
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name not in skip}


@dataclass
class Field:
    features: np.ndarray  # [G, S] float32, PLY order
    decoder_weight: np.ndarray  # [N, S] (direct: [D, S])
    decoder_bias: np.ndarray  # [N] (direct: [D])
    codebook: np.ndarray  # [N, D] (not necessarily unit: normalise before cosines)
    direct: bool = False  # the without-TFCC ablation: no codebook lookup
    ply_sha256: str = ""  # the PLY it was fitted for

    @property
    def seen(self) -> np.ndarray:
        """[G] bool: Gaussians some training view saw. The others keep their zero initial
        feature, and what it decodes to says nothing about them."""
        return np.any(self.features != 0, axis=1)

    def check_scene(self, ply_sha256: str, where: str) -> None:
        """Refuse to use the field with another PLY than the one it was fitted on."""
        if self.ply_sha256 and self.ply_sha256 != ply_sha256:
            raise GoiError(
                f"{where}: the field was fitted on another PLY (sha256 {self.ply_sha256[:12]}..., "
                f"this scene's is {ply_sha256[:12]}...); fit the field on this scene"
            )

    def logits(self, f: np.ndarray) -> np.ndarray:
        """[M, S] -> [M, N]"""
        return f @ self.decoder_weight.T + self.decoder_bias

    def decode_index(self, f: np.ndarray) -> np.ndarray:
        """[M, S] -> [M] codebook entry of each feature."""
        if self.direct:
            raise GoiError(
                "this field was fitted with --no-tfcc (an ablation) and has no codebook "
                "entries; queries need a field fitted with the TFCC"
            )
        return np.argmax(self.logits(f), axis=1)

    def decode_direct(self, f: np.ndarray) -> np.ndarray:
        """[M, S] -> [M, D] unit features, for a --no-tfcc field."""
        x = f.astype(np.float32) @ self.decoder_weight.T + self.decoder_bias
        return x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)

    def unit_codebook(self) -> np.ndarray:
        n = np.linalg.norm(self.codebook, axis=1, keepdims=True)
        return self.codebook / np.maximum(n, 1e-12)


def load_field(path: str | os.PathLike[str]) -> Field:
    with open_h5(path, SCHEMA) as f:
        return Field(
            f["features"][()],
            f["decoder_weight"][()],
            f["decoder_bias"][()],
            f["codebook"][()],
            str(f.attrs["decoder"]) == "direct",
            str(f.attrs["ply_sha256"]),
        )


def load_field_for(path: str | os.PathLike[str], ply_sha256: str) -> Field:
    """load_field, refusing a field fitted on another PLY than the scene's."""
    field = load_field(path)
    field.check_scene(ply_sha256, f"--field {path}")
    return field


class _Model(torch.nn.Module):
    def __init__(self, n_gaussians: int, sem_dim: int, codebook: np.ndarray, direct: bool):
        super().__init__()
        self.features = torch.nn.Parameter(torch.zeros(n_gaussians, sem_dim))
        self.decoder = torch.nn.Linear(sem_dim, codebook.shape[1 if direct else 0])
        self.codebook = torch.nn.Parameter(torch.from_numpy(codebook.copy()))


def _losses(
    model: _Model,
    fr: FeatureRenderer,
    rows: np.ndarray,
    v_gt: torch.Tensor,
    tau: float,
    o: FieldOptions,
) -> tuple[torch.Tensor, list[float]]:
    f_hat = fr.render(model.features, rows)  # [B, S]
    e = model.decoder(f_hat)  # [B, N] (direct: [B, D])
    if o.no_tfcc:
        loss = 1 - (v_gt * F.normalize(e, dim=1)).sum(1).mean()
        return loss, [float(loss.detach()), 0.0, 0.0, 0.0, float(loss.detach())]
    t_unit = F.normalize(model.codebook, dim=1)  # [N, D]
    sim = v_gt @ t_unit.T  # [B, N] cosines (v_gt is unit)
    p = torch.softmax(sim * tau, dim=1)
    l_ent = -(p * torch.log(p.clamp_min(1e-12))).sum(1).mean()
    s_max, d = sim.max(dim=1)
    l_max = 1 - s_max.mean()
    l_joint = 50 * F.mse_loss(torch.softmax(e, dim=1), F.one_hot(d, sim.shape[1]).float())
    v = t_unit[e.argmax(dim=1)]
    l_e2e = 1 - (v_gt * v).sum(1).mean()
    total = o.w_ent * l_ent + o.w_max * l_max + o.w_joint * l_joint + o.w_e2e * l_e2e
    return total, [float(x.detach()) for x in (total, l_ent, l_max, l_joint, l_e2e)]


def _inputs(scene: Scene, features_path: Path, codebook_path: Path) -> dict[str, str]:
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
def fit_field(scene: Scene, features_path: Path, codebook_path: Path, o: FieldOptions) -> Path:
    check_writable(o.out, o.force)
    if o.iterations < 1 or o.sem_dim < 1 or o.views_per_step < 1:
        raise GoiError("--iterations, --sem-dim and --views-per-step must be positive")
    g = scene.gaussians
    views = [c.name for c in scene.views("train")]
    fm = load_features(features_path, views)
    codebook = load_codebook(codebook_path)
    if codebook.shape[1] != fm.dim:
        raise GoiError(
            f"{codebook_path}: codebook entries have dimension {codebook.shape[1]}, "
            f"but the features in {features_path} have {fm.dim}"
        )
    sizes = {v: (m.shape[1], m.shape[0]) for v, m in fm.maps.items()}
    cache_path = o.cache or o.out.with_name("blend_cache.h5")
    cache = build_or_load(cache_path, scene, scene.views("train"), o.top_k, sizes)
    fr = FeatureRenderer(cache, views)
    targets = {v: torch.from_numpy(m.reshape(-1, fm.dim)) for v, m in fm.maps.items()}

    inputs = _inputs(scene, features_path, codebook_path)
    torch.manual_seed(o.seed)
    model = _Model(g.count, o.sem_dim, codebook, o.no_tfcc)
    opt = torch.optim.Adam(
        [
            {"params": [model.features], "lr": o.lr_features, "eps": 1e-15},
            {"params": model.decoder.parameters(), "lr": o.lr_decoder},
            {"params": [model.codebook], "lr": o.lr_codebook},
        ]
    )
    rng = np.random.default_rng(o.seed)
    curve: list[list[float]] = []
    start = 0
    ckpt = o.out.with_name(o.out.name + ".ckpt")
    if o.resume and ckpt.is_file():
        start, curve = _load_checkpoint(ckpt, model, opt, rng, inputs, o)
        print(f"goi: resuming {ckpt} at iteration {start}", flush=True)

    anneal = int(round(o.anneal_at * o.iterations))

    def show(_: object) -> str:
        if not curve:
            return ""
        return "loss {:.3f} (ent {:.3f} max {:.3f} joint {:.3f} e2e {:.3f})".format(*curve[-1])

    steps = range(start, o.iterations)
    for it in progress(steps, "fit-field", length=len(steps), show=show):
        pick = rng.choice(len(views), min(o.views_per_step, len(views)), replace=False)
        rows, tgt = [], []
        for vi in sorted(pick):
            v = views[vi]
            n_cells = sizes[v][0] * sizes[v][1]
            if 0 < o.cells_per_view < n_cells:
                cells = np.sort(rng.choice(n_cells, o.cells_per_view, replace=False))
            else:
                cells = np.arange(n_cells)
            rows.append(fr.rows(v, cells))
            tgt.append(targets[v][torch.from_numpy(cells)])
        tau = o.tau_start if it < anneal else o.tau_end
        loss, parts = _losses(model, fr, np.concatenate(rows), torch.cat(tgt), tau, o)
        if not np.isfinite(parts[0]):
            raise GoiError(
                f"fit-field diverged at iteration {it} (loss {parts[0]}): lower the learning rates"
            )
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        curve.append(parts)
        done = it + 1
        if o.checkpoint_every and done % o.checkpoint_every == 0 and done < o.iterations:
            _save_checkpoint(ckpt, model, opt, rng, done, curve, inputs, o)

    with write_h5(o.out, SCHEMA, inputs, o.force) as f:
        f.attrs.update(
            n_gaussians=g.count,
            sem_dim=o.sem_dim,
            n_entries=codebook.shape[0],
            dim=fm.dim,
            iterations=o.iterations,
            seed=o.seed,
            config=json.dumps(o.config(), sort_keys=True),
            ply_sha256=inputs["ply"],
            decoder="direct" if o.no_tfcc else "codebook",
        )
        put(f, "features", model.features.detach().numpy())
        put(f, "decoder_weight", model.decoder.weight.detach().numpy())
        put(f, "decoder_bias", model.decoder.bias.detach().numpy())
        put(f, "codebook", model.codebook.detach().numpy())
        put(f, "loss_curve", np.asarray(curve, np.float32).reshape(-1, 5))
        put(f, "views", np.array(views, dtype=object), compress=False)
    ckpt.unlink(missing_ok=True)
    return o.out


_PARAMS = ("features", "decoder_weight", "decoder_bias", "codebook")


def _params(model: _Model) -> list[torch.Tensor]:
    return [model.features, model.decoder.weight, model.decoder.bias, model.codebook]


def _save_checkpoint(
    path: Path,
    model: _Model,
    opt: torch.optim.Optimizer,
    rng: np.random.Generator,
    it: int,
    curve: list[list[float]],
    inputs: dict[str, str],
    o: FieldOptions,
) -> None:
    with write_h5(path, CHECKPOINT, inputs, force=True) as f:
        f.attrs.update(
            iteration=it,
            rng_state=json.dumps(rng.bit_generator.state),
            config=json.dumps(o.config(), sort_keys=True),
        )
        for name, p in zip(_PARAMS, _params(model), strict=True):
            put(f, name, p.detach().numpy())
            st = opt.state.get(p, {})
            if st:
                grp = f.create_group(f"adam/{name}")
                put(grp, "exp_avg", st["exp_avg"].numpy())
                put(grp, "exp_avg_sq", st["exp_avg_sq"].numpy())
                put(grp, "step", np.float32(st["step"]))
        put(f, "loss_curve", np.asarray(curve, np.float32).reshape(-1, 5))


def _load_checkpoint(
    path: Path,
    model: _Model,
    opt: torch.optim.Optimizer,
    rng: np.random.Generator,
    inputs: dict[str, str],
    o: FieldOptions,
) -> tuple[int, list[list[float]]]:
    with open_h5(path, CHECKPOINT) as f:
        if json.loads(f.attrs["inputs"]) != inputs:
            raise GoiError(
                f"{path}: checkpoint was made from other inputs (scene, features or "
                "codebook); delete it or run without --resume"
            )
        if json.loads(f.attrs["config"]) != json.loads(json.dumps(o.config(), sort_keys=True)):
            raise GoiError(
                f"{path}: checkpoint was made with other fit-field options; use the "
                "same options or run without --resume"
            )
        with torch.no_grad():
            for name, p in zip(_PARAMS, _params(model), strict=True):
                if tuple(f[name].shape) != tuple(p.shape):
                    raise GoiError(
                        f"{path}: '{name}' has shape {f[name].shape}, expected {tuple(p.shape)}"
                    )
                p.copy_(torch.from_numpy(f[name][()]))
                if f"adam/{name}" in f:
                    grp = f[f"adam/{name}"]
                    opt.state[p] = {
                        "step": torch.tensor(float(grp["step"][()])),
                        "exp_avg": torch.from_numpy(grp["exp_avg"][()]),
                        "exp_avg_sq": torch.from_numpy(grp["exp_avg_sq"][()]),
                    }
        rng.bit_generator.state = json.loads(f.attrs["rng_state"])
        return int(f.attrs["iteration"]), f["loss_curve"][()].tolist()

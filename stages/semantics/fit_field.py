"""`goi fit-field`: the training loop of the semantic field (geometry frozen).

Each iteration draws a few training views and feature cells, renders the field at those cells
through the blend cache (pooled to the feature maps' grid), and takes one Adam step on the
paper's losses (`field_model`). Checkpoints let an interrupted fit resume bit for bit.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from stages.core.arrays import unit_norms
from stages.core.artifacts import check_writable, input_digest
from stages.core.errors import GoiError
from stages.core.files import check_output_name, output_lock, refuse_if_input, refuse_inputs
from stages.core.params import check_params
from stages.core.report import SILENT, Report, size_text
from stages.core.torch_numerics import settle_vml
from stages.render.constants import ALPHA_MIN
from stages.scene.cameras import Camera
from stages.scene.scene import Scene
from stages.semantics.blend_cache import build_cache_file, cache_nbytes, cache_sizes, cache_target
from stages.semantics.checkpoint import check_checkpoint, load_checkpoint, save_checkpoint
from stages.semantics.codebook import load_codebook
from stages.semantics.feature_renderer import FeatureRenderer, GradBuffers
from stages.semantics.features import feature_grid, feature_views, load_features
from stages.semantics.field import save_field
from stages.semantics.field_model import FieldModel, field_losses
from stages.semantics.field_params import FieldParams, FieldRun
from stages.semantics.memory import cache_floor, memory_budget, working_set


def field_inputs(scene: Scene, features_path: Path, codebook_path: Path) -> dict[str, str]:
    return {
        "ply": scene.ply_digest(),
        "cameras": scene.cameras_digest(),
        **input_digest("features", features_path),
        **input_digest("codebook", codebook_path),
    }


def deterministic(fn: Callable[..., Path]) -> Callable[..., Path]:
    """Run with torch's deterministic kernels. The codebook's gradient through T[argmax e] is an
    indexed accumulation, which torch otherwise runs with unordered parallel adds on the CPU, so
    two runs with the same seed would differ in the last bits. MKL's choice of exp kernel is
    settled first (`settle_vml`): the first step's softmax was otherwise wrong in one thread's
    half, now and then."""

    @functools.wraps(fn)
    def run(*args: Any, **kwargs: Any) -> Path:
        settle_vml()
        before = torch.are_deterministic_algorithms_enabled()
        torch.use_deterministic_algorithms(True)
        try:
            return fn(*args, **kwargs)
        finally:
            torch.use_deterministic_algorithms(before)

    return run


@dataclass
class FitSetup:
    """What a fit reads and checks before any heavy work, shared by the single-process and
    the distributed fit."""

    cache_path: Path
    train: list[Camera]
    views: list[str]
    sizes: dict[str, tuple[int, int]]  # view -> feature grid (width, height)
    dim: int  # D, the features' dimension
    codebook: np.ndarray  # [N, D]
    inputs: dict[str, str]  # the inputs' digests, recorded in every artifact
    shapes: dict[str, tuple[int, ...]]  # the parameters' shapes (a checkpoint must match)


def check_renders(scene: Scene) -> None:
    g = scene.gaussians
    renderable = g.valid if g.valid.size else np.ones(g.count, bool)
    if not (g.opacities[renderable] >= ALPHA_MIN).any():
        raise GoiError(
            f"{scene.ply_path}: every Gaussian is transparent (opacity below {ALPHA_MIN:.4f}): "
            "nothing renders, so there is nothing to fit"
        )


def prepare_fit(
    scene: Scene,
    features_path: Path,
    codebook_path: Path,
    p: FieldParams,
    run: FieldRun,
    n_gaussians: int | None = None,
) -> FitSetup:
    """Every check on the options and inputs; nothing is built or written. With
    `n_gaussians` (a distributed fit, from the PLY's header) the Gaussians are not read: the
    caller checks them (`check_renders`) if it rasterises them."""
    check_params(p)
    check_params(run)
    check_writable(run.out, run.force, "--out")
    cache_path = run.cache_path
    # <out>.ckpt is written while fitting and removed at the end, so it is an output too
    check_output_name(run.checkpoint, "--out")
    outputs = {"--out": run.out, "--cache": cache_path, "--out (its checkpoint)": run.checkpoint}
    refuse_inputs(outputs, [scene.ply_path, *scene.camera_files, features_path, codebook_path])
    if cache_path.resolve() == run.out.resolve():
        raise GoiError(f"--cache: {cache_path} is also --out; give them different paths")
    if n_gaussians is None:  # the Gaussians are read here, and checked
        check_renders(scene)
        n_gaussians = scene.gaussians.count
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
    shapes = {
        "features": (n_gaussians, p.sem_dim),
        "decoder_weight": (dim if p.no_tfcc else codebook.shape[0], p.sem_dim),
        "decoder_bias": (dim if p.no_tfcc else codebook.shape[0],),
        "codebook": codebook.shape,
    }
    inputs = field_inputs(scene, features_path, codebook_path)
    return FitSetup(cache_path, train, views, sizes, dim, codebook, inputs, shapes)


def make_optimizer(model: FieldModel, p: FieldParams) -> torch.optim.Adam:
    return torch.optim.Adam(
        [
            {"params": [model.features], "lr": p.lr_features, "eps": 1e-15},
            {"params": model.decoder.parameters(), "lr": p.lr_decoder},
            {"params": [model.codebook], "lr": p.lr_codebook},
        ],
        # one pass over the [G, S] features and their two moments, not ten
        fused=not p.reference_losses,
    )


def draw_cells(
    rng: np.random.Generator, views: list[str], sizes: dict[str, tuple[int, int]], p: FieldParams
) -> list[tuple[str, np.ndarray]]:
    """One step's sample: the views drawn (in list order) and each one's cells [C] int64.
    Every rank of a distributed fit draws the same from the shared seed."""
    pick = rng.choice(len(views), min(p.views_per_step, len(views)), replace=False)
    drawn = []
    for vi in sorted(pick):
        v = views[vi]
        n_cells = sizes[v][0] * sizes[v][1]
        if 0 < p.cells_per_view < n_cells:
            cells = np.sort(rng.choice(n_cells, p.cells_per_view, replace=False))
        else:
            cells = np.arange(n_cells)
        drawn.append((v, cells))
    return drawn


def step_targets(
    drawn: list[tuple[str, np.ndarray]],
    targets: dict[str, np.ndarray],
    norms: dict[str, np.ndarray],
) -> torch.Tensor:
    """The drawn cells' target features [B, D], unit, as `load_features` would give them."""
    v_gt = torch.from_numpy(np.concatenate([targets[v][c] for v, c in drawn])).float()
    v_gt.div_(torch.from_numpy(np.concatenate([norms[v][c] for v, c in drawn]))[:, None])
    return v_gt


def take_step(
    model: FieldModel,
    opt: torch.optim.Optimizer,
    f_hat: torch.Tensor,  # [B, S] rendered features
    v_gt: torch.Tensor,  # [B, D] unit targets
    it: int,
    p: FieldParams,
) -> list[float]:
    """The losses, their gradients and one Adam step; the loss terms (LOSS_NAMES)."""
    loss, parts = field_losses(model, f_hat, v_gt, p.tau(it), p)
    if not np.isfinite(parts[0]):
        raise GoiError(
            f"fit-field diverged at iteration {it} (loss {parts[0]}): lower the learning rates"
        )
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    return parts


def loss_line(curve: list[list[float]]) -> Callable[[object], str]:
    def show(_: object) -> str:
        if not curve:
            return ""
        return "loss {:.3f} (ent {:.3f} max {:.3f} joint {:.3f} e2e {:.3f})".format(*curve[-1])

    return show


@dataclass
class Training:
    """A fit's state between steps: the model, its optimiser, the cells' draw and the losses."""

    model: FieldModel
    opt: torch.optim.Adam
    rng: np.random.Generator
    curve: list[list[float]]

    @classmethod
    def start(
        cls, n_rows: int, s: FitSetup, p: FieldParams, order: np.ndarray | None = None
    ) -> Training:
        """Fresh from the seed: the decoder's initial weights and the draws are the same on
        every run (and every rank of a distributed fit)."""
        torch.manual_seed(p.seed)
        model = FieldModel(n_rows, p.sem_dim, s.codebook, p.no_tfcc, order=order)
        return cls(model, make_optimizer(model, p), np.random.default_rng(p.seed), [])

    def run(
        self,
        first: int,
        s: FitSetup,
        p: FieldParams,
        targets: tuple[dict[str, np.ndarray], dict[str, np.ndarray]],
        render: Callable[[list[tuple[str, np.ndarray]]], torch.Tensor],
        after: Callable[[int], None],
        report: Report,
    ) -> tuple[int, float]:
        """Iterations first .. p.iterations: draw the cells, `render` the field at them [B, S],
        one Adam step, then `after(iterations done)`. Returns the steps taken and seconds."""
        steps = range(first, p.iterations)
        t_fit = time.perf_counter()
        show = loss_line(self.curve)
        for it in report.progress(steps, "fit-field", length=len(steps), show=show):
            drawn = draw_cells(self.rng, s.views, s.sizes, p)
            f_hat = render(drawn)
            v_gt = step_targets(drawn, *targets)
            self.curve.append(take_step(self.model, self.opt, f_hat, v_gt, it, p))
            after(it + 1)
        return len(steps), time.perf_counter() - t_fit


def feature_targets(
    features_path: Path, views: list[str]
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """The views' feature maps as the fit's targets [cells, D] float16 and their norms [cells]
    (the features are read, and checked, whole)."""
    fm = load_features(features_path, views, unit=False)
    targets = {v: m.reshape(-1, fm.dim) for v, m in fm.maps.items()}
    return targets, {v: unit_norms(m.astype(np.float32)) for v, m in targets.items()}


def streaming(
    path: Path, views: list[str], need: int, budget: int, p: FieldParams
) -> tuple[bool, int, int]:
    """Whether the blend cache at `path` must be streamed (it does not fit in `budget` beside
    the `need` of the rest), and what a step then needs (its largest views' weights and the
    rest); the caller refuses a step that does not fit either."""
    per_view = cache_nbytes(path, views)
    step_need = need + sum(sorted(per_view.values())[-p.views_per_step :])
    return need + sum(per_view.values()) > budget, step_need, sum(per_view.values())


@deterministic
def fit_field(
    scene: Scene,
    features_path: Path,
    codebook_path: Path,
    p: FieldParams,
    run: FieldRun,
    report: Report = SILENT,
) -> Path:
    if run.distributed:  # the CLI calls fit_distributed.fit_field_distributed for it
        raise GoiError("--distributed: a distributed fit runs fit_field_distributed")
    # Everything is checked before the blend cache is built (minutes on a big scene).
    s = prepare_fit(scene, features_path, codebook_path, p, run)
    # one run per output: a second run of the same --out (or --cache) is refused here, before
    # it reads, builds or removes anything of the first run's
    with output_lock(run.out, "--out"), output_lock(s.cache_path, "--cache"):
        return _fit(scene, features_path, p, run, s, report)


def _fit(
    scene: Scene, features_path: Path, p: FieldParams, run: FieldRun, s: FitSetup, report: Report
) -> Path:
    cache_path, train, views, sizes = s.cache_path, s.train, s.views, s.sizes
    g = scene.gaussians
    inputs = s.inputs
    if run.resume and run.checkpoint.is_file():
        check_checkpoint(run.checkpoint, inputs, p.config(), s.shapes)
    budget = memory_budget(run.max_memory_gib)
    need = working_set(g.count, scene, train, sizes, s.dim, s.codebook.shape[0], p)
    floor = cache_floor(cache_sizes(train, sizes), p.views_per_step)
    if need + floor > budget:
        raise GoiError(
            f"--max-memory-gib: the fit needs at least {size_text(need + floor)} (features, "
            f"Gaussians, optimiser state, one view's rasterisation, a step's share of the blend "
            f"cache), more than the {size_text(budget)} allowed; raise it, or use fewer views "
            "or a smaller feature grid"
        )
    reuse_cache = cache_target(cache_path, scene, train, p.top_k, sizes, run.force)

    targets = feature_targets(features_path, views)
    if not reuse_cache:
        build_cache_file(cache_path, scene, train, p.top_k, cache_sizes(train, sizes), report)
    stream, step_need, cache_bytes = streaming(cache_path, views, need, budget, p)
    if stream:
        if step_need > budget:
            raise GoiError(
                f"--max-memory-gib: even streaming the blend cache needs {size_text(step_need)} "
                f"(the largest {p.views_per_step} views' weights beside the rest), more than "
                f"the {size_text(budget)} allowed (the cache {cache_path} is built and kept "
                "for the next run)"
            )
        report.log(
            f"streaming the blend cache from {cache_path}: its {size_text(cache_bytes)} do not "
            f"fit in {size_text(budget)} beside the rest ({size_text(need)})"
        )
        order = None  # read (and checked) with the first view, then reused
        for v in report.progress(views, "check cache", length=len(views)):
            order = FeatureRenderer.from_file(cache_path, [v], order=order).order
    else:
        fr = FeatureRenderer.from_file(cache_path, views)
        order = fr.order
    buffers = GradBuffers()
    t = Training.start(g.count, s, p, order)
    start = 0
    if run.resume and run.checkpoint.is_file():
        start, t.curve = load_checkpoint(run.checkpoint, t.model, t.opt, t.rng, inputs, p.config())
        report.log(f"resuming {run.checkpoint} at iteration {start}")

    def render(drawn: list[tuple[str, np.ndarray]]) -> torch.Tensor:
        nonlocal fr
        if stream:  # same rows in the same order as in memory: the same field, bit for bit
            fr = FeatureRenderer.from_file(
                cache_path, [v for v, _ in drawn], order=order, check=False
            )
        rows = np.concatenate([fr.rows(v, cells) for v, cells in drawn])
        return fr.render(t.model.features, rows, in_columns=True, buffers=buffers)

    def after(done: int) -> None:
        if run.checkpoint_every and done % run.checkpoint_every == 0 and done < p.iterations:
            save_checkpoint(
                run.checkpoint, t.model, t.opt, t.rng, done, t.curve, inputs, p.config()
            )

    n_steps, seconds = t.run(start, s, p, targets, render, after, report)
    report.log(
        f"fitted {n_steps} iterations in {seconds:.1f} s ({seconds / max(n_steps, 1):.3f} s each)"
    )
    save_field(run.out, t.model.arrays(), np.asarray(t.curve), views, p.config(), inputs, run.force)
    refuse_if_input(run.checkpoint)
    run.checkpoint.unlink(missing_ok=True)
    return run.out

"""`goi fit-field --distributed`: one scene's fit split by Gaussians across torchrun's ranks.

Rendering through the blend cache is linear: a cell's feature is sum_g w[cell, g] f_g. Rank r
keeps only its Gaussians' features, their Adam moments and its columns of the cache (a shard,
`cache_shards`); every rank draws the same cells from the shared seed, renders its partial sum
[B, S], and one all_reduce gives every rank the full rendered features. The decoder and the
codebook see the same batch on every rank, so they stay the same everywhere without being
communicated, and each rank's gradient for its own Gaussians is the single-process one (up to
the order in which the partial sums are added). Checkpoints are per rank and resume together;
the leader (rank 0) gathers the features at the end and writes today's field artifact.
"""

from __future__ import annotations

import signal
import time
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist

from stages.core.arrays import unit_norms
from stages.core.errors import GoiError
from stages.core.files import check_output_name, refuse_if_input, refuse_inputs
from stages.core.report import SILENT, Report
from stages.scene.scene import Scene
from stages.semantics.blend_cache import cache_nbytes, cache_sizes
from stages.semantics.cache_shards import SCHEMA as SHARD_CACHE
from stages.semantics.cache_shards import build_shards, plan_shard, shard_order
from stages.semantics.checkpoint import SHARD_SCHEMA, check_checkpoint, load_checkpoint
from stages.semantics.checkpoint import save_checkpoint as save_ckpt
from stages.semantics.distributed import Ranks, SumOverRanks, collective, start, stop, torchrun_env
from stages.semantics.feature_renderer import FeatureRenderer, GradBuffers
from stages.semantics.features import load_features
from stages.semantics.field import save_field
from stages.semantics.field_model import FieldModel, FieldParams
from stages.semantics.fit_field import (
    FieldRun,
    deterministic,
    draw_cells,
    loss_line,
    make_optimizer,
    prepare_fit,
    step_targets,
    take_step,
)
from stages.semantics.memory import GIB, memory_budget, rank_working_set


def rank_checkpoints(out: Path, rank: int, world: int) -> tuple[Path, Path]:
    """This rank's latest checkpoint and the one before it. Keeping two means that a rank
    killed while writing leaves an iteration every rank still has."""
    latest = out.with_name(f"{out.name}.ckpt-{rank}-of-{world}")
    return latest, latest.with_name(latest.name + ".prev")


@deterministic
def fit_field_distributed(
    scene: Scene,
    features_path: Path,
    codebook_path: Path,
    p: FieldParams,
    run: FieldRun,
    report: Report = SILENT,
) -> Path:
    torchrun_env()  # refused before anything else when torchrun did not start this process
    before = signal.signal(signal.SIGTERM, _stopped)
    try:
        ranks = start(run.dist_timeout_s, run.threads)
        try:
            return _fit(scene, features_path, codebook_path, p, run, ranks, report)
        finally:
            stop()
    finally:
        signal.signal(signal.SIGTERM, before)


def _stopped(signum: int, frame: object) -> None:
    """torchrun stops the other ranks with SIGTERM when one fails (a scheduler does when a
    job ends): unwind like an error, so that the files being written are removed."""
    raise GoiError("--distributed: stopped by SIGTERM (another rank failed, or the job ended)")


def _fit(
    scene: Scene,
    features_path: Path,
    codebook_path: Path,
    p: FieldParams,
    run: FieldRun,
    ranks: Ranks,
    report: Report,
) -> Path:
    report = report if ranks.leader else SILENT
    s = prepare_fit(scene, features_path, codebook_path, p, run)
    n = scene.gaussians.count
    want = cache_sizes(s.train, s.sizes)
    plan, reuse = plan_shard(s.cache_path, scene, p.top_k, want, ranks, run.force)
    n_cols = plan.hi - plan.lo
    latest, prev = rank_checkpoints(run.out, ranks.rank, ranks.world)
    for c in (latest, prev):
        check_output_name(c, "--out")
    inputs_files = [scene.ply_path, *scene.camera_files, features_path, codebook_path]
    outputs = {"--cache (this rank's shard)": plan.path, "--out (this rank's checkpoint)": latest}
    refuse_inputs(outputs, inputs_files)
    attrs = {"rank": ranks.rank, "world_size": ranks.world, "column_lo": plan.lo}
    attrs["column_hi"] = plan.hi
    shapes = {**s.shapes, "features": (n_cols, p.sem_dim)}
    config = p.config()
    found = {}
    if run.resume:
        for c in (latest, prev):
            if c.is_file():
                found[check_checkpoint(c, s.inputs, config, shapes, SHARD_SCHEMA, attrs)] = c

    budget = memory_budget(run.max_memory_gib)
    entries = s.codebook.shape[0]
    need = rank_working_set(n, n_cols, scene, s.train, s.sizes, s.dim, entries, p, ranks.leader)
    if need > budget:
        raise GoiError(
            f"--max-memory-gib: rank {ranks.rank} needs at least {need / GIB:.2f} GiB beside "
            f"its blend cache shard (features, the PLY while the shards are built, its "
            f"{n_cols} Gaussians' optimiser state), more than the {budget / GIB:.2f} GiB "
            "allowed; raise it, or start more ranks"
        )
    if not ranks.all_agree(reuse, "the check of the blend cache shards"):
        build_shards(plan, scene, s.train, p.top_k, want, ranks, s.cache_path, report)
    per_view = cache_nbytes(plan.path, s.views)
    stream = need + sum(per_view.values()) > budget
    if stream:
        step_need = need + sum(sorted(per_view.values())[-p.views_per_step :])
        if step_need > budget:
            raise GoiError(
                f"--max-memory-gib: rank {ranks.rank} needs {step_need / GIB:.2f} GiB even "
                f"streaming its blend cache shard, more than the {budget / GIB:.2f} GiB "
                "allowed; raise it, or start more ranks"
            )
        report.log(f"streaming the blend cache shards ({plan.path} on rank {ranks.rank})")
    order = shard_order(plan)  # [n_cols] PLY ids of this rank's Gaussians
    # The PLY was needed for the checks and to rasterise the shards; the fit is not.
    scene.__dict__.pop("gaussians", None)

    fm = load_features(features_path, s.views, unit=False)
    targets = {v: m.reshape(-1, fm.dim) for v, m in fm.maps.items()}  # [cells, D] float16
    norms = {v: unit_norms(m.astype(np.float32)) for v, m in targets.items()}  # [cells]
    del fm

    def shard(names: list[str], check: bool) -> FeatureRenderer:
        return FeatureRenderer.from_file(plan.path, names, order, check, SHARD_CACHE)

    if stream:
        for v in report.progress(s.views, "check cache", length=len(s.views)):
            shard([v], True)
    else:
        fr = shard(s.views, True)

    torch.manual_seed(p.seed)  # the decoder's initial weights: the same on every rank
    model = FieldModel(n_cols, p.sem_dim, s.codebook, p.no_tfcc)  # rows in column order
    opt = make_optimizer(model, p)
    rng = np.random.default_rng(p.seed)
    curve: list[list[float]] = []
    first = _resume_point(found, ranks)
    if first:
        first, curve = load_checkpoint(
            found[first], model, opt, rng, s.inputs, config, SHARD_SCHEMA, attrs
        )
        report.log(f"resuming the {ranks.world} ranks' checkpoints at iteration {first}")
    elif not run.resume:
        for c in (latest, prev):  # another run's: never mixed with this one's
            refuse_if_input(c)
            c.unlink(missing_ok=True)

    def checkpoint(done: int) -> None:
        if latest.is_file():
            latest.replace(prev)
        save_ckpt(latest, model, opt, rng, done, curve, s.inputs, config, SHARD_SCHEMA, attrs)

    buffers = GradBuffers()
    steps = range(first, p.iterations)
    t_fit = time.perf_counter()
    sent = 0
    for it in report.progress(steps, "fit-field", length=len(steps), show=loss_line(curve)):
        drawn = draw_cells(rng, s.views, s.sizes, p)
        if stream:
            fr = shard([v for v, _ in drawn], False)
        rows = np.concatenate([fr.rows(v, cells) for v, cells in drawn])
        partial = fr.render(model.features, rows, in_columns=True, buffers=buffers)  # [B, S]
        f_hat = SumOverRanks.apply(partial, ranks)  # [B, S], the same on every rank
        sent = partial.numel() * partial.element_size()
        curve.append(take_step(model, opt, f_hat, step_targets(drawn, targets, norms), it, p))
        done = it + 1
        if run.checkpoint_every and (done % run.checkpoint_every == 0 or done == p.iterations):
            checkpoint(done)  # the last one too: a leader lost while writing the field resumes
    report.log(
        f"fitted {len(steps)} iterations on {ranks.world} ranks in "
        f"{time.perf_counter() - t_fit:.1f} s; all_reduce {sent / 1024:.0f} KiB per step"
    )
    features = _gather_features(model.features.detach(), order, n, ranks)
    if ranks.leader:
        assert features is not None
        arrays = {k: v for k, v in model.arrays().items() if k != "features"}
        arrays["features"] = features
        save_field(run.out, arrays, np.asarray(curve), s.views, config, s.inputs, run.force)
    ranks.barrier("the field's write")
    for c in (latest, prev):
        refuse_if_input(c)
        c.unlink(missing_ok=True)
    return run.out


def _resume_point(found: dict[int, Path], ranks: Ranks) -> int:
    """The latest iteration every rank has a checkpoint of (0: none)."""
    everyone = ranks.gather_objects(sorted(found), "the checkpoints' iterations")
    common = set(everyone[0]).intersection(*everyone[1:])
    return max(common, default=0)


def _gather_features(
    features: torch.Tensor,  # [n_cols, S] this rank's, in column order
    order: np.ndarray,  # [n_cols] their PLY ids
    n_gaussians: int,
    ranks: Ranks,
) -> np.ndarray | None:
    """Every rank's features on the leader, in PLY order [G, S]; None on the other ranks."""
    width = -(-n_gaussians // ranks.world)  # the largest shard (column_range)
    rows = torch.zeros(width, features.shape[1] + 1, dtype=torch.float64)
    rows[: len(order), 0] = torch.from_numpy(order.astype(np.float64))
    rows[: len(order), 1:] = features.double()  # float32 and int32 ids: exact in float64
    sizes = torch.tensor([len(order)])
    parts = [torch.zeros_like(rows) for _ in range(ranks.world)] if ranks.leader else None
    counts = [torch.zeros_like(sizes) for _ in range(ranks.world)] if ranks.leader else None
    with collective("the gather of the features", ranks.timeout_s):
        dist.gather(sizes, counts, dst=0)
        dist.gather(rows, parts, dst=0)
    if parts is None or counts is None:
        return None
    out = np.zeros((n_gaussians, features.shape[1]), np.float32)
    for part, count in zip(parts, counts, strict=True):
        got = part[: int(count)].numpy()
        out[got[:, 0].astype(np.int64)] = got[:, 1:].astype(np.float32)
    return out

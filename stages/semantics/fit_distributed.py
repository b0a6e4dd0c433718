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

import contextlib
import resource
import signal
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist

from stages.core.errors import GoiError
from stages.core.files import check_output_name, output_lock, refuse_if_input, refuse_inputs
from stages.core.report import SILENT, Report
from stages.scene.gaussians import ply_count
from stages.scene.scene import Scene
from stages.semantics.blend_cache import cache_sizes
from stages.semantics.cache_shards import SCHEMA as SHARD_CACHE
from stages.semantics.cache_shards import build_shards, column_range, plan_shard, shard_order
from stages.semantics.checkpoint import SHARD_SCHEMA, check_checkpoint, load_checkpoint
from stages.semantics.checkpoint import save_checkpoint as save_ckpt
from stages.semantics.distributed import Ranks, SumOverRanks, collective, start, stop, torchrun_env
from stages.semantics.feature_renderer import FeatureRenderer, GradBuffers
from stages.semantics.field import save_field
from stages.semantics.field_params import FieldParams, FieldRun
from stages.semantics.fit_field import (
    Training,
    check_renders,
    deterministic,
    feature_targets,
    prepare_fit,
    streaming,
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
            with _leader_locks(run, ranks):
                return _fit(scene, features_path, codebook_path, p, run, ranks, report)
        finally:
            stop()
    finally:
        signal.signal(signal.SIGTERM, before)


@contextlib.contextmanager
def _leader_locks(run: FieldRun, ranks: Ranks) -> Iterator[None]:
    """One run per output, as in the single-process fit: the leader holds the locks on --out
    and on the blend cache (whose shards and parts files sit beside it) for the whole run, and
    every rank learns whether it got them, so that all ranks of a second run of the same --out
    refuse with the leader's line before any of them reads, builds or removes anything."""
    with contextlib.ExitStack() as held:
        refused = ""
        if ranks.leader:
            try:
                held.enter_context(output_lock(run.out, "--out"))
                held.enter_context(output_lock(run.cache_path, "--cache"))
            except GoiError as e:
                refused = str(e)
        said = ranks.gather_objects(refused, "the output lock")
        if any(said):
            raise GoiError(next(m for m in said if m))
        yield


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
    n = ply_count(scene.ply_path)  # the Gaussians themselves are read only to build shards
    s = prepare_fit(scene, features_path, codebook_path, p, run, n_gaussians=n)
    want = cache_sizes(s.train, s.sizes)
    plan, reuse = plan_shard(s.cache_path, scene, n, p.top_k, want, ranks, run.force)
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

    building = not ranks.all_agree(reuse, "the check of the blend cache shards")
    if building:
        check_renders(scene)
    budget = memory_budget(run.max_memory_gib)
    need = rank_working_set(
        n, n_cols, scene, s.train, s.sizes, s.dim, s.codebook.shape[0], p, ranks.leader,
        building, ranks.world,
    )  # fmt: skip
    if need > budget:
        raise GoiError(
            f"--max-memory-gib: rank {ranks.rank} needs at least {need / GIB:.2f} GiB beside "
            f"its blend cache shard (features, {'the PLY while shards are built, ' * building}"
            f"its {n_cols} Gaussians' optimiser state), more than the {budget / GIB:.2f} GiB "
            "allowed; raise it, or start more ranks"
        )
    if building:
        build_shards(plan, scene, s.train, p.top_k, want, ranks, s.cache_path, report)
        # The PLY was needed to rasterise the shards; the fit is not.
        scene.__dict__.pop("gaussians", None)
    stream, step_need, _ = streaming(plan.path, s.views, need, budget, p)
    if stream:
        if step_need > budget:
            raise GoiError(
                f"--max-memory-gib: rank {ranks.rank} needs {step_need / GIB:.2f} GiB even "
                f"streaming its blend cache shard, more than the {budget / GIB:.2f} GiB "
                "allowed; raise it, or start more ranks"
            )
        report.log(f"streaming the blend cache shards ({plan.path} on rank {ranks.rank})")
    order = shard_order(plan)  # [n_cols] PLY ids of this rank's Gaussians

    targets = feature_targets(features_path, s.views)

    def shard(names: list[str], check: bool) -> FeatureRenderer:
        return FeatureRenderer.from_file(plan.path, names, order, check, SHARD_CACHE)

    if stream:
        for v in report.progress(s.views, "check cache", length=len(s.views)):
            shard([v], True)
    else:
        fr = shard(s.views, True)

    t = Training.start(n_cols, s, p)  # rows in column order
    first = _resume_point(found, ranks)
    if first:
        first, t.curve = load_checkpoint(
            found[first], t.model, t.opt, t.rng, s.inputs, config, SHARD_SCHEMA, attrs
        )
        report.log(f"resuming the {ranks.world} ranks' checkpoints at iteration {first}")
    elif run.resume:
        report.log("--resume: no iteration every rank has a checkpoint of; starting at 0")
    else:
        for c in (latest, prev):  # another run's: never mixed with this one's
            refuse_if_input(c)
            c.unlink(missing_ok=True)

    buffers = GradBuffers()
    sent = 0

    def render(drawn: list[tuple[str, np.ndarray]]) -> torch.Tensor:
        nonlocal fr, sent
        if stream:
            fr = shard([v for v, _ in drawn], False)
        rows = np.concatenate([fr.rows(v, cells) for v, cells in drawn])
        partial = fr.render(t.model.features, rows, in_columns=True, buffers=buffers)  # [B, S]
        sent = partial.numel() * partial.element_size()
        return SumOverRanks.apply(partial, ranks)  # [B, S], the same on every rank

    def after(done: int) -> None:
        # the last one too: a leader lost while writing the field resumes
        if run.checkpoint_every and (done % run.checkpoint_every == 0 or done == p.iterations):
            if latest.is_file():
                latest.replace(prev)
            save_ckpt(
                latest, t.model, t.opt, t.rng, done, t.curve, s.inputs, config, SHARD_SCHEMA, attrs
            )

    n_steps, seconds = t.run(first, s, p, targets, render, after, report)
    report.log(
        f"fitted {n_steps} iterations on {ranks.world} ranks ({torch.get_num_threads()} "
        f"threads on rank 0) in {seconds:.1f} s; all_reduce of {sent} bytes per step"
    )
    features = _gather_features(t.model.features.detach(), order, n, ranks)
    if features is not None:
        arrays = {k: v for k, v in t.model.arrays().items() if k != "features"}
        arrays["features"] = features
        save_field(run.out, arrays, np.asarray(t.curve), s.views, config, s.inputs, run.force)
        del features, arrays
    peaks = ranks.gather_objects(_peak_rss(), "the field's write")
    report.log(
        "peak resident memory per rank: " + ", ".join(f"{x / GIB:.3f}" for x in peaks) + " GiB"
    )
    for c in (latest, prev):
        refuse_if_input(c)
        c.unlink(missing_ok=True)
    return run.out


def _peak_rss() -> int:
    """This process's peak resident memory so far (bytes; Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


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
    """Every rank's features on the leader, in PLY order [G, S] (None on the other ranks).
    The leader receives one rank's share at a time and puts it in place, so that it holds the
    field's features once and a single share beside them."""
    ids = torch.from_numpy(order.astype(np.int32))
    with collective("sending the features to rank 0", ranks.timeout_s):
        if not ranks.leader:
            dist.send(ids, dst=0)
            dist.send(features.contiguous(), dst=0)
            return None
        out = np.zeros((n_gaussians, features.shape[1]), np.float32)
        out[order] = features.numpy()
        for r in range(1, ranks.world):
            lo, hi = column_range(n_gaussians, ranks.world, r)
            got_ids = torch.empty(hi - lo, dtype=torch.int32)
            got = torch.empty(hi - lo, features.shape[1], dtype=features.dtype)
            dist.recv(got_ids, src=r)
            dist.recv(got, src=r)
            out[got_ids.numpy()] = got.numpy()
    return out

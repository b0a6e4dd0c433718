"""The distributed suite: one scene's fit-field on 1 and 2 torchrun ranks against 1 process.

Every fit runs as its own process tree, as a user runs it. A distributed fit's first run
builds the blend-cache shards (every rank then holds the whole PLY, which rasterising a view
needs); the figures named `..._1rank` / `..._2ranks` come from a second run that reuses the
shards, where a rank holds only its share of the Gaussians. Each rank reports its own peak
resident memory (getrusage); the single process's comes from the kernel's rusage of it. The
Gaussian-dependent part is the peak minus the same run's on a scene of the same views with
few Gaussians. On a 2-core machine this measures memory and agreement, not speed-up.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from benchmarks.scale import ROOT, Size, make_scene

GIB = 2**30
SMALL = 10_000  # Gaussians of the baseline scene (same views, same features grid)


@dataclass(frozen=True)
class DistSize:
    gaussians: int = 1_000_000
    views: int = 8
    width: int = 320
    height: int = 240
    iterations: int = 100

    @classmethod
    def from_env(cls) -> DistSize:
        """GOI_DISTRIBUTED="gaussians,views,width,height,iterations" runs at another size."""
        text = os.environ.get("GOI_DISTRIBUTED")
        return cls(*(int(x) for x in text.split(","))) if text else cls()


def _run(cmd: list[str], log: Path) -> tuple[int, float, float, str]:
    """(exit status, wall s, peak RSS GiB of the process tree's largest process, its output)."""
    t = time.perf_counter()
    with open(log, "w") as out:
        proc = subprocess.Popen(cmd, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(proc.pid, 0)
    return (
        os.waitstatus_to_exitcode(status),
        time.perf_counter() - t,
        usage.ru_maxrss / 2**20,
        log.read_text(errors="replace"),
    )


def _goi(args: list[str], log: Path) -> tuple[int, float, float, str]:
    return _run([sys.executable, "-m", "goi_cli", *args], log)


def _torchrun(n: int, args: list[str], log: Path) -> tuple[int, float, float, str]:
    torchrun = str(Path(sys.executable).with_name("torchrun"))
    cmd = [torchrun, "--standalone", "--nproc-per-node", str(n), "-m", "goi_cli"]
    return _run([*cmd, "fit-field", "--distributed", *args], log)


def _rank_peaks(text: str) -> list[float]:
    for line in text.splitlines()[::-1]:
        if "peak resident memory per rank:" in line:
            nums = line.split("per rank:")[1].replace("GiB", "").split(",")
            return [float(x) for x in nums]
    raise SystemExit(f"no per-rank peak memory in the run's output:\n{text[-2000:]}")


def _inputs(root: Path, size: DistSize, n: int, log: Path) -> list[str]:
    """A scene of `n` Gaussians, its features and codebook; fit-field's input options."""
    make_scene(root, Size(n, size.views, size.width, size.height, size.iterations))
    sc = ["--scene", str(root)]
    for args in (
        ["extract", *sc, "--from", str(root / "features"), "--out", str(root / "f.h5")],
        ["init-codebook", "--features", str(root / "f.h5"), "--out", str(root / "c.h5")],
    ):
        rc, _, _, text = _goi(args, log)
        if rc != 0:
            raise SystemExit(f"goi {args[0]} failed:\n{text[-2000:]}")
    return [*sc, "--features", str(root / "f.h5"), "--codebook", str(root / "c.h5"),
            "--iterations", str(size.iterations), "--checkpoint-every", "0"]  # fmt: skip


def _distributed_peak(
    n: int, fit: list[str], root: Path, name: str, log: Path
) -> tuple[float, float, str]:
    """The largest rank's peak (GiB) of a fit on `n` ranks that reuses its shards, the same
    of the first run that built them, and the second run's output."""
    peaks, text = [], ""
    for run in ("build", "fit"):
        out = ["--out", str(root / f"{name}_{run}.h5"), "--cache", str(root / f"{name}.h5")]
        rc, _, _, text = _torchrun(n, [*fit, *out], log)
        if rc != 0:
            raise SystemExit(f"{n}-rank fit-field failed:\n{text[-3000:]}")
        peaks.append(max(_rank_peaks(text)))
    return peaks[1], peaks[0], text


def suite_distributed(repeat: int, tmp: Path, size: DistSize | None = None) -> dict[str, float]:
    from stages.scene.scene import load_scene
    from stages.semantics.codebook import load_codebook
    from stages.semantics.features import feature_grid, feature_views
    from stages.semantics.field import load_field
    from stages.semantics.field_params import FieldParams
    from stages.semantics.memory import working_set

    size = size or DistSize.from_env()
    out: dict[str, float] = {
        "distributed_gaussians": size.gaussians,
        "distributed_views": size.views,
        "distributed_iterations": size.iterations,
    }
    log = tmp / "distributed.log"
    big, small = tmp / "dist_big", tmp / "dist_small"
    fit = _inputs(big, size, size.gaussians, log)
    fit_small = _inputs(small, size, SMALL, log)

    rc, wall, rss, text = _goi(
        ["fit-field", *fit, "--out", str(big / "single.h5"), "--cache", str(big / "c1.h5")], log
    )
    if rc != 0:
        raise SystemExit(f"single-process fit-field failed:\n{text[-3000:]}")
    out["distributed_rss_gib_single_process"] = rss

    for n, key in ((1, "1rank"), (2, "2ranks")):
        peak, building, text = _distributed_peak(n, fit, big, f"r{n}", log)
        out[f"distributed_rss_gib_{key}"] = peak
        out[f"distributed_rss_gib_{key}_building"] = building
        out[f"distributed_rss_gib_{key}_at_{SMALL}"] = _distributed_peak(
            n, fit_small, small, f"r{n}", log
        )[0]
    sent = [ln for ln in text.splitlines() if "bytes per step" in ln]
    out["distributed_allreduce_bytes_per_step"] = float(
        sent[-1].split("all_reduce of")[1].split()[0]
    )
    part1 = out["distributed_rss_gib_1rank"] - out[f"distributed_rss_gib_1rank_at_{SMALL}"]
    part2 = out["distributed_rss_gib_2ranks"] - out[f"distributed_rss_gib_2ranks_at_{SMALL}"]
    out["distributed_gaussian_part_gib_1rank"] = part1
    out["distributed_gaussian_part_gib_2ranks"] = part2
    out["distributed_gaussian_part_ratio_2ranks_to_1"] = part2 / part1 if part1 > 0 else 0.0

    p = FieldParams(iterations=size.iterations)
    # The baseline of the agreement: the single process's own paper-formulation path, which
    # adds the same sums in another order too (docs/performance.md).
    rc, _, _, text_ref = _goi(["fit-field", *fit, "--out", str(big / "reference.h5"), "--cache",
                               str(big / "c1.h5"), "--reference-losses"], log)  # fmt: skip
    if rc != 0:
        raise SystemExit(f"fit-field --reference-losses failed:\n{text_ref[-3000:]}")
    a = load_field(big / "single.h5")
    for key, other in (("", "r2_fit.h5"), ("_1rank", "r1_fit.h5"),
                       ("_reference_losses", "reference.h5")):  # fmt: skip
        b = load_field(big / other)
        out[f"distributed_field_max_abs_diff{key}"] = float(np.abs(a.features - b.features).max())
        out[f"distributed_field_max_abs_diff_codebook{key}"] = float(
            np.abs(a.codebook - b.codebook).max()
        )
        same = a.decode_index(a.features) == b.decode_index(b.features)
        out[f"distributed_same_decoded_fraction{key}"] = float(same.mean())

    # A budget that refuses one process but holds two ranks: between the single process's
    # own estimate and the 2-rank run's measured peak.
    scene = load_scene(big)
    train = scene.views("train")
    sizes = feature_grid(big / "f.h5", [c.name for c in train])
    dim, _ = feature_views(big / "f.h5")
    entries = load_codebook(big / "c.h5").shape[0]
    need = working_set(scene.gaussians.count, scene, train, sizes, dim, entries, p) / GIB
    out["distributed_single_process_estimate_gib"] = need
    peak2 = out["distributed_rss_gib_2ranks"]
    out["distributed_budget_gib"] = budget = round((need + peak2) / 2, 2)
    refused = _goi(["fit-field", *fit, "--out", str(big / "x.h5"), "--cache",
                    str(big / "c1.h5"), "--max-memory-gib", str(budget)], log)  # fmt: skip
    out["distributed_budget_single_process_refused"] = float(
        refused[0] == 2 and "--max-memory-gib" in refused[3]
    )
    rc, _, _, text = _torchrun(
        2, [*fit, "--out", str(big / "budget.h5"), "--cache", str(big / "r2.h5"),
            "--max-memory-gib", str(budget)], log,
    )  # fmt: skip
    ok = rc == 0 and (big / "budget.h5").is_file()
    out["distributed_budget_2ranks_fitted"] = float(ok)
    out["distributed_budget_2ranks_peak_gib"] = max(_rank_peaks(text)) if ok else -1.0
    return out

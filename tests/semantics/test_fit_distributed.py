"""fit-field --distributed: the Gaussians split across torchrun's ranks.

On this 2-core machine the tests show correctness, placement and resume, not speed-up: two
ranks give the single-process field within float rounding (the partial sums are added in
another order), a rank killed mid-run stops the run with nothing half-written and the rerun
resumes, and bad setups are refused with one line.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from goi_cli.main import main
from stages.core.errors import GoiError
from stages.semantics.blend_cache import ViewWeights
from stages.semantics.cache_shards import column_range, split_columns
from stages.semantics.feature_renderer import FeatureRenderer
from tests.helpers import semantic_scene

TORCHRUN = str(Path(sys.executable).with_name("torchrun"))
#: The agreement asked of 2 ranks against 1 process after ITERATIONS steps: the rendered sums
#: differ in their last bits (two partial sums instead of one), and the fit carries that on.
TOLERANCE = 1e-5
ITERATIONS = 150


def test_the_column_shards_sum_to_the_whole_view():
    rng = np.random.default_rng(0)
    n_rows, n_cols = 50, 37
    dense = rng.random((n_rows, n_cols)) * (rng.random((n_rows, n_cols)) < 0.3)
    indptr = np.concatenate([[0], np.cumsum((dense > 0).sum(1))]).astype(np.int64)
    rows, cols = np.nonzero(dense)
    vw = ViewWeights(
        5, 10, indptr, cols.astype(np.int32), dense[rows, cols].astype(np.float32), 1, 0
    )
    world = 3
    bounds = np.array([column_range(n_cols, world, r)[0] for r in range(world)] + [n_cols])
    f = torch.from_numpy(rng.normal(size=(n_cols, 4)).astype(np.float32))
    order = np.arange(n_cols, dtype=np.int32)
    whole = FeatureRenderer(order, {"v": (5, 10)}, vw.indptr, vw.indices, vw.weights)
    want = whole.render(f, np.arange(n_rows), in_columns=True)
    total = torch.zeros_like(want)
    for s, piece in enumerate(split_columns(vw, bounds)):
        lo, hi = bounds[s], bounds[s + 1]
        assert piece.indices.min(initial=0) >= 0 and piece.indices.max(initial=-1) < hi - lo
        fr = FeatureRenderer(
            order[lo:hi], {"v": (5, 10)}, piece.indptr, piece.indices, piece.weights
        )
        total += fr.render(f[lo:hi], np.arange(n_rows), in_columns=True)
    torch.testing.assert_close(total, want, rtol=0, atol=1e-6)


def test_distributed_without_torchrun_is_refused(tmp_path, monkeypatch, capsys):
    for k in ("RANK", "WORLD_SIZE", "LOCAL_WORLD_SIZE", "MASTER_ADDR"):
        monkeypatch.delenv(k, raising=False)
    f = tmp_path / "x.h5"
    f.write_bytes(b"")
    args = ["fit-field", "--distributed", "--scene", str(tmp_path), "--features", str(f)]
    assert main([*args, "--codebook", str(f), "--out", str(tmp_path / "o.h5")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("goi: error: --distributed: not started by torchrun") and "\n" not in err
    assert not (tmp_path / "o.h5").exists()


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """One small scene, its single-process field and its field from 2 ranks."""
    from stages.scene.scene import load_scene
    from stages.semantics.codebook import CodebookParams, CodebookRun, init_codebook
    from stages.semantics.extract import ExtractParams, ExtractRun, import_features
    from stages.semantics.field_params import FieldParams, FieldRun
    from stages.semantics.fit_field import fit_field

    root = tmp_path_factory.mktemp("dist")
    s = semantic_scene(root, n=3000, n_views=6, size=(48, 36))
    scene = load_scene(s["scene"])
    feats = import_features(scene, s["features"], ExtractParams(), ExtractRun(root / "f.h5"))
    cb = init_codebook(feats, CodebookParams(entries=8), CodebookRun(root / "c.h5"))
    p = FieldParams(iterations=ITERATIONS, cells_per_view=64)
    fit_field(scene, feats, cb, p, FieldRun(root / "single.h5"))
    args = [
        "fit-field",
        "--distributed",
        "--scene",
        str(s["scene"]),
        "--features",
        str(feats),
        "--codebook",
        str(cb),
        "--iterations",
        str(ITERATIONS),
        "--cells-per-view",
        "64",
        "--dist-timeout-s",
        "60",
    ]
    r = torchrun(2, [*args, "--out", str(root / "dist.h5")], root)
    assert r.returncode == 0, r.stderr[-2000:]
    return root, args, r


def torchrun(n: int, args: list[str], cwd: Path, script: str | None = None):  # noqa: ANN201
    cmd = [TORCHRUN, "--standalone", "--nproc-per-node", str(n)]
    cmd += [script] if script else ["-m", "goi"]
    return subprocess.run([*cmd, *args], cwd=cwd, capture_output=True, text=True, timeout=300)


def goi_lines(text: str) -> list[str]:
    return [ln for ln in text.splitlines() if ln.startswith("goi: ")]


@pytest.mark.slow
def test_two_ranks_give_the_single_process_field(fitted):
    from stages.semantics.field import load_field

    root, _, run = fitted
    err = run.stderr
    assert run.stdout == f"field: {root / 'dist.h5'}\n"  # once, not once per rank
    a, b = load_field(root / "single.h5"), load_field(root / "dist.h5")
    for name in ("features", "decoder_weight", "decoder_bias", "codebook"):
        diff = np.abs(getattr(a, name) - getattr(b, name)).max()
        assert diff <= TOLERANCE, (name, diff)
    same = a.decode_index(a.features) == b.decode_index(b.features)
    assert same.mean() >= 0.999
    assert a.seen.mean() > 0.5  # most Gaussians were fitted, not left at zero
    # each rank rendered from its own shard: half the columns each
    shards = sorted(root.glob("blend_cache.shard-*-of-2.h5"))
    assert [p.name for p in shards] == [
        "blend_cache.shard-0-of-2.h5",
        "blend_cache.shard-1-of-2.h5",
    ]
    assert not list(root.glob("dist.h5.ckpt*")) and not list(root.glob(".goi-*"))
    # two ranks on this machine share its cores: no rank runs more threads than its share
    share = max(1, len(os.sched_getaffinity(0)) // 2)
    assert f"ranks ({share} threads on rank 0)" in err


def _children(pid: int) -> list[int]:
    out = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        text = (task / "children").read_text().split()
        out += [int(c) for c in text]
    return out


def _rank_of(pid: int) -> int | None:
    try:
        env = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
    except OSError:
        return None
    for kv in env:
        if kv.startswith(b"RANK="):
            return int(kv[5:])
    return None


@pytest.mark.slow
def test_a_killed_rank_stops_the_run_and_the_rerun_resumes(fitted):
    from stages.semantics.field import load_field

    root, args, _ = fitted
    out = root / "killed.h5"
    cmd = [TORCHRUN, "--standalone", "--nproc-per-node", "2", "-m", "goi", *args]
    cmd += ["--out", str(out), "--checkpoint-every", "10"]
    proc = subprocess.Popen(cmd, cwd=root, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    ckpt = root / "killed.h5.ckpt-1-of-2"
    deadline = time.monotonic() + 120
    while not ckpt.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.005)
    victim = next((c for c in _children(proc.pid) if _rank_of(c) == 1), None)
    assert victim is not None, "rank 1 was not found among torchrun's children"
    os.kill(victim, signal.SIGKILL)  # the process this test started, by its id
    _, err = proc.communicate(timeout=120)
    assert proc.returncode != 0
    assert not out.exists()  # nothing half-written under the field's name
    left = sorted(p.name for p in root.glob("killed.h5.ckpt-*"))
    assert "killed.h5.ckpt-1-of-2" in left or "killed.h5.ckpt-1-of-2.prev" in left, left
    r = torchrun(2, [*args, "--out", str(out), "--checkpoint-every", "10", "--resume"], root)
    assert r.returncode == 0, r.stderr[-2000:]
    assert any("resuming the 2 ranks' checkpoints at iteration" in ln for ln in goi_lines(r.stderr))
    # the resumed run is the uninterrupted 2-rank run, bit for bit
    a, b = load_field(root / "dist.h5"), load_field(out)
    np.testing.assert_array_equal(a.features, b.features)
    np.testing.assert_array_equal(a.codebook, b.codebook)
    assert not list(root.glob("killed.h5.ckpt*"))


def test_a_world_size_other_than_the_shards_is_refused(tmp_path):
    """Shards built for 2 ranks, a run of 3: refused, naming the files and what to do (the
    check runs before any collective, so no process group is needed here)."""
    from stages.scene.formats.inria import write_inria
    from stages.scene.scene import load_scene
    from stages.semantics.cache_shards import plan_shard, shard_path
    from stages.semantics.distributed import Ranks
    from stages.semantics.field_params import FieldParams
    from tests.helpers import front_camera, random_vertex, write_ply

    write_ply(tmp_path / "point_cloud.ply", random_vertex(60))
    write_inria(tmp_path / "cameras.json", [front_camera(20, 16)])
    scene = load_scene(tmp_path)
    cache = tmp_path / "blend_cache.h5"
    for r in range(2):
        shard_path(cache, r, 2).write_bytes(b"")
    want = {"c0": (20, 16)}
    with pytest.raises(GoiError, match=r"were built for 2 ranks, this run has 3; start torchrun"):
        plan_shard(cache, scene, 60, FieldParams().top_k, want, Ranks(0, 3, 3, 1.0), force=False)
    plan, reuse = plan_shard(cache, scene, 60, 0, want, Ranks(2, 3, 3, 1.0), force=True)
    assert plan.path.name == "blend_cache.shard-2-of-3.h5" and not reuse
    assert (plan.lo, plan.hi) == (40, 60)
    # a file of the same name that is not this rank's shard: refused without --force
    with pytest.raises(GoiError, match=r"is not this rank's shard"):
        plan_shard(cache, scene, 60, 0, want, Ranks(1, 2, 2, 1.0), force=False)


@pytest.mark.slow
def test_ranks_of_different_goi_versions_are_refused_at_the_rendezvous(fitted, tmp_path):
    root, args, _ = fitted
    script = tmp_path / "mixed.py"
    script.write_text(
        "import os, sys\n"
        "import stages\n"
        "if os.environ['RANK'] == '1':\n"
        "    stages.__version__ = '0.0.1'  # this rank runs another goi\n"
        "from goi_cli.main import entry\n"
        "entry()\n"
    )
    r = torchrun(2, [*args, "--out", str(root / "mixed.h5")], root, script=str(script))
    assert r.returncode != 0
    lines = goi_lines(r.stderr)
    # each rank refuses; torchrun may stop the slower one before its line is out
    assert 1 <= len(lines) <= 2
    assert all("the ranks run different goi versions" in ln for ln in lines)
    assert not (root / "mixed.h5").exists()


@pytest.mark.slow
def test_a_second_run_of_the_same_out_is_refused_on_every_rank(fitted):
    """The leader holds the output lock for the whole run; here this test holds it (as a first
    run would), and both ranks of the second run refuse with the leader's one line."""
    from stages.core.files import output_lock

    root, args, _ = fitted
    out = root / "locked.h5"
    with output_lock(out, "--out"):
        r = torchrun(2, [*args, "--out", str(out)], root)
    assert r.returncode != 0
    lines = goi_lines(r.stderr)
    # each rank refuses; torchrun may stop the slower one before its line is out
    assert 1 <= len(lines) <= 2, r.stderr[-2000:]
    assert all("is being written by another goi run (pid " in ln for ln in lines)
    assert not out.exists() and not list(root.glob("locked.h5.ckpt*"))

"""A RES index that grows as prompts are asked (#39), on the synthetic scene with photos and
the tiny random Grounded-SAM bundle: a lifted query indexes the views it needs and keeps them,
a later prompt reuses them, goi index-res fills in the rest (also as parts, merged), the
progressive mode rewrites the answer as views are indexed, goi view refines the same way, and
a second process on the same index waits or is refused, never corrupting it."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from goi_cli.main import main
from stages.core.files import output_lock
from stages.query.lift_answer import RefineParams
from stages.query.lift_math import LiftParams
from stages.query.osh import HyperplaneParams
from stages.query.pipeline import PromptSources, QueryParams, QueryRun, run_query
from stages.query.prompts import Prompt, safe_name
from stages.query.res_index import check_values, load_res_index
from stages.query.selection import load_selection
from stages.scene.scene import load_scene
from tests.query.test_res_index import photographed  # noqa: F401  (a scene with photos)

PROMPT = "the red box"
OTHER = "the green lamp"

pytestmark = pytest.mark.slow  # the session's tiny RES models (~30 s to export)


def _q(s, idx, bundle, out, prompt=PROMPT, *extra):
    return ["query", "--scene", str(s["scene"]), "--prompt", prompt, "--lift",
            "--res-index", str(idx), "--bundle", str(bundle), "--out", str(out),
            "--export", "none", *extra]  # fmt: skip


def _sel(out, prompt=PROMPT):
    return load_selection(out / safe_name(prompt) / "selection.h5")


def _same_arrays(a, b, views):
    for v in views:
        x, y = a.image_side(v), b.image_side(v)
        assert all(np.array_equal(x[k], y[k]) for k in x), v


@pytest.fixture(scope="module")
def full_index(photographed, res_bundles, tmp_path_factory):  # noqa: F811
    """The scene's index as goi index-res builds it at once."""
    s, _ = photographed
    idx = tmp_path_factory.mktemp("full") / "index.h5"
    argv = ["index-res", "--scene", str(s["scene"]), "--bundle", str(res_bundles["grounded"]),
            "--out", str(idx)]  # fmt: skip
    assert main(argv) == 0
    return idx


def test_a_lifted_query_grows_the_index_and_later_prompts_reuse_it(
    photographed,  # noqa: F811
    res_bundles,
    full_index,
    tmp_path,
    capsys,
):
    s, _ = photographed
    bundle = res_bundles["grounded"]
    idx = tmp_path / "index.h5"
    # no index yet: the query indexes the 2 views it chooses (a line per view, the time
    # left, off a terminal too) and keeps them
    assert main(_q(s, idx, bundle, tmp_path / "a", PROMPT, "--res-views", "2")) == 0
    err = capsys.readouterr().err
    assert "indexed view" in err and "(1 of 2," in err and "left)" in err, err
    index = load_res_index(idx)
    sel = _sel(tmp_path / "a")
    assert list(index.views) == sel.lifted["views"] and len(index.views) == 2
    assert sel.lifted["refinement"] == {"n_views": 2, "of": 2, "final": True}
    assert sel.lifted["chosen_by"].startswith("coverage (RES index, 2 indexed")
    assert (
        not (tmp_path / "index.h5.partial").exists() and not (tmp_path / "index.h5.lock").exists()
    )
    _same_arrays(index, load_res_index(full_index), index.views)
    # a second prompt on 2 views: the indexed ones, nothing computed, the file untouched
    before = os.stat(idx)
    assert main(_q(s, idx, bundle, tmp_path / "b", OTHER, "--res-views", "2")) == 0
    assert "indexed view" not in capsys.readouterr().err
    after = os.stat(idx)
    assert (after.st_ino, after.st_mtime_ns) == (before.st_ino, before.st_mtime_ns)
    assert sorted(_sel(tmp_path / "b", OTHER).lifted["views"]) == sorted(index.views)
    # by default at least 8 views (here: the scene's 4): the 2 held first, then 2 indexed
    assert main(_q(s, idx, bundle, tmp_path / "c")) == 0
    sel = _sel(tmp_path / "c")
    assert sel.lifted["views"][:2] == list(index.views) and len(sel.lifted["views"]) == 4
    assert sel.lifted["chosen_by"].startswith("the 2 indexed views, then coverage")
    grown = load_res_index(idx)
    assert sorted(grown.views) == sorted(s["train"])
    _same_arrays(grown, load_res_index(full_index), s["train"])
    # on a complete index a query is the complete index's answer, bit for bit
    assert main(_q(s, idx, bundle, tmp_path / "d")) == 0
    assert main(_q(s, full_index, bundle, tmp_path / "e")) == 0
    d, e = _sel(tmp_path / "d"), _sel(tmp_path / "e")
    assert np.array_equal(d.selected, e.selected) and d.lifted["views"] == e.lifted["views"]
    assert "refinement" not in d.lifted and "refinement" not in e.lifted
    # goi index-res fills in what an index lacks, and refuses a complete one
    part = tmp_path / "part.h5"
    assert main(_q(s, part, bundle, tmp_path / "f", PROMPT, "--res-views", "1")) == 0
    capsys.readouterr()
    argv = ["index-res", "--scene", str(s["scene"]), "--bundle", str(bundle), "--out", str(part)]
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert "1 of 4 views already indexed" in err and "indexing 3 views" in err, err
    assert sorted(load_res_index(part).views) == sorted(s["train"])
    assert main(argv) == 2
    assert "already exists and holds all 4 views; pass --force" in capsys.readouterr().err


def test_the_progressive_answer_is_rewritten_as_views_are_indexed(
    photographed,  # noqa: F811
    res_bundles,
    tmp_path,
):
    """Each answer before the last is written in place (selection, masks) and records how
    many views it rests on; the last is the non-progressive answer."""
    s, _ = photographed
    scene = load_scene(s["scene"])
    idx = tmp_path / "index.h5"
    src = PromptSources(bundle=res_bundles["grounded"], res_index=idx)
    path = tmp_path / "q" / safe_name(PROMPT) / "selection.h5"
    seen = []

    class Recorder:
        def log(self, message):
            if message.startswith("answer written"):
                seen.append(load_selection(path).lifted["refinement"])

        def progress(self, items, label, length=None, show=None):
            yield from items

    run = QueryRun(out=tmp_path / "q", export="none")
    lp = LiftParams(lift=True)
    r = run_query(scene, None, Prompt(PROMPT), src, HyperplaneParams(), QueryParams(), run,
                  report=Recorder(), lp=lp,
                  refine=RefineParams(progressive=True, refine_every=1))  # fmt: skip
    assert seen == [{"n_views": k, "of": 4, "final": False} for k in (1, 2, 3)]
    last = load_selection(r.selection)
    assert last.lifted["refinement"] == {"n_views": 4, "of": 4, "final": True}
    # the same answer without --progressive, from no index again: --res-views all
    idx2 = tmp_path / "index2.h5"
    out2 = tmp_path / "q2"
    argv = _q(s, idx2, res_bundles["grounded"], out2, PROMPT, "--res-views", "all")
    assert main(argv) == 0
    assert np.array_equal(_sel(out2).selected, last.selected)
    assert _sel(out2).lifted["views"] == last.lifted["views"]
    # --progressive needs an index, and goi render-mask does not rewrite its answer
    assert main([*argv[:-2], "--progressive"]) == 0  # (complete now: one answer)
    no_index = [a for a in argv if a not in ("--res-index", str(idx2))]
    assert main([*no_index, "--progressive"]) == 2


def _goi(*args):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    return subprocess.Popen([sys.executable, "-m", "goi", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)  # fmt: skip


def test_a_second_process_waits_or_is_refused_and_never_corrupts_the_index(
    photographed,  # noqa: F811
    res_bundles,
    full_index,
    tmp_path,
):
    s, _ = photographed
    bundle = res_bundles["grounded"]
    idx = tmp_path / "index.h5"
    with output_lock(idx, "--res-index"):  # this process adds views to the index
        p = _goi(*_q(s, idx, bundle, tmp_path / "a", PROMPT, "--index-wait", "0"))
        _, err = p.communicate(timeout=300)
        assert p.returncode == 2, err
        assert f"is being written by another goi run (pid {os.getpid()})" in err, err
        assert len(err.strip().splitlines()) == 1, err
        waiting = _goi(*_q(s, idx, bundle, tmp_path / "b", PROMPT, "--index-wait", "600"))
        assert waiting.stderr is not None
        said = []
        for line in waiting.stderr:  # it says so when it meets the lock: wait for that state
            said.append(line)
            if "waiting for it" in line:
                break
        assert waiting.poll() is None, "".join(said)  # still waiting for the lock
        assert not idx.exists()
    _, rest = waiting.communicate(timeout=300)
    err = "".join(said) + rest
    assert waiting.returncode == 0, err
    assert "waiting for it" in err, err
    assert sorted(load_res_index(idx).views) == sorted(s["train"])
    # two processes growing one index at once: both answer, the index is whole
    idx2 = tmp_path / "index2.h5"
    a = _goi(*_q(s, idx2, bundle, tmp_path / "c", PROMPT))
    b = _goi("index-res", "--scene", str(s["scene"]), "--bundle", str(bundle),
             "--out", str(idx2))  # fmt: skip
    (_, ea), (_, eb) = a.communicate(timeout=300), b.communicate(timeout=300)
    assert a.returncode == 0, ea
    # index-res either filled it (first, or after the query) or found the query had
    assert b.returncode == 0 or "holds all 4 views" in eb, eb
    grown = load_res_index(idx2)
    check_values(grown, grown.spec)
    assert sorted(grown.views) == sorted(s["train"])
    _same_arrays(grown, load_res_index(full_index), s["train"])
    assert not list(tmp_path.glob("index2.h5.*"))


def test_index_res_in_parts_merged(photographed, res_bundles, full_index, tmp_path, capsys):  # noqa: F811
    s, _ = photographed
    bundle = res_bundles["grounded"]
    base = ["index-res", "--scene", str(s["scene"]), "--bundle", str(bundle)]
    for k in (1, 2):
        assert main([*base, "--part", f"{k}/2", "--threads", "1",
                     "--out", str(tmp_path / f"p{k}.h5")]) == 0  # fmt: skip
    p1, p2 = load_res_index(tmp_path / "p1.h5"), load_res_index(tmp_path / "p2.h5")
    assert len(p1.views) == len(p2.views) == 2 and not set(p1.views) & set(p2.views)
    capsys.readouterr()
    argv = [*base, "--merge", str(tmp_path / "p1.h5"), "--merge", str(tmp_path / "p2.h5"),
            "--out", str(tmp_path / "all.h5")]  # fmt: skip
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert "4 views from 2 parts" in err and "indexed view" not in err, err
    merged = load_res_index(tmp_path / "all.h5")
    assert list(merged.views) == list(load_res_index(full_index).views)
    _same_arrays(merged, load_res_index(full_index), s["train"])
    for bad in ("3/2", "0/2", "x", "5/6"):  # 5/6: the scene's 4 views leave part 5 empty
        assert main([*base, "--part", bad, "--out", str(tmp_path / "x.h5")]) == 2
        assert "--part" in capsys.readouterr().err
        assert not list(tmp_path.glob("x.h5*"))


def test_goi_view_refines_a_lifted_answer_as_the_index_grows(
    photographed,  # noqa: F811
    res_bundles,
    tmp_path,
):
    """The viewer's lifted route on an index that lacks views: partial answers say how many
    views they rest on, and the answer is goi select --res-views all's."""
    from stages.view.session import Control, ViewRun, ViewSession

    s, _ = photographed
    scene = load_scene(s["scene"])
    bundle = res_bundles["grounded"]
    idx = tmp_path / "index.h5"
    src = PromptSources(bundle=bundle, res_index=idx)
    session = ViewSession(scene, None, src, ViewRun(out=tmp_path / "view"))
    labels = []
    control = Control(partial=lambda a: labels.append(a.label), partial_every=0.0)
    ans = session.answer(PROMPT, "lifted_fieldless", control)
    assert labels == [f"lifted, field-free, {k} of 4 views" for k in (1, 2, 3)]
    assert ans.final and ans.views_done == 4
    assert sorted(load_res_index(idx).views) == sorted(s["train"])
    out = tmp_path / "sel.h5"
    argv = ["select", "--scene", str(s["scene"]), "--prompt", PROMPT, "--lift",
            "--res-index", str(tmp_path / "fresh.h5"), "--bundle", str(bundle),
            "--res-views", "all", "--out", str(out)]  # fmt: skip
    assert main(argv) == 0
    assert np.array_equal(load_selection(out).selected, ans.selected)
    # the next prompt: every view indexed, one answer
    labels.clear()
    session.answer(OTHER, "lifted_fieldless", control)
    assert all("of 4 views" in x for x in labels)
    assert json.loads(json.dumps(load_selection(out).lifted["refinement"]))["final"] is True


def test_a_linked_index_that_lacks_views_is_refused_before_any_work(
    photographed,  # noqa: F811
    res_bundles,
    tmp_path,
    capsys,
):
    """Adding views renames the grown index over the path: a symbolic link there would be
    replaced by a file, so it is refused (exit 2, naming it) and the index it points to is
    left as it was."""
    s, _ = photographed
    bundle = res_bundles["grounded"]
    real = tmp_path / "real.h5"
    assert main(_q(s, real, bundle, tmp_path / "a", PROMPT, "--res-views", "2")) == 0
    before = real.read_bytes()
    link = tmp_path / "link.h5"
    link.symlink_to(real)
    capsys.readouterr()
    assert main(_q(s, link, bundle, tmp_path / "b", OTHER, "--res-views", "3")) == 2
    err = capsys.readouterr().err
    assert "--res-index" in err and "symbolic link" in err, err
    assert link.is_symlink() and real.read_bytes() == before
    assert not (tmp_path / "b").exists()


def test_a_process_reads_each_view_once_to_check_it(full_index, tmp_path, monkeypatch):
    """Prompt after prompt on one index (goi view, goi eval) checks each view's values at the
    first open only; the file written again is checked again."""
    import shutil

    import h5py

    from stages.core.errors import GoiError
    from stages.query import res_index as R

    idx = tmp_path / "index.h5"
    shutil.copy(full_index, idx)
    reads: list[str] = []
    real = R.ResIndex.image_side

    def counted(self, view):
        reads.append(view)
        return real(self, view)

    monkeypatch.setattr(R.ResIndex, "image_side", counted)
    index = load_res_index(idx)
    check_values(index, index.spec)
    assert sorted(reads) == sorted(index.views)
    check_values(load_res_index(idx), index.spec)
    assert len(reads) == len(index.views)  # the same file: not read again
    moved = tmp_path / "published.h5"  # as a writer renames its checked partial file
    os.replace(idx, moved)
    check_values(load_res_index(moved), index.spec)
    assert len(reads) == len(index.views)  # the same file under another name
    os.replace(moved, idx)
    key = next(k for k, (_, d) in index.spec.items() if np.dtype(d).kind == "f")
    view = next(iter(index.views))
    with h5py.File(idx, "r+") as f:
        ds = f["views"][view][key]
        ds[(0,) * ds.ndim] = np.nan
    st = os.stat(idx)  # a write moves the mtime; moved here so the clock's tick cannot hide it
    os.utime(idx, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))
    with pytest.raises(GoiError, match="NaN or infinite"):
        check_values(load_res_index(idx), index.spec)

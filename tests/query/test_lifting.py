"""The lifted mode on a synthetic room: exact masks, a distractor, empty masks, view choice."""

from dataclasses import replace

import numpy as np
import pytest

from stages.core.errors import GoiError, GoiWarning
from stages.query.lift_answer import (
    fit_lifted_plane,
    lift_prompt,
    lifted_masks,
    view_evidence,
    view_visibility,
)
from stages.query.lift_math import (
    Lifted,
    LiftParams,
    ViewEvidence,
    accumulate,
    core_kin,
    fuse,
    relative,
    view_confidence,
    vote_share,
)
from stages.query.osh import HyperplaneParams, probability
from stages.query.prompts import Prompt
from stages.query.res import ResFiles
from stages.query.views import next_view, provisional
from stages.render.lift import selection_mask
from stages.render.rasterizer import Rasterizer
from stages.scene.gaussians import load_ply
from stages.semantics.decode import SemanticRenderer
from stages.semantics.field import Field
from stages.testing.synthetic import look_at, ring_cameras, room_vertex
from tests.helpers import write_ply

N_OBJ = 6
TARGET, DISTRACTOR = 2, 3  # neighbouring boxes on the ring of objects


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    d = tmp_path_factory.mktemp("lift")
    v, ids = room_vertex(12_000, seed=1, n_objects=N_OBJ)
    g = load_ply(write_ply(d / "room.ply", v))
    rast = Rasterizer.from_gaussians(g)
    cams = ring_cameras(16, 96, 72, radius=1.9, height_m=1.5)
    return {"rast": rast, "ids": ids, "cams": cams, "dir": d, "g": g}


def _gt_mask(rast, cam, sel):
    proj, bins = rast.prepare(cam)
    return selection_mask(proj, bins, sel, cam.width, cam.height)


def _perfect_field(ids, dim=8, seed=0):
    """A field whose decoded entry of each Gaussian is its object (entry = id)."""
    n = ids.max() + 1
    codebook = np.random.default_rng(seed).normal(size=(n, dim)).astype(np.float32)
    return Field(
        np.eye(n, dtype=np.float32)[ids], np.eye(n, dtype=np.float32), np.zeros(n), codebook
    )


def _iou(a, b):
    return (a & b).sum() / max((a | b).sum(), 1)


def _evidence(room, masks):
    return [view_evidence(room["rast"], c, m) for c, m in masks]


def test_exact_masks_recover_the_object(room):
    rast, ids = room["rast"], room["ids"]
    target = ids == TARGET
    masks = [(c, _gt_mask(rast, c, target)) for c in room["cams"]]
    assert sum(m.any() for _, m in masks) >= 8
    ev = _evidence(room, masks)
    entry = ids
    out = fuse(ev, entry, np.ones(ids.size, bool), np.zeros(N_OBJ + 1, bool), LiftParams())
    assert _iou(out.selected, target) >= 0.95
    # the masks alone decide most of it; what they do not see, the entry fills in
    assert _iou(out.selected & out.evident, target & out.evident) >= 0.9
    assert out.evident[target].mean() > 0.5


def test_a_distractor_in_one_view_of_many_is_not_selected(room):
    rast, ids = room["rast"], room["ids"]
    target, distractor = ids == TARGET, ids == DISTRACTOR
    masks = [(c, _gt_mask(rast, c, target)) for c in room["cams"]]
    # one view whose mask also holds the distractor (the RES added the neighbour)
    j = max(range(len(masks)), key=lambda i: _gt_mask(rast, masks[i][0], distractor).sum())
    cam, m = masks[j]
    masks[j] = (cam, m | _gt_mask(rast, cam, distractor))
    assert masks[j][1].sum() > m.sum() + 20
    for rounds in (0, 1):
        out = fuse(
            _evidence(room, masks),
            ids,
            np.ones(ids.size, bool),
            np.zeros(N_OBJ + 1, bool),
            LiftParams(confidence_rounds=rounds),
        )
        assert (out.selected & distractor).sum() <= 0.02 * distractor.sum()
        assert _iou(out.selected, target) >= 0.9
    # the confidence of the view that added the distractor drops below the others'
    assert out.confidence[cam.name] < np.median(list(out.confidence.values()))


def test_an_empty_mask_removes_false_positives(room):
    rast, ids = room["rast"], room["ids"]
    target, distractor = ids == TARGET, ids == DISTRACTOR
    # a view that sees both, whose mask wrongly holds the distractor too
    both = max(
        room["cams"],
        key=lambda c: min(_gt_mask(rast, c, target).sum(), _gt_mask(rast, c, distractor).sum()),
    )
    m = _gt_mask(rast, both, target | distractor)
    field_seen = np.ones(ids.size, bool)
    no_plane = np.zeros(N_OBJ + 1, bool)
    alone = fuse(_evidence(room, [(both, m)]), ids, field_seen, no_plane, LiftParams())
    assert (alone.selected & distractor).sum() > 0.3 * distractor.sum()
    # close-ups of the distractor where the target is absent: the RES answers empty
    centre = rast.means[distractor].mean(axis=0).astype(np.float64)
    empties = []
    for k, a in enumerate(np.linspace(0, 2 * np.pi, 12, endpoint=False)):
        eye = centre + np.r_[0.8 * np.cos(a), 0.8 * np.sin(a), 0.8]
        cam = look_at(f"e{k}", eye, centre, 96, 72, 25.0)
        if _gt_mask(rast, cam, target).sum() == 0 and _gt_mask(rast, cam, distractor).sum() > 50:
            empties.append((cam, np.zeros((72, 96), bool)))
    assert len(empties) >= 2
    with_empty = fuse(
        _evidence(room, [(both, m), *empties]), ids, field_seen, no_plane, LiftParams()
    )
    assert (with_empty.selected & distractor).sum() <= 0.05 * distractor.sum()
    assert (with_empty.selected & target).sum() >= 0.9 * (alone.selected & target).sum()


def test_view_confidence_of_an_empty_mask():
    core = np.array([True, True, False, False])
    sees_core = ViewEvidence("a", np.array([0, 1]), np.zeros(2), np.array([500.0, 500.0]), True)
    sliver = ViewEvidence("s", np.array([0, 2]), np.zeros(2), np.array([1.0, 500.0]), True)
    elsewhere = ViewEvidence("b", np.array([2, 3]), np.zeros(2), np.array([5.0, 5.0]), True)
    agrees = ViewEvidence(
        "c", np.array([0, 1, 2]), np.array([5.0, 5.0, 0]), np.array([0, 0, 5.0]), False
    )
    # "nothing here" where much of the core is visible; a sliver of it hardly matters
    assert view_confidence(sees_core, core) < 0.01
    assert view_confidence(sliver, core) > 0.9
    assert view_confidence(elsewhere, core) == 1.0  # nothing claimed, nothing of the core seen
    assert view_confidence(agrees, core) == 1.0


def test_view_choice_covers_the_selection_from_different_sides(room):
    rast, ids = room["rast"], room["ids"]
    target = ids == TARGET
    vis = [view_visibility(rast, c) for c in room["cams"]]
    E = np.zeros(ids.size)
    chosen = []
    left = list(range(len(vis)))
    for _ in range(4):
        j = left.pop(next_view([vis[i] for i in left], target, E))
        chosen.append(j)
        E += vis[j]
    # the first view sees the target best; the next ones add sides the first did not show
    assert chosen[0] == int(np.argmax([np.minimum(v[target], 3.0).sum() for v in vis]))
    seen_by_first = vis[chosen[0]][target] > 0.1
    seen_by_all = E[target] > 0.1
    assert seen_by_all.sum() > seen_by_first.sum()
    assert len(set(chosen)) == 4
    # the provisional selection falls back to the best entry when no entry is positive
    scores = np.full(N_OBJ + 1, -1.0)
    scores[TARGET] = -0.2
    assert np.array_equal(provisional(scores, ids, np.ones(ids.size, bool)), target)


def _write_masks(room, d, sel, names):
    import cv2

    d.mkdir(parents=True, exist_ok=True)
    for c in room["cams"]:
        if c.name in names:
            cv2.imwrite(
                str(d / f"{c.name}.png"), _gt_mask(room["rast"], c, sel).astype(np.uint8) * 255
            )


def test_lift_prompt_from_mask_files(room):
    rast, ids = room["rast"], room["ids"]
    target = ids == TARGET
    field = _perfect_field(ids)
    text = field.unit_codebook()[TARGET]
    d = room["dir"] / "res" / "p"
    names = [c.name for c in room["cams"][::2]]
    _write_masks(room, d, target, names)
    src = ResFiles(d.parent, Prompt("the box", "p"))
    hp = HyperplaneParams()
    ans = lift_prompt(
        SemanticRenderer(room["g"], field),
        room["cams"],
        src,
        "the box",
        text,
        hp,
        LiftParams(lift=True),
    )
    assert ans.views == names and ans.chosen_by == "all mask files"
    assert _iou(ans.selected, target) >= 0.95
    rec = ans.record(LiftParams(lift=True))
    assert [v["view"] for v in rec["per_view"]] == names
    # K of the files, chosen by coverage
    k3 = lift_prompt(
        SemanticRenderer(room["g"], field),
        room["cams"],
        src,
        "the box",
        text,
        hp,
        LiftParams(res_views=3),
    )
    assert len(k3.views) == 3 and set(k3.views) <= set(names)
    assert _iou(k3.selected, target) >= 0.9
    # masks rendered from the selection agree with the object's own silhouette
    m = lifted_masks(rast, ans.selected, room["cams"][1:4])
    for c in room["cams"][1:4]:
        gt = _gt_mask(rast, c, target)
        assert _iou(m[c.name], gt) >= 0.9


def test_lift_prompt_bad_inputs(room, tmp_path):
    ids = room["ids"]
    field = _perfect_field(ids)
    text = field.unit_codebook()[TARGET]
    d = tmp_path / "res" / "p"
    d.mkdir(parents=True)
    import cv2

    cv2.imwrite(str(d / "nope.png"), np.zeros((72, 96), np.uint8))
    src = ResFiles(d.parent, Prompt("x", "p"))
    with pytest.raises(GoiError, match="none of the 16 training views"):
        lift_prompt(
            SemanticRenderer(room["g"], field),
            room["cams"],
            src,
            "x",
            text,
            HyperplaneParams(),
            LiftParams(),
        )
    with pytest.raises(GoiError, match="--res-views: 17 is more than"):
        lift_prompt(
            SemanticRenderer(room["g"], field),
            room["cams"],
            src,
            "x",
            text,
            HyperplaneParams(),
            LiftParams(res_views=17),
        )


def test_res_views_needs_lift():
    LiftParams(lift=True, res_views=3).check()
    with pytest.raises(GoiError, match="only with --lift"):
        LiftParams(res_views=3).check()


def test_lift_prompt_without_a_field(room):
    """The field-free mode: the masks alone decide; what no view's evidence reaches is out."""
    rast, ids = room["rast"], room["ids"]
    target = ids == TARGET
    d = room["dir"] / "res_free" / "p"
    names = [c.name for c in room["cams"][::2]]
    _write_masks(room, d, target, names)
    src = ResFiles(d.parent, Prompt("the box", "p"))
    lp = LiftParams(lift=True)
    ans = lift_prompt(rast, room["cams"], src, "the box", None, HyperplaneParams(), lp)
    assert ans.plane is None and ans.views == names
    # the target's hidden inside (no evidence) stays out, so judge what the views show: the
    # selection holds only the target, and renders as the target does on unseen views
    assert (ans.selected & target).sum() >= 0.95 * ans.selected.sum() > 0
    assert not (ans.selected & ~ans.lifted.evident).any()
    m = lifted_masks(rast, ans.selected, room["cams"][1::4])
    for c in room["cams"][1::4]:
        assert _iou(m[c.name], _gt_mask(rast, c, target)) >= 0.9
    assert ans.record(lp)["semantics"] == "none (field-free)"
    # K views chosen by coverage, with nothing to aim at before the first mask
    k3 = lift_prompt(
        rast, room["cams"], src, "the box", None, HyperplaneParams(), LiftParams(res_views=3)
    )
    assert len(k3.views) == 3 and set(k3.views) <= set(names)
    assert (k3.selected & target).sum() >= 0.9 * k3.selected.sum() > 0


def test_a_res_that_finds_nothing_anywhere_gives_an_empty_answer(room):
    """Every view's mask empty (the detector found nothing): an empty selection and a
    warning, with or without a field, not the field's guess from the text alone."""
    ids = room["ids"]
    field = _perfect_field(ids)
    d = room["dir"] / "res_nothing" / "p"
    names = [c.name for c in room["cams"][::4]]
    _write_masks(room, d, np.zeros(ids.size, bool), names)
    src = ResFiles(d.parent, Prompt("a unicorn", "p"))
    text = field.unit_codebook()[TARGET]  # the text alone would select the target's entry
    for renderer, t in ((SemanticRenderer(room["g"], field), text), (room["rast"], None)):
        with pytest.warns(GoiWarning, match="found nothing for 'a unicorn' on any of the 4 views"):
            ans = lift_prompt(renderer, room["cams"], src, "a unicorn", t, HyperplaneParams(),
                              LiftParams(lift=True))  # fmt: skip
        assert not ans.selected.any() and ans.views == names


def _thin_evidence(views: int = 12, share: float = 0.25):
    """Synthetic evidence of #26's collapse: a thin target (Gaussians 0-199, entry 1) whose
    eroded masks cover only `share` of each Gaussian's footprint, in front of a wall (entry 0)
    of which a rim next to the target (Gaussians 200-249) gets a little (2%) of the masks."""
    target, rim, wall = np.arange(200), np.arange(200, 250), np.arange(250, 3000)
    ev = []
    for v in range(views):
        seen_wall = wall[(wall + 37 * v) % 5 == 0]  # each view sees another part of the wall
        ids = np.concatenate([target, rim, seen_wall])
        w = np.concatenate([np.full(200, 3.0), np.full(50, 5.0), np.full(seen_wall.size, 5.0)])
        s1 = np.concatenate([share * w[:200], 0.02 * w[200:250], np.zeros(seen_wall.size)])
        ev.append(ViewEvidence(f"v{v}", ids, s1, w - s1, False))
    entry = np.zeros(3000, np.int64)
    entry[target] = 1
    return ev, entry, np.arange(3000) < 200


def test_thin_target_with_eroded_masks_does_not_collapse():
    ev, entry, target = _thin_evidence()
    seen = np.ones(entry.size, bool)
    out = fuse(ev, entry, seen, np.array([False, True]), LiftParams())
    # the confidences are relative: the views agree, so none is silenced (#26: all fell to
    # 0.007-0.33 together, because an absolute core of S1 >= 0.75 E was empty)
    conf = np.array(list(out.confidence.values()))
    assert conf.max() == 1.0 and conf.min() > 0.9
    # no Gaussian is more in than out, and the entry is only a quarter in: the vote selects
    # nothing, 0 of the field's 200 Gaussians, and the guard fuses the field's answer with it
    assert not ((out.S1 - out.S0) > 0).any()
    assert out.info["collapsed_vote_fused_with_field"]
    assert _iou(out.selected, target) == 1.0
    # masks that keep 60% of each footprint decide alone
    ev60, _, _ = _thin_evidence(share=0.6)
    out60 = fuse(ev60, entry, seen, np.array([False, True]), LiftParams())
    assert not out60.info["collapsed_vote_fused_with_field"]
    assert _iou(out60.selected, target) == 1.0
    # a rim that the masks barely touch (2%) stays out whatever its entry says
    entry2 = entry.copy()
    entry2[200:250] = 1
    out2 = fuse(ev, entry2, seen, np.array([False, True]), LiftParams())
    assert not out2.selected[200:250].any()


def test_relative_confidence_still_silences_a_confuser():
    ev, entry, target = _thin_evidence(share=0.9)
    # two views also claim the wall they see (the confuser), in full
    for k in (0, 1):
        e = ev[k]
        wall = e.ids >= 250
        e.s1[wall], e.s0[wall] = e.s0[wall], 0.0
    out = fuse(ev, entry, np.ones(entry.size, bool), np.array([False, True]), LiftParams())
    assert out.confidence["v0"] < 0.2 and out.confidence["v1"] < 0.2
    assert min(out.confidence[f"v{v}"] for v in range(2, 12)) == 1.0
    assert _iou(out.selected, target) == 1.0


def test_empty_masks_do_not_set_the_scale_of_the_views_that_answer():
    """#38: a small target that many views show at a few pixels, where the RES answers empty
    (the coffee cup under correlated masks). Its side that only the answering views see (A,
    Gaussians 0-19) becomes the core; the empty masks see none of it and keep the prior's 1,
    and the views that outline the whole cup claim B (20-99) outside the core. Relative to an
    empty mask they sank to 0.22 and the re-vote dropped B; relative to the best view that
    answers they keep 1. A wall (100-199) every view leaves out stays out."""
    ids = np.arange(200)
    whole = np.r_[np.full(100, 5.0), np.zeros(100)]
    ev = [ViewEvidence(f"a{k}", ids, whole.copy(), 10.0 - 2 * whole, False) for k in range(3)]
    sliver = np.r_[np.zeros(20), np.ones(80), np.full(100, 10.0)]  # B at 1 px, the wall
    ev += [ViewEvidence(f"e{k}", ids, np.zeros(200), sliver.copy(), True) for k in range(12)]
    unseen = np.zeros(200, bool)
    out = fuse(ev, np.zeros(200, int), unseen, np.zeros(1, bool), LiftParams())
    assert [out.confidence[f"a{k}"] for k in range(3)] == [1.0, 1.0, 1.0]
    assert out.selected[:100].all() and not out.selected[100:].any()
    # the raw scores, by hand: an empty mask that shows none of the core is the prior's 1; a
    # view claiming A and B has IoU (100 + 10) / (500 + 10) with the core A
    core = ids < 20
    assert view_confidence(ev[3], core) == 1.0
    assert view_confidence(ev[0], core) == pytest.approx(110 / 510)
    raw = np.array([110 / 510] * 3 + [1.0] * 12)
    answering = np.array([True] * 3 + [False] * 12)
    assert relative(raw, answering) == pytest.approx(np.ones(15))
    every = np.ones(15, bool)  # every view set the scale before
    assert relative(raw, every)[:3] == pytest.approx(np.full(3, 110 / 510))
    # a view that answers worse than the best is still ranked under it
    raw[0] = 0.1
    assert relative(raw, answering)[0] == pytest.approx(0.1 / (110 / 510))


def test_the_osh_is_fitted_on_the_views_that_answer():
    """#38: a small object whose masks are mostly empty (the cup under correlated masks). Its
    first codebook entry (A, Gaussians 0-49) only the answering views see; its second (B,
    50-99) the 12 empty masks show too, and their "nothing here" outweighs the 3 answering
    views' claim in the vote. Fitted on every view's S0, the OSH learns to leave B out and the
    guard has nothing to bring back; fitted on the answering views' S0, as the paper fits on
    one RES mask (which always answers), it keeps B, and the guard fuses it with the vote."""
    ids = np.arange(150)
    entry = np.r_[np.zeros(50, int), np.ones(50, int), np.full(50, 2)]  # A, B, a wall
    claim = np.r_[np.full(100, 5.0), np.zeros(50)]
    ev = [ViewEvidence(f"a{k}", ids, claim.copy(), 5.0 - claim, False) for k in range(3)]
    shows_b = np.r_[np.zeros(50), np.full(100, 5.0)]
    ev += [ViewEvidence(f"e{k}", ids, np.zeros(150), shows_b.copy(), True) for k in range(12)]
    # A and B 70 degrees apart, the prompt on A: B starts on the far side of the 0.5 threshold
    codebook = np.array([[1.0, 0, 0], [np.cos(1.22), np.sin(1.22), 0], [0, 0, 1.0]], np.float32)
    eye = np.eye(3, dtype=np.float32)
    field = Field(eye[entry], eye, np.zeros(3, np.float32), codebook)
    hp, lp = HyperplaneParams(), LiftParams()
    text = codebook[0]
    start = field.unit_codebook() @ text - hp.threshold > 0
    first = fuse(ev, entry, field.seen, start, lp)
    assert not first.selected[50:].any()  # the vote: A only
    _, S0_answering = accumulate(ev[:3], np.ones(3), 150)
    assert first.S0_answering == pytest.approx(S0_answering)
    plane = fit_lifted_plane(first, field, entry, "cup", text, hp)
    assert plane.positive.tolist() == [True, True, False]
    out = fuse(ev, entry, field.seen, plane.positive, lp)
    assert out.info["guard"]["fused"] and out.selected[:100].all() and not out.selected[100:].any()
    # every view's S0, empty masks' too, would have taught the plane to leave B out
    every = fit_lifted_plane(replace(first, S0_answering=None), field, entry, "cup", text, hp)
    assert every.positive.tolist() == [True, False, False]
    # with no empty mask there is nothing to leave out
    assert fuse(ev[:3], entry, field.seen, start, lp).S0_answering is None


def _big_object_evidence():
    """A big object whose middle (Gaussians 0-99) every view claims and whose arms (100-199)
    only the 3 views with a whole mask do; 2 tight views see the arms and put them out. Every
    view sees a wall (200-299) and leaves it out. 5 pixels' worth per Gaussian per view."""
    ids = np.arange(300)
    whole, tight = np.r_[np.full(200, 5.0), np.zeros(100)], np.r_[np.full(100, 5.0), np.zeros(200)]
    ev = [ViewEvidence(f"w{k}", ids, whole.copy(), 5.0 - whole, False) for k in range(3)]
    ev += [ViewEvidence(f"t{k}", ids, tight.copy(), 5.0 - tight, False) for k in range(2)]
    return ev


def test_claims_the_field_puts_with_the_core_do_not_count_against_a_view():
    """#38: SAM's tight boxes around a big object agree on its middle, which becomes the core;
    the whole views' claims on the arms must not sink them when the field decodes the arms to
    entries the core holds too. The same claims on a support (entries of its own) still do."""
    ev = _big_object_evidence()
    seen, plane = np.ones(300, bool), np.zeros(4, bool)
    arms = (np.arange(300) >= 100) & (np.arange(300) < 200)
    # the arms' entry (2) also holds 10 Gaussians of the middle (10 / 110 of its weight in the
    # core): the field's "same thing". Without the rule the whole views sink to 0.5 and the
    # arms' entry is put 0.48 in, under the thin-parts rule's 0.5: the arms would be out
    entry = np.r_[np.full(10, 2), np.ones(90, int), np.full(100, 2), np.zeros(100, int)]
    out = fuse(ev, entry, seen, plane, LiftParams())
    assert out.info["core_kin_gaussians"] == 100
    assert min(out.confidence.values()) == 1.0
    assert out.selected[arms].all() and out.selected[:100].all() and not out.selected[200:].any()
    # the same masks where the claimed part decodes to its own entry (3): a support
    entry[100:200] = 3
    support = fuse(ev, entry, seen, plane, LiftParams())
    assert support.info["core_kin_gaussians"] == 0
    assert max(support.confidence[f"w{k}"] for k in range(3)) < 0.6
    assert not support.selected[arms].any() and support.selected[:100].all()
    # by hand: a whole view's union leaves its kin claims out
    kin = np.zeros(300, bool)
    kin[100:200] = True
    core = np.arange(300) < 100
    assert view_confidence(ev[0], core, kin) == 1.0
    assert view_confidence(ev[0], core) == pytest.approx(510 / 1010)
    # kin is the field's word: Gaussians the field never saw are never kin
    S1, S0 = accumulate(ev, np.ones(len(ev)), 300)
    entry[100:200] = 2
    assert core_kin(S1, S0, core, entry, seen, LiftParams()).sum() == 100
    seen[100:200] = False
    assert not core_kin(S1, S0, core, entry, seen, LiftParams()).any()


def _one_view(S1, S0):
    """Aggregated evidence as one view's (confidence 1): the typical view is the pooled one."""
    ids = np.arange(S1.size)
    return [ViewEvidence("v", ids, S1.copy(), S0.copy(), False)], np.ones(1)


def test_guard_fuses_a_collapsed_vote_with_the_field():
    from stages.query.lift_math import guard

    n = 3000
    S1, S0 = np.zeros(n), np.full(n, 10.0)
    S1[:2225] = 1.0  # the masks put the field's answer a little in (eroded), not a majority
    S0[2000:2225] = 0.0
    S1[2225:2300] = 0.1  # seen, rejected outright: stays out
    S1[2300:2400], S0[2300:2400] = 0.0, 0.5  # the field's, under a pixel of evidence: joins
    S1[2400:2500], S0[2400:2500] = 0.0, 0.5  # under a pixel, not the field's: stays out
    field_sel = np.arange(n) < 2400
    sel = np.zeros(n, bool)
    sel[:19] = True  # #26: 19 Gaussians against the field's 2,225
    fused, weighed = guard(sel, field_sel, S1, S0, LiftParams(), *_one_view(S1, S0))
    assert weighed is not None and weighed["fused"]
    assert fused.sum() == 2325 and fused[:2225].all() and fused[2300:2400].all()
    # what it weighed is recorded: 19 against 2,400, and the 2,306 it added
    assert (weighed["vote"], weighed["field"], weighed["added"]) == (19, 2400, 2306)
    # a lifted answer that is merely smaller than the field's (0.6 of it or more) is left alone
    sel[:1440] = True
    same, weighed = guard(sel, field_sel, S1, S0, LiftParams(), *_one_view(S1, S0))
    assert weighed is None and (same == sel).all()  # the size rule did not fire


def test_guard_does_not_fuse_a_field_that_over_selects_what_the_masks_reject():
    """A sound vote (1,400 Gaussians the masks put 90% in) under half of a field that also
    selects a support (2,000 more, which the masks put 10% in: a dilated mask's rim): what the
    field adds carries 0.16 of the vote's claim, and stays out. A vote that lost a thin part
    the masks graze (500 Gaussians kept; the field adds 2,000 the masks put 25% in, 1.1 times
    the vote's claim) is fused."""
    from stages.query.lift_math import guard

    n = 4000
    S1, S0 = np.zeros(n), np.full(n, 10.0)
    S1[:1400], S0[:1400] = 9.0, 1.0  # the object: the vote's
    S1[1400:3400], S0[1400:3400] = 1.0, 9.0  # the support the field also selects
    field_sel = np.arange(n) < 3400
    sel = np.arange(n) < 1400
    same, weighed = guard(sel, field_sel, S1, S0, LiftParams(), *_one_view(S1, S0))
    assert weighed is not None and not weighed["fused"] and (same == sel).all()
    assert weighed["claim_vs_vote"] == round(2000 / (1400 * 9), 4)  # 0.16 of the vote's claim
    assert weighed["pooled_share"] == 0.1
    S1[500:1400], S0[500:1400] = 2.5, 7.5  # a thin part the masks graze, voted out
    S1[1400:3400], S0[1400:3400] = 2.5, 7.5
    field_sel = np.arange(n) < 3400
    sel = np.arange(n) < 500
    fused, weighed = guard(sel, field_sel, S1, S0, LiftParams(), *_one_view(S1, S0))
    assert weighed is not None and weighed["fused"] and (fused == field_sel).all()


def test_guard_does_not_fuse_what_only_some_views_take_in_whole():
    """The same thin part and support, pooled 25% in (claim under half the vote's), but from
    views that differ: under eroded masks every view grazes them (25% each) and they are
    fused; when one view in four takes them in whole and the rest leave them out (a box over
    the object and its table), the typical view says out and the vote stands."""
    from stages.query.lift_math import accumulate, guard, typical_share

    n, views = 4000, 8
    obj, added = np.arange(n) < 1400, (np.arange(n) >= 1400) & (np.arange(n) < 3400)
    field_sel = obj | added
    ids = np.arange(n)

    def evidence(added_share):
        ev = []
        for v, a in enumerate(added_share):
            w = np.where(obj, 20.0, 2.0)  # the object's claim is 10x the support's
            s1 = np.where(obj, 19.0, np.where(added, a * 2.0, 0.0))
            ev.append(ViewEvidence(f"v{v}", ids, s1, w - s1, False))
        return ev

    conf = np.ones(views)
    grazed = evidence([0.25] * views)
    whole = evidence([1.0, 0.0, 0.0, 0.0] * 2)
    assert typical_share(grazed, conf, added) == pytest.approx(0.25)
    assert typical_share(whole, conf, added) == 0.0
    p = LiftParams()
    for ev, fuses in ((grazed, True), (whole, False)):
        S1, S0 = accumulate(ev, conf, n)  # only the pooled share could fuse the support
        fused, weighed = guard(obj.copy(), field_sel, S1, S0, p, ev, conf)
        assert weighed is not None and weighed["fused"] == fuses
        assert weighed["pooled_share"] == 0.25 and weighed["claim_vs_vote"] < 0.5
        assert (fused == (field_sel if fuses else obj)).all()


def test_thin_parts_of_an_object_the_masks_mostly_agree_on():
    from stages.query.lift_math import decide

    # an object (entry 1): a body the masks hold (90% in) and thin legs erosion cut to 30%;
    # a floor (entry 0) whose rim next to the legs the masks touch (30% in) too
    S1 = np.r_[np.full(150, 9.0), np.full(50, 3.0), np.full(50, 3.0), np.zeros(100)]
    S0 = np.r_[np.full(150, 1.0), np.full(50, 7.0), np.full(50, 7.0), np.full(100, 10.0)]
    entry = np.r_[np.ones(200, np.int64), np.zeros(150, np.int64)]
    sel, _ = decide(S1, S0, entry, np.ones(350, bool), np.array([False, True]), LiftParams())
    assert sel[:200].all()  # the legs too: partly in, and so is their entry (76%)
    assert not sel[200:].any()  # the rim: partly in, but its entry (the floor) is not


def test_vote_share_and_the_planes_probability_by_hand():
    """The continuous scores of the relevancy-map protocols: S1 / E where E >= min_evidence,
    the field's probability elsewhere (0 without a field); s(z) is 1/2 on the plane."""
    S1, S0 = np.array([3.0, 0.0, 0.5, 0.0]), np.array([1.0, 2.0, 0.2, 0.0])
    lf = Lifted(np.zeros(4, bool), np.zeros(4, bool), S1, S0, {})
    p = LiftParams(min_evidence=1.0)
    fallback = np.array([0.1, 0.2, 0.3, 0.4], np.float32)
    np.testing.assert_allclose(vote_share(lf, p, fallback), [0.75, 0.0, 0.3, 0.4])
    np.testing.assert_allclose(vote_share(lf, p, None), [0.75, 0.0, 0.0, 0.0])
    z = np.array([0.0, np.log(3.0), -np.log(3.0), 800.0, -800.0])
    np.testing.assert_allclose(probability(z), [0.5, 0.75, 0.25, 1.0, 0.0], atol=1e-7)


def test_guard_yields_to_a_typical_view_that_puts_the_additions_out():
    """#38, "the cactus on the desk": a sound vote (the object, 1,000 Gaussians every view
    puts in) under a field that also selects the support (5,000 more). A box detector takes
    the support in whole on a third of the views; it is big, so its claim beats half the
    vote's, but the typical view puts it out: not fused, and the record says why. The same
    claim from a vote that collapsed (a cup the masks of the views that show it put in, and
    empty masks on the many views that show a sliver of it) is fused: an empty mask puts the
    vote and the additions out alike, so the typical view is taken over the views that
    answer."""
    from stages.query.lift_math import accumulate, guard

    n, views = 6000, 9
    obj = np.arange(n) < 1000  # the rest (5,000) is the support
    ids = np.arange(n)
    ev = []
    for v in range(views):
        boxed = v % 3 == 0  # a third of the views box the support whole
        s1 = np.where(obj, 9.0, 4.0 if boxed else 0.0)
        ev.append(ViewEvidence(f"v{v}", ids, s1, np.where(obj, 10.0, 4.0) - s1, False))
    conf = np.ones(views)
    S1, S0 = accumulate(ev, conf, n)
    sel, field_sel = obj.copy(), np.ones(n, bool)
    kept, weighed = guard(sel, field_sel, S1, S0, LiftParams(), ev, conf)
    assert weighed is not None and weighed["claim_vs_vote"] > 0.5  # the claim alone would fuse
    assert weighed["typical_share"] == 0.0 and not weighed["fused"]
    assert (kept == obj).all()
    assert "typical view that answers puts the field's additions out" in weighed["why"]
    # the collapsed vote: 3 views show the cup (in), 12 empty masks see a sliver of it
    cup = np.arange(n) < 300
    ev = [ViewEvidence(f"s{v}", ids[cup], np.full(300, 3.0), np.full(300, 1.0), False)
          for v in range(3)]  # fmt: skip
    ev += [ViewEvidence(f"e{v}", ids[cup], np.zeros(300), np.full(300, 2.0), True)
           for v in range(12)]  # fmt: skip
    conf = np.ones(len(ev))
    S1, S0 = accumulate(ev, conf, n)
    sel = np.zeros(n, bool)
    sel[:5] = True  # the vote kept 5 of the cup's 300
    fused, weighed = guard(sel, cup, S1, S0, LiftParams(), ev, conf)
    assert weighed is not None and weighed["fused"] and (fused == cup).all()
    assert weighed["typical_share"] == 0.75  # over the 3 views that answer
    assert "carry much of the masks' claim" in weighed["why"]

"""The lifted mode's math, arrays in and arrays out: RES masks of several views voted onto the
Gaussians and fused with the semantic field (the tile walks are in `stages.render.lift`; one
prompt's answer is orchestrated in `stages.query.lift_answer`, its files in `lift_files`).

Per view v the walk gives each Gaussian i its evidence s1_v,i (blend weight on mask pixels) and
s0_v,i (on the other pixels). An empty mask is evidence too: every Gaussian the view sees gets
s0 (nothing of the prompt there). The decision, per prompt:

  1. vote      S1 = sum_v c_v s1_v, S0 = sum_v c_v s0_v, E = S1 + S0; a Gaussian with
               E >= tau (`min_evidence`, in pixels' worth of blend weight) is selected when
               S1 - S0 > beta E (`background_bias` beta; 0 is the plain majority, FlashSplat's
               background bias in the same role).
  2. fallback  a Gaussian with E < tau (no view saw enough of it) takes the semantic decision of
               its codebook entry k (the field's decoded feature): the entry's own vote, summed
               over the entry's Gaussians that have evidence, or, for an entry none of whose
               Gaussians has evidence, the OSH's side of the plane. Gaussians the field never
               saw (zero feature) are out, as in the paper's selection.
  3. view confidence (`rounds`): real RES models repeat their mistakes across views (the same
               confuser in many views, masks on views where the target is absent), so errors
               are correlated and a plain majority can lose. After a vote, the core
               C = {E >= tau, S1 >= q E} (q = `core_share`) is what the views agree on
               confidently; each view is scored by the weighted IoU of its lifted mask with
               the core (K: the core's kin, below),
                   c_v = (sum_C s1_v + k) / (sum_C (s1_v + s0_v) + sum_notCnotK s1_v + k),
               (k = CONFIDENCE_PRIOR pixels' worth, so a view that neither sees the core nor
               claims anything keeps 1, and an empty mask on a view that shows a sliver of the
               core is not silenced by it; an empty mask on a view that shows much of the core
               goes to ~0), and the vote is taken again with c_v. A view
               that keeps adding the same confuser, or answers where the target is absent, is
               down-weighted as a whole instead of winning Gaussian by Gaussian.
               The core is relative (`agreed_core`: a share S1 / E of at least q times the
               largest share any Gaussian has), so it is empty only when no mask claims
               anything, and so are the confidences (`relative`: c_v over the largest c_v of
               a view that answers, floored at CONFIDENCE_FLOOR and capped at 1): on a thin
               target under eroded masks an absolute core is empty, every view scored
               0.007-0.33 and the re-vote silenced all the evidence at once (#26). An empty
               mask has no claim to score, so it never sets that scale (#38: a small cup's
               empty masks kept 1 on the prior alone and the views outlining it 0.17-0.35).
               The rounds stop when the confidences stop moving.
               A claim outside the core does not count against a view where the field says
               it is the same thing as the core (`core_kin`: an evident, field-seen Gaussian
               whose codebook entry holds at least KIN_SHARE of its evident weight in the
               core): SAM's tight boxes around a big object, repeated on half the views,
               agree on its middle, which becomes the core, and the views that take it whole
               (arms, frame) sank to 0.27-0.49 while the tight ones kept 0.58-1 (#38). A
               support a box detector takes in, or a neighbour, decodes to other entries and
               still counts against the views that claim it. Kin is only forgiven, never
               rewarded: a same-class neighbour can share the core's entries (two armchairs),
               and counting claims on it as hits brought it in (docs/studies/correlated-errors.md).
  4. thin parts: a Gaussian voted out that the masks still put partly in (S1 >= PARTLY_IN E),
               and whose codebook entry they put at least ENTRY_PARTLY_IN in (summed over the
               entry's evident Gaussians), is in: erosion by 2-3 px leaves a thin part only 6-32% of
               its footprint, and the field, not a majority of pixels, says what it is.
  5. guard:    a lifted answer under 0.6 of the field's own (the OSH's side of the plane) may be
               a vote that lost what the masks only graze: the field's answer joins it where the
               masks see it and do not reject it outright, when what it adds carries at least
               half as much of the masks' claim (S1) as the vote does or the masks put it
               partly in, pooled (`guard`); neither reason fuses against the typical view that
               answers (a non-empty mask) when it rejects the additions outright, and the
               pooled share also needs it to put them partly in: a field that over-selects
               what the masks hardly claim, or what only some views take in whole (a support
               a box detector boxes on a third of the views), is not fused.

The OSH itself is fitted on the lifted evidence (`entry_counts`): entry k's positive and
negative weights are the S1 and S0 of its Gaussians, the same loss as the paper's per-pixel
counts but over the Gaussians all the views see, S0 taken over the views that answer (a mask
that is not empty). The paper fits on one RES mask, which always answers; an empty mask says
"nothing of the prompt here" of the target and everything else alike, so it cannot tell the
plane which is which, and on a small target whose masks are mostly empty (the cup under
correlated masks: 33 empty, 5 right) its negatives taught the plane to leave out the cup's
second codebook entry (it kept one of the two, 214 Gaussians; without them both, 577; lifted
test IoU 0.51 -> 0.81, no other prompt of the dev runs moved). The vote itself still counts
empty masks: they are what keeps a confuser out where the target is absent.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Annotated

import numpy as np

from stages.core.errors import GoiError
from stages.core.params import FRACTION, NON_NEGATIVE, Range
from stages.query.osh import Counts, HyperplaneParams

#: Pixels' worth of agreement every view starts with in its confidence (see the module doc).
CONFIDENCE_PRIOR = 10.0
#: The least confidence a view keeps, relative to the most trusted view's (see `relative`).
CONFIDENCE_FLOOR = 0.02
#: Share of a Gaussian's evidence (S1 / E) from which the masks count it as partly in (decide:
#: thin structures under eroded masks; lower shares bled into neighbours on dilated masks,
#: measured in docs/studies/thin-targets.md) ...
PARTLY_IN = 0.2
#: ... when its codebook entry's share is at least this (a support that one view's mask takes
#: whole stays out).
ENTRY_PARTLY_IN = 0.5
#: The lifted answer disagrees with the field below this share of the field's selection
#: (`guard`; 0.02 would catch only #26's outright collapse, 19 against 2,225 Gaussians, and
#: left the palm plant at 3D IoU 0.17 on res/). The guitar's vote, which loses its neck,
#: holds 0.46-0.56 of the field's answer over 3 fields and 2 draws of the masks: 0.6 lets the
#: guard weigh it, and every fusion between 0.5 and 0.6 (7 of them) helped; the first that
#: hurt sits at 0.61-0.65 (docs/studies/thin-targets.md).
COLLAPSE_RATIO = 0.6
#: Share of "in" below which the masks reject a Gaussian outright (`guard`).
REJECTED_SHARE = 0.05
#: The guard fuses only when what the field adds carries at least this share of the masks'
#: claim (S1) that the vote itself carries: the vote lost much of what the masks claim. On the
#: dev room (3 fits of the field x 4 RES sets, every firing of the size rule) the fusions that
#: helped had 0.75-11, the ones that hurt 0.03-0.39 (docs/studies/thin-targets.md).
LOST_CLAIM = 0.5
#: ... and the masks' pooled share counts only when the typical view that answers (the median
#: of the non-empty views' own shares, weighted by how much of the additions each sees) puts
#: them at least this much in too: a pooled share from a few views that take the additions in
#: whole (SAM's box over the plant and its table, repeated in a quarter of the views) is the
#: per-view error the vote exists to out-vote. On the dev room (3 fits x 5 RES sets, every case
#: the pooled share decided) the fusions that hurt had 0.00-0.01, the ones that helped
#: 0.19-0.31. The claim counts unless the typical view rejects the additions outright (under
#: REJECTED_SHARE): a detector's box over the desk under "the cactus on the desk" on a third
#: of the views carried 1.22 of the vote's claim at a typical view of 0.0005; the fusions by
#: the claim that helped on the dev room had 0.10-0.97, p07's table 0.001-0.011
#: (docs/studies/correlated-errors.md).
TYPICAL_PARTLY_IN = 0.1
#: A Gaussian outside the core is kin to it (`core_kin`) when its codebook entry holds at
#: least this share of its evident weight (E) in the core. Of the sofa's 4,344 Gaussians that
#: SAM's tight boxes leave out on half the views (in the vote, not in the core), 2,486-3,086
#: decode to entries with 10 % or more of their weight in the core; of the 1,196 of the side
#: table under "the plant on the side table", 31-67 (fields 0-2). Replayed on the dev room's
#: runs of #38 (docs/studies/correlated-errors.md), 0.1 brought the sofa (field 2) from 0.761
#: to 0.777 only, 0.05 to 0.794; 0.03 began to forgive the television's cabinet
#: (`res-correlated/`, 0.882 -> 0.857).
KIN_SHARE = 0.05
#: The rounds stop once no view's relative confidence moves by more than this.
CONFIDENCE_TOL = 1e-3
#: Views the RES model runs on when it has to run (a model costs seconds per view on a CPU).
DEFAULT_MODEL_VIEWS = 8


#: --confidence-rounds at most: the weights settle within a few rounds (the loop stops there).
MAX_ROUNDS = 100


@dataclass
class LiftParams:
    """The lifted mode: RES masks of several views lifted onto the Gaussians, fused with the
    OSH. Recorded with every lifted answer."""

    lift: bool = False
    """Lift the RES masks of several views onto the Gaussians and fuse them with the OSH (masks
    are then rendered from the 3D selection); the default is the paper's one-view query."""
    res_views: Annotated[int | None, Range(ge=1)] = None
    """With --lift: how many views' RES masks to lift. Default: every mask file of the prompt
    (--res-masks), or 8 views chosen to cover the provisional selection when a RES model runs."""
    min_evidence: Annotated[float, NON_NEGATIVE] = 1.0
    """With --lift: a Gaussian whose lifted blend weight S1 + S0 over the views is below this
    (in pixels' worth) takes the semantic decision (its codebook entry / the OSH) instead."""
    background_bias: Annotated[float, Range(gt=-1.0, lt=1.0)] = 0.0
    """With --lift: a Gaussian is in when S1 - S0 > bias (S1 + S0); > 0 favours background."""
    confidence_rounds: Annotated[int, Range(ge=0, le=MAX_ROUNDS)] = 1
    """With --lift: rounds of per-view confidence re-weighting (0: a plain vote); the rounds
    stop early once the views' weights settle."""
    core_share: Annotated[float, FRACTION] = 0.75
    """With --lift: share of S1 that puts a Gaussian in the core the views are scored against."""
    clean: bool = True
    """With --lift: drop the pieces of the answer farther than 3 % of the scene's extent
    from its body, unless the masks claim them strongly in their own right (a second object
    of the prompt stays); the selection records how many Gaussians went and by which rule.
    --no-clean keeps the vote's answer as it is."""

    def config(self) -> dict:
        return asdict(self)

    def check(self, hp: HyperplaneParams | None = None) -> None:
        """Options that mean nothing in the mode chosen are refused, never ignored: the
        lifted-mode options without --lift, and with --lift the one-view fit's choice of views
        (`hp`'s --fit-on and --fit-views; the lifted mode picks its own, see --res-views)."""
        if not self.lift:
            defaults = LiftParams()
            for name in ("res_views", "min_evidence", "background_bias", "confidence_rounds",
                         "core_share", "clean"):  # fmt: skip
                if getattr(self, name) != getattr(defaults, name):
                    no = "no-" if getattr(defaults, name) is True else ""  # --no-clean
                    option = "--" + no + name.replace("_", "-")
                    raise GoiError(f"{option}: only with --lift (an option of the lifted mode)")
            return
        if hp is not None and hp.fit_on is not None:
            raise GoiError(
                f"--fit-on: not with --lift, which lifts the RES masks of many views (choose "
                f"how many with --res-views), not of the view(s) {hp.fit_on[:60]!r}"
            )
        if hp is not None and hp.fit_views != HyperplaneParams().fit_views:
            raise GoiError("--fit-views: not with --lift (choose how many with --res-views)")


@dataclass
class ViewEvidence:
    """One view's lifted mask, kept sparse: only the Gaussians the view sees."""

    view: str
    ids: np.ndarray  # [k] int64, Gaussians with weight in the view
    s1: np.ndarray  # [k] float64
    s0: np.ndarray  # [k] float64
    empty: bool  # the mask had no pixel

    @classmethod
    def from_dense(cls, view: str, s1: np.ndarray, s0: np.ndarray) -> ViewEvidence:
        ids = np.flatnonzero((s1 > 0) | (s0 > 0))
        return cls(view, ids, s1[ids], s0[ids], not bool((s1 > 0).any()))

    def visibility(self, n: int) -> np.ndarray:
        """[G] the view's blend weight per Gaussian (s1 + s0)."""
        out = np.zeros(n)
        out[self.ids] = self.s1 + self.s0
        return out

    def summary(self) -> dict:
        return {
            "view": self.view,
            "empty": self.empty,
            "s1": float(self.s1.sum()),
            "s0": float(self.s0.sum()),
        }


@dataclass
class Lifted:
    selected: np.ndarray  # [G] bool
    evident: np.ndarray  # [G] bool: decided by the masks (E >= tau)
    S1: np.ndarray  # [G] float64
    S0: np.ndarray  # [G] float64
    confidence: dict[str, float]  # view -> c_v of the final vote
    info: dict = field(default_factory=dict)
    #: [G] float64: S0 over the views that answer (not empty), what the OSH is fitted on (the
    #: module doc); None: S0 (no view is empty)
    S0_answering: np.ndarray | None = None


def accumulate(
    evidence: list[ViewEvidence], conf: np.ndarray, n: int
) -> tuple[np.ndarray, np.ndarray]:
    """S1, S0 [G]: the confidence-weighted sums over the views."""
    S1, S0 = np.zeros(n), np.zeros(n)
    for c, e in zip(conf, evidence, strict=True):
        if c > 0:
            S1[e.ids] += c * e.s1
            S0[e.ids] += c * e.s0
    return S1, S0


def view_confidence(e: ViewEvidence, core: np.ndarray, kin: np.ndarray | None = None) -> float:
    """Weighted IoU of a view's lifted mask with the core [G] bool (see the module doc); its
    claims on `kin` [G] bool (outside the core, see `core_kin`) are left out of the union."""
    in_core = core[e.ids]
    hit = float(e.s1[in_core].sum())
    claimed = e.s1 if kin is None else e.s1[~kin[e.ids]]
    union = float(e.s0[in_core].sum()) + float(claimed.sum())
    return (hit + CONFIDENCE_PRIOR) / (union + CONFIDENCE_PRIOR)


def core_kin(
    S1: np.ndarray, S0: np.ndarray, core: np.ndarray, entry: np.ndarray, seen: np.ndarray,
    p: LiftParams,
) -> np.ndarray:  # fmt: skip
    """[G] bool: the evident, field-seen Gaussians outside the core whose codebook entry holds
    at least KIN_SHARE of its evident weight (S1 + S0) in the core: what the field says is the
    same thing as what the views agree on. entry [G] int, seen [G] bool, core [G] bool."""
    E = S1 + S0
    evident = (E >= p.min_evidence) & seen
    n = int(entry.max(initial=-1)) + 1
    in_core = np.bincount(entry[evident & core], weights=E[evident & core], minlength=n)  # [N]
    total = np.bincount(entry[evident], weights=E[evident], minlength=n)  # [N]
    share = np.divide(in_core, total, out=np.zeros(n), where=total > 0)
    return evident & ~core & (share[entry] >= KIN_SHARE)


def agreed_core(S1: np.ndarray, S0: np.ndarray, p: LiftParams) -> np.ndarray:
    """[G] bool: the core the views are scored against: the evident Gaussians whose share of
    "in" S1 / E is at least `core_share` of the largest share any evident Gaussian has. On a
    compact target the largest share is ~1 and this is S1 >= q E; on a thin one, whose every
    Gaussian straddles eroded mask boundaries, no Gaussian reaches q E and an absolute core
    would be empty (every view then scores ~0). Empty only when no mask claims anything."""
    E = S1 + S0
    evident = E >= p.min_evidence
    share = np.divide(S1, E, out=np.zeros_like(E), where=evident)  # [G]
    top = float(share.max(initial=0.0))
    if top <= 0.0:
        return np.zeros(E.shape, bool)
    return evident & (share >= p.core_share * top)


def relative(raw: np.ndarray, answering: np.ndarray) -> np.ndarray:
    """[V] confidences relative to the most trusted answering view's (`answering` [V] bool: the
    views whose mask is not empty; when none is, all), floored at CONFIDENCE_FLOOR and capped
    at 1. The weighted IoU with the core falls for every view together when the core is small
    against what the views claim (a thin target, eroded masks): absolute confidences of 0.007-0.33
    shrink every Gaussian's evidence below `min_evidence` and hand the prompt to the field.
    Relative ones keep the best view's evidence at full weight and rank the others.
    An empty mask has nothing to agree with: its raw confidence is the prior's alone, 1 when
    it shows none of the core, so it must not set the scale. Under a small target's correlated
    masks (the coffee cup: 33 empty masks, 5 right ones) it did, and the views that outline
    the cup kept 0.17-0.35 while the empty ones kept 0.9-1."""
    answers = raw[answering] if answering.any() else raw
    top = float(answers.max(initial=0.0))
    if top <= 0.0:
        return np.ones_like(raw)
    return np.clip(raw / top, CONFIDENCE_FLOOR, 1.0)


def entry_counts(
    S1: np.ndarray, S0: np.ndarray, entry: np.ndarray, seen: np.ndarray, n_entries: int
) -> Counts:
    """The OSH's training counts from lifted evidence: per codebook entry, the S1 and S0 of the
    (field-seen) Gaussians decoding to it (S0 of the views that answer: `Lifted.S0_answering`)."""
    return Counts(
        np.bincount(entry[seen], weights=S1[seen], minlength=n_entries),
        np.bincount(entry[seen], weights=S0[seen], minlength=n_entries),
    )


def decide(
    S1: np.ndarray,
    S0: np.ndarray,
    entry: np.ndarray,
    seen: np.ndarray,
    plane_positive: np.ndarray,
    p: LiftParams,
) -> tuple[np.ndarray, np.ndarray]:
    """[G] selection and [G] 'decided by the masks' (steps 1 and 2 of the module doc).
    entry [G] int: each Gaussian's codebook entry; seen [G] bool; plane_positive [N] bool."""
    n = plane_positive.shape[0]
    E = S1 + S0
    evident = E >= p.min_evidence
    vote = (S1 - S0) > p.background_bias * E
    ev = evident & seen
    a = np.bincount(entry[ev], weights=S1[ev], minlength=n)  # [N]
    b = np.bincount(entry[ev], weights=S0[ev], minlength=n)
    # an entry decides for its unseen Gaussians once it has a pixel's worth of evidence
    entry_in = np.where(a + b >= 1.0, (a - b) > p.background_bias * (a + b), plane_positive)
    # thin structures: a Gaussian that the masks put partly in (eroded masks cut most of a thin
    # part's footprint) is in when its codebook entry, over all its evident Gaussians, is put
    # mostly in: the masks and the field agree on it (step 4 of the module doc)
    share = np.divide(S1, E, out=np.zeros_like(E), where=evident)  # [G]
    # (bincount of no Gaussians is int64, whatever the weights)
    entry_share = np.divide(a, a + b, out=np.zeros(n), where=a + b >= 1.0)  # [N]
    partly = seen & (share >= PARTLY_IN) & (entry_share[entry] >= ENTRY_PARTLY_IN)
    sel = np.where(evident, vote | partly, seen & entry_in[entry])
    return sel, evident


def fuse(
    evidence: list[ViewEvidence],
    entry: np.ndarray,
    seen: np.ndarray,
    plane_positive: np.ndarray,
    p: LiftParams,
) -> Lifted:
    """The lifted answer from the views' evidence (module doc, steps 1-3). With no evidence at
    all every Gaussian takes the semantic decision (the OSH)."""
    n = entry.shape[0]
    conf = np.ones(len(evidence))
    answering = np.array([not e.empty for e in evidence], bool)  # [V]
    S1, S0 = accumulate(evidence, conf, n)
    rounds, kin_count = 0, None  # kin of the last round's core (None: no round ran)
    for _ in range(p.confidence_rounds):
        core = agreed_core(S1, S0, p)
        kin = core_kin(S1, S0, core, entry, seen, p)
        kin_count = int(kin.sum())
        new = relative(np.array([view_confidence(e, core, kin) for e in evidence]), answering)
        if np.abs(new - conf).max(initial=0.0) <= CONFIDENCE_TOL:
            break  # the vote would not change: more rounds only cost time
        conf = new
        S1, S0 = accumulate(evidence, conf, n)
        rounds += 1
    sel, evident = decide(S1, S0, entry, seen, plane_positive, p)
    sel, weighed = guard(sel, seen & plane_positive[entry], S1, S0, p, evidence, conf)
    S0_answering = None
    if not answering.all():
        _, S0_answering = accumulate(
            [e for e, a in zip(evidence, answering, strict=True) if a], conf[answering], n
        )
    confidence = {e.view: round(float(c), 4) for e, c in zip(evidence, conf, strict=True)}
    info = {
        "confidence_rounds_run": rounds,
        "core_kin_gaussians": kin_count,
        "collapsed_vote_fused_with_field": bool(weighed and weighed["fused"]),
        "guard": weighed,
    }
    return Lifted(sel, evident, S1, S0, confidence, info, S0_answering)


def vote_share(lifted: Lifted, p: LiftParams, fallback: np.ndarray | None) -> np.ndarray:
    """[G] float32 in [0, 1], the lifted answer as a continuous score: the masks' share
    S1 / (S1 + S0) where the evidence reaches min_evidence, else `fallback` (the field's
    probability, [G]) or 0 without a field. The selection's own cut is the vote with its
    background bias, the entry rules and the guard, so 0.5 is not exactly its boundary."""
    E = lifted.S1 + lifted.S0
    evident = E >= p.min_evidence
    share = np.divide(lifted.S1, E, out=np.zeros_like(E), where=evident)
    rest = np.zeros_like(E) if fallback is None else fallback
    return np.where(evident, share, rest).astype(np.float32)


def typical_share(evidence: list[ViewEvidence], conf: np.ndarray, members: np.ndarray) -> float:
    """The share of "in" the typical view that answers gives the Gaussians `members` [G] bool:
    each view's own share (s1 over s1 + s0 of the members it sees), and the median over the
    views, each weighted by how much of the members it sees times its confidence. A view whose
    mask is empty is left out: "nothing of the prompt here" puts the vote and the additions out
    alike, so it cannot say which of them the prompt is (the coffee cup under the room's
    correlated masks: 33 empty masks on views that show a sliver of it, and the cup itself on
    the 8 that show it). 0 when no answering view sees them."""
    shares, weights = [], []
    for c, e in zip(conf, evidence, strict=True):
        if e.empty:
            continue
        m = members[e.ids]
        seen = float((e.s1[m] + e.s0[m]).sum())
        if c > 0 and seen > 0:
            shares.append(float(e.s1[m].sum()) / seen)
            weights.append(c * seen)
    if not shares:
        return 0.0
    order = np.argsort(shares, kind="stable")
    cum = np.cumsum(np.asarray(weights)[order])
    return float(np.asarray(shares)[order][np.searchsorted(cum, 0.5 * cum[-1])])


def guard(
    sel: np.ndarray,
    field_sel: np.ndarray,
    S1: np.ndarray,
    S0: np.ndarray,
    p: LiftParams,
    evidence: list[ViewEvidence],
    conf: np.ndarray,
) -> tuple[np.ndarray, dict | None]:
    """[G] selection, and what the guard weighed (None when the size rule did not fire; else the
    vote's, the field's and the added Gaussians' counts, the additions' claim against the vote's,
    their pooled and typical-view shares, whether they were fused and why, in words; recorded with
    the answer, so a user can see why a prompt was fused or not). When the lifted answer holds fewer
    than COLLAPSE_RATIO of the Gaussians the field selects (#26: 19 against 2,225; a palm whose
    fronds erosion erased: 980 against 4,371) the vote may have lost what the masks only graze, and
    the field's answer joins it where the masks see it and do not reject it outright (S1 >=
    REJECTED_SHARE E): a field that selects a whole support must not bring in what no mask claims.
    The field's Gaussians that no mask sees (E < min_evidence: a thin frond's footprint is under a
    pixel in most views) join too: the vote has no evidence against them, and its entry-level
    decision for them is the collapsed one (the palm on res/: 3D IoU 0.429 -> 0.667).

    A smaller answer than the field's is also what a sound vote gives when the field
    over-selects: the dev room's "plant on the side table" with other fits of the field
    (seeds 1, 2) selected 3,374-4,312 Gaussians, the table's among them, against the vote's
    1,439-1,634, and fusing took its 3D IoU from 0.78-0.92 to 0.36-0.66. What tells them apart
    is how much of the masks' claim the field's additions carry: S1 summed over them is 0.75
    to 11 times the vote's own where the vote lost a thin part or collapsed (the palm, a cup
    its correlated masks put out) and 0.03-0.39 times where the field over-selects. So the
    field's additions join only when they carry at least LOST_CLAIM of the vote's S1, or when
    the masks put them at least PARTLY_IN, pooled over them: under masks eroded 2-3 px a thin
    part's claim is small against the core's (0.17-0.22 of it for the side-table plant and the
    guitar) but its pooled share is 0.24-0.29, where a field that takes in the table under the
    room's simulated masks gets 0.07-0.16. SAM's boxes that take the table in whole on a quarter
    of the views pool to 0.23 too, so the pooled share counts only when the typical view puts
    the additions partly in as well (`typical_share` >= TYPICAL_PARTLY_IN: 0.19-0.31 for the thin
    parts under eroded masks, 0.00-0.01 for the table).

    The claim alone is no better a reason (#38): a support that a box detector takes in whole
    on a third of the views ("the cactus on the desk", "the flowers on the table") is big, so
    its claim beats half the vote's (1.22 times it, lifted test IoU 0.16 where the vote alone
    was right), while the typical view puts it out (0.0005). So no reason fuses against a
    typical view that rejects the additions outright (under REJECTED_SHARE). The typical view
    is taken over the views that answer: an empty mask puts the vote and the additions out
    alike, and a cup its correlated masks answer "absent" (empty) on 33 views that show a
    sliver of it (vote 10 Gaussians, field 635) is put in by the views that show it (0.78).
    `evidence` and `conf` are the views' evidence and confidences that S1 and S0 accumulate."""
    n_field = int(field_sel.sum())
    if n_field == 0 or sel.sum() >= COLLAPSE_RATIO * n_field:
        return sel, None
    E = S1 + S0
    kept = (E < p.min_evidence) | (S1 >= REJECTED_SHARE * E)
    extra = field_sel & kept & ~sel
    claim, vote_claim = float(S1[extra].sum()), float(S1[sel].sum())
    seen = float(E[extra & (E >= p.min_evidence)].sum())
    typical = typical_share(evidence, conf, extra)
    lost = claim >= LOST_CLAIM * vote_claim  # the vote lost much of the masks' claim
    partly = claim >= PARTLY_IN * seen  # the masks put the additions partly in, pooled
    # (when neither, the masks claim little of what the field adds: it over-selects). Either
    # reason yields to a typical view that rejects the additions outright, as the guard
    # rejects a Gaussian (#38: a support boxed on a third of the views, 0.0005-0.011; the
    # fusions by the claim that helped, 0.10-0.97); the pooled share, a weaker reason, also
    # needs the typical view to put them partly in
    by_claim = lost and typical >= REJECTED_SHARE
    by_share = partly and typical >= TYPICAL_PARTLY_IN
    if by_claim:
        why = "fused: the field's additions carry much of the masks' claim"
    elif by_share:
        why = "fused: the masks put the field's additions partly in, pooled and typically"
    elif lost or partly:
        why = "not fused: the typical view that answers puts the field's additions out"
    else:
        why = "not fused: the masks claim little of the field's additions"
    weighed = {
        "vote": int(sel.sum()),
        "field": n_field,
        "added": int(extra.sum()),
        "claim_vs_vote": round(claim / vote_claim, 4) if vote_claim > 0 else None,
        "pooled_share": round(claim / seen, 4) if seen > 0 else None,
        "typical_share": round(typical, 4),
        "fused": by_claim or by_share,
        "why": why,
    }
    return (sel | extra if weighed["fused"] else sel), weighed

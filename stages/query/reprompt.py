"""The 3D answer prompts SAM back (`--refine sam`): every lifted view re-segmented from the
lifted answer, and those masks voted beside the RES masks.

The lifted mode can only weigh the masks it is given, and a box detector repeats its mistakes
view after view (it boxes the support a prompt names; SAM, given that box, misses the same part
of a large object in every view). But the lifted answer is 3D: projected into a view it says
where the object is and where it is not, consistently across views, which is the question SAM
answers best (cross-view self-prompting, as in SA3D). Per round and lifted view:

    box        the box around the answer's projection there (its main parts: a few stray
               Gaussians do not stretch it), with a small margin;
    points     the projection's most interior pixels (deep inside: SAM segments the whole of
               what they are in);
    not here   a point deep inside what the vote rejected outright (S1 < 0.1 E, seen by the
               masks) that shows inside the box and outside the answer: a support the vote kept
               out, which SAM, given only the box, would outline with the object.

SAM's masks are lifted and voted together with the RES masks, with the route's own fusion (the
field, the OSH, the guard). The RES masks stay the first evidence: a view's SAM mask is one
more mask, named VIEW+sam, weighing SAM_WEIGHT = 0.5 against its RES mask's 1 (and the vote's
confidence rounds weigh each by how well it agrees with the core), so SAM decides where the
RES masks are split or silent, not against their majority. At full weight SAM's outline won
where it repeats its own mistake in every view (the TV's screen without its frame: the TV on
the support set 0.894 -> 0.880, at half weight 0.915; the TV cabinet with the TV on it 0.942
-> 0.915, at half 0.940), and the thin palm gained less at half weight (0.291 -> 0.638 at
full, 0.550 at half) while no prompt lost more than 0.004. Rounds repeat while the answer
changes by more than `refine_settle` of its size, at most `refine_rounds`; in a later round a
view whose sight of the answer moved by at most RESHOWN keeps its SAM mask (SAM's answer to a
prompt moved by a few pixels), so a round costs the views it moves. A view that shows less
than LEAST_SIGHT pixels of the answer is not asked (its RES mask already says what it says, and
SAM given a box of a few pixels outlines what it likes).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import numpy as np

from stages.core.errors import GoiError
from stages.core.params import Choice, Range
from stages.core.report import SILENT, Report
from stages.models.bundle import Bundle
from stages.models.grounded import Sam
from stages.query.lift_answer import LiftedAnswer, Revise, view_evidence
from stages.query.lift_math import ViewEvidence
from stages.query.point_math import box_pixels, expand_box, interior_points, main_parts, mask_box
from stages.query.pointing import BOX_KEEP, INTERIOR_POINTS, TIGHT, SamImages
from stages.query.res_index import GrowingIndex, ResIndex
from stages.render.lift import selection_masks
from stages.render.rasterizer import KEEP_VIEWS_BYTES, Rasterizer
from stages.scene.cameras import Camera
from stages.scene.scene import Scene

REFINERS = ("none", "sam")
#: What the vote rejected outright: a Gaussian the masks see whose share is below this.
REJECTED_SHARE = 0.1
#: A "not here" point is given when the rejected part inside the box covers at least this
#: share of the box's pixels (a sliver of background at the box's edge is no support).
REJECTED_PIXELS = 0.05
#: The suffix of a SAM mask's view name in the evidence (and the selection's record).
SAM_VIEW = "+sam"
#: After the first round, a view is asked again only when its sight of the answer changed by
#: more than this share of it (pixels gained or lost); otherwise it keeps its SAM mask.
RESHOWN = 0.02
#: A view's SAM mask weighs this much against its RES mask's 1 (see the module doc).
SAM_WEIGHT = 0.5
#: A view that shows fewer pixels of the answer than this is not asked: SAM given a box of a
#: few pixels outlines what it likes (the thin room's cup, 58 Gaussians: 13 pixels a view at
#: the median, and the refinement took half of it elsewhere; every view of the support set's
#: cup shows 660 or more).
LEAST_SIGHT = 64


@dataclass
class RepromptParams:
    """The lifted answer prompting SAM back (stages.query.reprompt)."""

    refine: Annotated[str, Choice(REFINERS)] = "none"
    """sam: re-segment every lifted view with SAM prompted from the lifted answer (the box of
    its projection, points deep inside it, a 'not here' point on what the vote rejected in that
    box), and vote SAM's masks beside the RES masks, again while the answer changes. Needs a
    --bundle with a SAM (beside --res-masks, or the RES bundle's own)."""
    refine_rounds: Annotated[int, Range(ge=1, le=10)] = 2
    """With --refine sam: at most this many rounds of re-prompting."""
    refine_settle: Annotated[float, Range(ge=0, le=1)] = 0.01
    """With --refine sam: the rounds stop once one changes fewer Gaussians than this share of
    the answer."""


def answer_masks(
    rast: Rasterizer, cam: Camera, selected: np.ndarray, rejected: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """[H, W] bool each: the answer and what the vote rejected, seen from `cam` (one walk)."""
    proj, bins = rast.prepare(cam)
    both = selection_masks(proj, bins, np.stack([selected, rejected], 1), cam.width, cam.height)
    return both[:, :, 0], both[:, :, 1]


def prompts_from(
    shown: np.ndarray, rejected_shown: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(points [P, 2], labels [P], box [4]) for SAM from the answer and the rejected part seen
    in a view (see the module doc); None when the view shows nothing of the answer."""
    height, width = shown.shape
    main = main_parts(shown, BOX_KEEP)
    tight = mask_box(main)
    if tight is None:
        return None
    box = expand_box(tight, TIGHT, width, height, 0.0)
    pos = interior_points(main, INTERIOR_POINTS)
    inside = box_pixels(box, width, height)
    out = rejected_shown & inside & ~shown
    neg = np.zeros((0, 2), np.int64)
    if out.sum() >= REJECTED_PIXELS * inside.sum():
        neg = interior_points(out, 1)
    points = np.concatenate([pos, neg]).astype(np.float64)
    labels = np.r_[np.ones(len(pos)), np.zeros(len(neg))]
    return points, labels, box


def sam_prompts(
    rast: Rasterizer, cam: Camera, selected: np.ndarray, rejected: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """prompts_from the 3D answer seen from `cam`."""
    return prompts_from(*answer_masks(rast, cam, selected, rejected))


def rejected_of(answer: LiftedAnswer) -> np.ndarray:
    """[G] bool: what the vote rejected outright (seen by the masks, a share below
    REJECTED_SHARE)."""
    lf = answer.lifted
    E = lf.S1 + lf.S0
    return lf.evident & ~lf.selected & (lf.S1 < REJECTED_SHARE * E)


def reprompt(
    answer: LiftedAnswer,
    rast: Rasterizer,
    sam: Sam,
    images: SamImages,
    cams: dict[str, Camera],
    revote: Callable[[list[ViewEvidence]], LiftedAnswer],
    p: RepromptParams,
    check: Callable[[], None] = lambda: None,
    report: Report = SILENT,
) -> tuple[LiftedAnswer, dict]:
    """The answer refined by SAM (see the module doc) and the record of its rounds. `revote`
    votes a list of evidence with the route's fusion (the RES masks' evidence is the answer's
    own, first); `cams` the training views by name."""
    res_evidence = [e for e in answer.evidence if not e.view.endswith(SAM_VIEW)]
    views = [cams[e.view] for e in res_evidence if e.view in cams]
    rounds: list[dict] = []
    # after the first round a view whose sight of the answer moved by at most RESHOWN of it
    # keeps its SAM mask: its prompt would move by a few pixels, and SAM's mask with it
    # (measured: the sofa's second round changed 10 Gaussians of 9,594)
    asked: dict[str, tuple[np.ndarray, ViewEvidence]] = {}
    t0 = time.perf_counter()
    for _ in range(p.refine_rounds):
        selected, rejected = answer.selected, rejected_of(answer)
        evidence: list[ViewEvidence] = []
        negatives = runs = 0
        for cam in report.progress(views, "refine", show=lambda c: c.name if c else None):
            check()
            shown, rejected_shown = answer_masks(rast, cam, selected, rejected)
            sight = int(shown.sum())
            if cam.name in asked:
                before, kept = asked[cam.name]
                if (shown ^ before).sum() <= RESHOWN * max(1, sight):
                    evidence.append(kept)
                    continue
            if sight < LEAST_SIGHT:
                continue  # too little of the answer there to prompt SAM with
            prompt = prompts_from(shown, rejected_shown)
            if prompt is None:
                continue
            points, labels, box = prompt
            if not sam.takes_points:  # boxes only: the box alone
                points, labels = points[:0], labels[:0]
            negatives += int((labels == 0).sum())
            runs += 1
            logits = sam.prompt_logits(images.embedding(cam), (cam.height, cam.width),
                                       points if len(points) else None,
                                       labels if len(points) else None, box)  # fmt: skip
            ev = view_evidence(rast, cam, logits > 0)
            evidence.append(ViewEvidence(cam.name + SAM_VIEW, ev.ids, SAM_WEIGHT * ev.s1,
                                         SAM_WEIGHT * ev.s0, ev.empty))  # fmt: skip
            asked[cam.name] = (shown, evidence[-1])
        if not evidence or (rounds and runs == 0):
            break  # nothing to ask, or every view kept its mask: the vote would not change
        new = revote([*res_evidence, *evidence])
        added = int((new.selected & ~selected).sum())
        removed = int((selected & ~new.selected).sum())
        rounds.append({"views": len(evidence), "asked": runs, "added": added,
                       "removed": removed, "not_here": negatives,
                       "gaussians": int(new.selected.sum())})  # fmt: skip
        answer = new
        if added + removed < p.refine_settle * max(1, int(selected.sum())):
            break
    record = {"by": "sam", "rounds": rounds, "seconds": round(time.perf_counter() - t0, 3)}
    return answer, record


def sam_reviser(
    p: RepromptParams,
    scene: Scene,
    rast: Rasterizer,
    bundle: Path | Bundle | None,
    source: object = None,
    images: SamImages | None = None,
    check: Callable[[], None] = lambda: None,
    report: Report = SILENT,
) -> Revise | None:
    """The `revise` of lift_prompt for --refine sam (None for --refine none): SAM from
    --bundle; the views' image embeddings from the RES source's index when it has one of this
    bundle (views it lacks are indexed), else `images`, else from the photos (kept for the
    run)."""
    if p.refine == "none":
        return None
    from stages.query.point_files import point_bundle
    from stages.query.pointing import IndexedEmbeddings, PhotoEmbeddings, sam_of

    try:
        b = point_bundle(bundle)
    except GoiError as e:
        raise GoiError(f"--refine sam: {e}") from None
    sam = sam_of(b)
    index = getattr(source, "index", None)
    if isinstance(index, GrowingIndex | ResIndex) and index.bundle_sha256 == b.digest():
        images = IndexedEmbeddings(index, sam)
    elif images is None:
        images = PhotoEmbeddings(scene, sam, report)
    cams = {c.name: c for c in scene.views("train")}
    if not rast.keeping:
        # a one-shot command: the lift and each round walk every view again (the answer seen
        # from it, SAM's mask lifted), each walk on the view's same projection
        rast.keep_views(KEEP_VIEWS_BYTES, cams.values())

    def revise(answer: LiftedAnswer, revote: Callable[[list[ViewEvidence]], LiftedAnswer]):  # noqa: ANN202
        return reprompt(answer, rast, sam, images, cams, revote, p, check, report)

    return revise

"""The lifted query of one prompt: which views, their RES masks lifted onto the Gaussians, the
OSH fitted on that evidence, the fused 3D selection, and masks rendered from it.

    answer = lift_prompt(renderer, train_cams, res_source, prompt, text, hp, lp)
    masks = lifted_masks(renderer.rast, answer.selected, cams)

Views: with mask files every file of the prompt is lifted by default (more views out-vote
per-view RES errors), or K of them with --res-views K; when a RES model has to run, K views
(8 by default) are chosen one at a time to cover the provisional selection from different sides
(`stages.query.views`), and the selection is updated after each, so the next view looks where
the answer still lacks evidence. The math is in `stages.query.lifting`.

Without a semantic field (`lift_prompt` given a bare Rasterizer: the field-free mode, the
training-free route of FlashSplat and Seed2GS) the vote alone decides: a Gaussian is in when its
own evidence says so, and one with less than `min_evidence` (which no view's evidence reaches)
stays out, since there is no codebook entry or OSH to decide it. No feature model, codebook or
fit-field is needed, and no text embedding: the RES masks carry the prompt.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from stages.core.errors import GoiError, warn
from stages.core.params import check_params
from stages.core.report import SILENT, Report
from stages.query.lifting import (
    DEFAULT_MODEL_VIEWS,
    Lifted,
    LiftParams,
    ViewEvidence,
    entry_counts,
    fuse,
)
from stages.query.osh import Hyperplane, HyperplaneParams, fit_osh, threshold_plane
from stages.query.res import ResFiles
from stages.query.views import COVER, next_view, provisional
from stages.render.lift import lift_mask, selection_mask
from stages.render.rasterizer import Rasterizer
from stages.scene.cameras import Camera
from stages.semantics.decode import SemanticRenderer
from stages.semantics.field import Field

#: partial(make, views done, views in all): see lift_prompt.
Partial = Callable[[Callable[[], "LiftedAnswer"], int, int], None]


class MaskSource(Protocol):
    """Where RES masks come from (stages.query.res): files, a model, or a stand-in for one.
    `every_view`: a mask costs little (a file, or the prompt side on an indexed view), so the
    lifted mode lifts every available view by default instead of choosing K."""

    source: str
    every_view: bool

    def available(self, cams: list[Camera]) -> list[Camera]: ...

    def mask(self, cam: Camera) -> np.ndarray: ...


@dataclass
class LiftedAnswer:
    lifted: Lifted
    plane: Hyperplane | None  # the OSH fitted on the lifted evidence (None without a field)
    evidence: list[ViewEvidence]
    chosen_by: str  # "all mask files", "K of the mask files", "coverage (RES model)"

    @property
    def selected(self) -> np.ndarray:
        return self.lifted.selected

    @property
    def views(self) -> list[str]:
        return [e.view for e in self.evidence]

    def record(self, lp: LiftParams) -> dict:
        """What the selection artifact and reports keep: views, how they were chosen, each
        view's evidence and confidence, and the parameters."""
        lf = self.lifted
        return {
            "views": self.views,
            "chosen_by": self.chosen_by,
            "params": lp.config(),
            "semantics": "field" if self.plane is not None else "none (field-free)",
            "per_view": [
                {**e.summary(), "confidence": lf.confidence[e.view]} for e in self.evidence
            ],
            "n_evident": int(lf.evident.sum()),
            "n_selected_by_masks": int((lf.selected & lf.evident).sum()),
            "n_selected_by_semantics": int((lf.selected & ~lf.evident).sum()),
            "fusion": lf.info,
        }


def view_evidence(rast: Rasterizer, cam: Camera, mask: np.ndarray) -> ViewEvidence:
    """One view's mask lifted onto the Gaussians (one tile walk at full resolution)."""
    proj, bins = rast.prepare(cam)
    s1, s0 = lift_mask(proj, bins, mask)
    return ViewEvidence.from_dense(cam.name, s1, s0)


def view_visibility(rast: Rasterizer, cam: Camera) -> np.ndarray:
    """[G] each Gaussian's blend weight in the view: the lift of an empty mask."""
    proj, bins = rast.prepare(cam)
    return lift_mask(proj, bins, np.zeros((cam.height, cam.width), bool))[1]


def fit_lifted_plane(
    lifted: Lifted,
    field: Field,
    entry: np.ndarray,
    prompt: str,
    text: np.ndarray,
    hp: HyperplaneParams,
) -> Hyperplane:
    """The OSH fitted on the Gaussians' lifted evidence (per entry: S1 and S0 of its Gaussians);
    the fixed-threshold plane when the masks claim nothing."""
    unit = field.unit_codebook().astype(np.float64)
    counts = entry_counts(lifted.S1, lifted.S0, entry, field.seen, unit.shape[0])
    if counts.pos.sum() <= 0:
        return threshold_plane(prompt, text, unit, hp.threshold)
    W, b, rec = fit_osh(counts, unit, text, hp)
    scores = (unit @ W + b).astype(np.float32)
    return Hyperplane(prompt, W.astype(np.float32), b, scores, text.astype(np.float32), rec)


def _answer(
    evidence: list[ViewEvidence],
    field: Field | None,
    entry: np.ndarray,
    prompt: str,
    text: np.ndarray | None,
    hp: HyperplaneParams,
    lp: LiftParams,
    chosen_by: str,
) -> LiftedAnswer:
    """Vote, fit the OSH on the vote's evidence, and decide with it (a second fuse: the plane
    only changes what unseen entries do, the votes are the same). Without a field the vote
    alone decides: no Gaussian is 'seen' by a field, so the ones below min_evidence are out."""
    if field is None or text is None:
        unseen = np.zeros(entry.shape, bool)
        lifted = fuse(evidence, entry, unseen, np.zeros(1, bool), lp)
        return LiftedAnswer(lifted, None, evidence, chosen_by)
    seen = field.seen
    text_plane = threshold_plane(prompt, text, field.unit_codebook(), hp.threshold)
    first = fuse(evidence, entry, seen, text_plane.positive, lp)
    plane = fit_lifted_plane(first, field, entry, prompt, text, hp)
    lifted = fuse(evidence, entry, seen, plane.positive, lp)
    return LiftedAnswer(lifted, plane, evidence, chosen_by)


def lift_prompt(
    renderer: SemanticRenderer | Rasterizer,
    train: list[Camera],
    source: MaskSource,
    prompt: str,
    text: np.ndarray | None,
    hp: HyperplaneParams,
    lp: LiftParams,
    visibility: Callable[[Camera], np.ndarray] | None = None,
    report: Report = SILENT,
    partial: Partial | None = None,
) -> LiftedAnswer:
    """The lifted answer of one prompt (see the module doc). A bare Rasterizer (and text None)
    gives the field-free answer. `visibility` may give a cached view_visibility (the eval shares
    it between prompts). `partial(make, done, total)` is called after each view is lifted;
    `make()` gives the answer of the views so far (a vote: the caller decides when it is worth
    it; `goi view` shows the answer refining)."""
    check_params(lp)
    if isinstance(renderer, Rasterizer):
        rast, field = renderer, None
    else:
        rast, field = renderer.rast, renderer.field
    if field is not None and text is None:
        raise GoiError("the lifted mode with a field needs the prompt's text embedding")
    if lp.res_views is not None and lp.res_views > len(train):
        raise GoiError(
            f"--res-views: {lp.res_views} is more than the scene's {len(train)} training views"
        )
    pool = source.available(train)
    if not pool:
        raise GoiError(
            f"--res-masks: {source.source} holds masks for none of the {len(train)} training "
            f"views (e.g. {train[0].name}.png): do the masks belong to this scene?"
        )
    if field is None:
        entry = np.zeros(
            rast.means.shape[0], np.int32
        )  # no codebook: one entry no Gaussian is seen in
    else:
        # [G] each Gaussian's codebook entry, by the renderer's kernel: field.decode_index would
        # build the [G, N] logits (360 MB for 300k Gaussians and 300 entries)
        assert isinstance(renderer, SemanticRenderer)
        entry = renderer.decode(field.features)
    files = isinstance(source, ResFiles)
    if source.every_view and lp.res_views is None:
        evidence: list[ViewEvidence] = []
        for c in report.progress(pool, "lift", show=_name):
            evidence.append(view_evidence(rast, c, source.mask(c)))
            if partial is not None:
                args = (list(evidence), field, entry, prompt, text, hp, lp, "so far")
                partial(functools.partial(_answer, *args), len(evidence), len(pool))
        everything = "all mask files" if files else f"every indexed view ({source.source})"
        lifted_all = _answer(evidence, field, entry, prompt, text, hp, lp, everything)
        return _found_nothing(lifted_all, source, prompt)
    k = lp.res_views or DEFAULT_MODEL_VIEWS
    if k > len(pool):
        warn(f"--res-views {k}: only {len(pool)} views have RES masks; lifting all of them")
        k = len(pool)
    vis_of = visibility or (lambda c: view_visibility(rast, c))
    vis = [vis_of(c) for c in report.progress(pool, "visibility", show=_name)]
    if field is None or text is None:
        # nothing to aim at before the first mask: the first view is the one that covers the
        # most of the scene, then the views cover the selection the masks build up
        S = np.ones(entry.shape, bool)
    else:
        unit = field.unit_codebook().astype(np.float64)
        S = provisional(unit @ text.astype(np.float64) - hp.threshold, entry, field.seen)
    E = np.zeros(entry.shape[0])
    left = list(range(len(pool)))
    chosen: list[ViewEvidence] = []
    chosen_by = "coverage (RES model)" if not files else f"coverage ({k} of the mask files)"
    answer = None
    for step in report.progress(range(k), "lift", length=k):
        j = left.pop(next_view([vis[i] for i in left], S, E, COVER))
        cam = pool[j]
        chosen.append(view_evidence(rast, cam, source.mask(cam)))
        E += vis[j]
        answer = _answer(chosen, field, entry, prompt, text, hp, lp, chosen_by)
        if answer.selected.any():
            S = answer.selected
        if partial is not None:
            partial(functools.partial(_given, answer), step + 1, k)
    assert answer is not None  # k >= 1
    return _found_nothing(answer, source, prompt)


def _given(answer: LiftedAnswer) -> LiftedAnswer:
    return answer


def _found_nothing(answer: LiftedAnswer, source: MaskSource, prompt: str) -> LiftedAnswer:
    """When every view's RES mask is empty (the detector found nothing anywhere), the answer is
    empty, with a warning: not an error, and not the field's guess from the text alone."""
    if any(not e.empty for e in answer.evidence):
        return answer
    warn(
        f"{source.source}: the RES found nothing for '{prompt}' on any of the "
        f"{len(answer.evidence)} views; the answer is empty"
    )
    answer.lifted.selected = np.zeros_like(answer.lifted.selected)
    return answer


def lifted_masks(
    rast: Rasterizer, selected: np.ndarray, cams: list[Camera]
) -> dict[str, np.ndarray]:
    """Each camera's mask rendered from the 3D selection (> half of the pixel's blend weight)."""
    out = {}
    for cam in cams:
        proj, bins = rast.prepare(cam)
        out[cam.name] = selection_mask(proj, bins, selected, cam.width, cam.height)
    return out


def _name(cam: Camera | None) -> str | None:
    return cam.name if cam else None

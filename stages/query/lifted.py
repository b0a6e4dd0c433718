"""The lifted query of one prompt: which views, their RES masks lifted onto the Gaussians, the
OSH fitted on that evidence, the fused 3D selection, and masks rendered from it.

    answer = lift_prompt(renderer, train_cams, res_source, prompt, text, hp, lp)
    masks = lifted_masks(renderer.rast, answer.selected, cams)

Views: with mask files every file of the prompt is lifted by default (more views out-vote
per-view RES errors), or K of them with --res-views K; when a RES model has to run, K views
(8 by default) are chosen one at a time to cover the provisional selection from different sides
(`stages.query.views`), and the selection is updated after each, so the next view looks where
the answer still lacks evidence. The math is in `stages.query.lifting`.
"""

from __future__ import annotations

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


class MaskSource(Protocol):
    """Where RES masks come from (stages.query.res): files, a model, or a stand-in for one."""

    source: str

    def available(self, cams: list[Camera]) -> list[Camera]: ...

    def mask(self, cam: Camera) -> np.ndarray: ...


@dataclass
class LiftedAnswer:
    lifted: Lifted
    plane: Hyperplane  # the OSH fitted on the lifted evidence (decides unseen entries)
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
    field: Field,
    entry: np.ndarray,
    prompt: str,
    text: np.ndarray,
    hp: HyperplaneParams,
    lp: LiftParams,
    chosen_by: str,
) -> LiftedAnswer:
    """Vote, fit the OSH on the vote's evidence, and decide with it (a second fuse: the plane
    only changes what unseen entries do, the votes are the same)."""
    seen = field.seen
    text_plane = threshold_plane(prompt, text, field.unit_codebook(), hp.threshold)
    first = fuse(evidence, entry, seen, text_plane.positive, lp)
    plane = fit_lifted_plane(first, field, entry, prompt, text, hp)
    lifted = fuse(evidence, entry, seen, plane.positive, lp)
    return LiftedAnswer(lifted, plane, evidence, chosen_by)


def lift_prompt(
    renderer: SemanticRenderer,
    train: list[Camera],
    source: MaskSource,
    prompt: str,
    text: np.ndarray,
    hp: HyperplaneParams,
    lp: LiftParams,
    visibility: Callable[[Camera], np.ndarray] | None = None,
    report: Report = SILENT,
) -> LiftedAnswer:
    """The lifted answer of one prompt (see the module doc). `visibility` may give a cached
    view_visibility (the eval shares it between prompts)."""
    check_params(lp)
    rast, field = renderer.rast, renderer.field
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
    # [G] each Gaussian's codebook entry, by the renderer's kernel: field.decode_index would
    # build the [G, N] logits (360 MB for 300k Gaussians and 300 entries)
    entry = renderer.decode(field.features)
    files = isinstance(source, ResFiles)
    if files and lp.res_views is None:
        evidence = [
            view_evidence(rast, c, source.mask(c))
            for c in report.progress(pool, "lift", show=_name)
        ]
        return _answer(evidence, field, entry, prompt, text, hp, lp, "all mask files")
    k = lp.res_views or DEFAULT_MODEL_VIEWS
    if k > len(pool):
        warn(f"--res-views {k}: only {len(pool)} views have RES masks; lifting all of them")
        k = len(pool)
    vis_of = visibility or (lambda c: view_visibility(rast, c))
    vis = [vis_of(c) for c in report.progress(pool, "visibility", show=_name)]
    unit = field.unit_codebook().astype(np.float64)
    S = provisional(unit @ text.astype(np.float64) - hp.threshold, entry, field.seen)
    E = np.zeros(entry.shape[0])
    left = list(range(len(pool)))
    chosen: list[ViewEvidence] = []
    chosen_by = "coverage (RES model)" if not files else f"coverage ({k} of the mask files)"
    answer = None
    for _ in report.progress(range(k), "lift", length=k):
        j = left.pop(next_view([vis[i] for i in left], S, E, COVER))
        cam = pool[j]
        chosen.append(view_evidence(rast, cam, source.mask(cam)))
        E += vis[j]
        answer = _answer(chosen, field, entry, prompt, text, hp, lp, chosen_by)
        if answer.selected.any():
            S = answer.selected
    assert answer is not None  # k >= 1
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

"""Orchestrates one prompt's lifted answer: which views, their RES masks lifted onto the
Gaussians, the OSH fitted on that evidence, the fused 3D selection, and masks rendered from it
(no files: `stages.query.lift_files` writes them).

    answer = lift_prompt(renderer, train_cams, res_source, prompt, text, hp, lp)
    masks = lifted_masks(renderer.rast, answer.selected, cams)

Views: with mask files every file of the prompt is lifted by default (more views out-vote
per-view RES errors), or K of them with --res-views K; when a RES model has to run, K views
(8 by default) are chosen one at a time to cover the provisional selection from different sides
(`stages.query.views`), and the selection is updated after each, so the next view looks where
the answer still lacks evidence. The math is in `stages.query.lift_math`.

On a RES index that grows (`--res-index` with its bundle, stages.query.res.ResGrowing) the
views the index holds are cheap and are lifted first; when the answer should rest on more
views than it holds (at least 8 by default, --res-views K, or `all`), the rest are chosen by
coverage, one at a time, from sides not yet seen (`stages.query.views.next_view_apart`), and
each is indexed as it is chosen, so the index grows by the views that serve the prompts
asked. With `RefineParams.progressive` the answer is handed to `on_answer` once the first
views are lifted and again after every further batch, so a caller rewrites it as it refines.

Every answer lift_prompt gives (not the previews `partial` gets) is cleaned unless
`LiftParams.clean` is off: its pieces far from its body are dropped unless the masks claim
them strongly in their own right (`stages.query.clean`), and `LiftedAnswer.cleaned` records
how many went and by which rule.

Without a semantic field (`lift_prompt` given a bare Rasterizer: the field-free mode, the
training-free route of FlashSplat and Seed2GS) the vote alone decides: a Gaussian is in when its
own evidence says so, and one with less than `min_evidence` (which no view's evidence reaches)
stays out, since there is no codebook entry or OSH to decide it. No feature model, codebook or
fit-field is needed, and no text embedding: the RES masks carry the prompt.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Annotated, Protocol

import numpy as np

from stages.core.errors import GoiError, warn
from stages.core.params import AT_LEAST_1, Range, check_params
from stages.core.report import SILENT, Report
from stages.query.clean import clean_selection
from stages.query.lift_math import (
    DEFAULT_MODEL_VIEWS,
    Lifted,
    LiftParams,
    ViewEvidence,
    entry_counts,
    fuse,
)
from stages.query.osh import Hyperplane, HyperplaneParams, fit_osh, threshold_plane
from stages.query.res import ResFiles
from stages.query.res_index import INDEX_WAIT_S, camera_distance
from stages.query.views import COVER, next_view, next_view_apart, provisional
from stages.render.lift import selection_mask
from stages.render.rasterizer import Rasterizer
from stages.scene.cameras import Camera
from stages.semantics.decode import SemanticRenderer
from stages.semantics.field import Field

#: partial(make, views done, views in all): see lift_prompt.
Partial = Callable[[Callable[[], "LiftedAnswer"], int, int], None]
#: on_answer(answer, views it rests on, views it refines to): see lift_prompt.
OnAnswer = Callable[["LiftedAnswer", int, int], object]
#: revise(answer, revote) -> (a better answer, its record): see lift_prompt (`revote` votes a
#: list of evidence with the answer's own fusion). stages.query.reprompt makes one.
Revise = Callable[
    ["LiftedAnswer", Callable[[list[ViewEvidence]], "LiftedAnswer"]], tuple["LiftedAnswer", dict]
]


@dataclass
class RefineParams:
    """A lifted query on a RES index that grows (--res-index): whether the answer is written
    as it refines."""

    progressive: bool = False
    """With --lift and --res-index: write the answer once the first views are lifted (the
    ones the index holds, at least --refine-every) and rewrite it, atomically and recording
    how many views it rests on, after each further --refine-every views are indexed, until
    --res-views (default with --progressive: every training view)."""
    refine_every: Annotated[int, AT_LEAST_1] = DEFAULT_MODEL_VIEWS
    """With --progressive: views indexed before the first answer, and between two answers."""
    index_wait: Annotated[float, Range(ge=0, le=86_400)] = INDEX_WAIT_S
    """With --res-index: seconds to wait while another goi process adds views to the same
    index before giving up (0: refuse at once)."""
    all_views: bool = False  # --res-views all: every training view (set by the CLI's option)

    def check(self, lift: bool) -> None:
        if not lift:
            if self.progressive:
                raise GoiError("--progressive: only with --lift (an option of the lifted mode)")
            if self.all_views:
                raise GoiError("--res-views: only with --lift (an option of the lifted mode)")


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
    refines_to: int | None = None  # on an index that grows: the views the answer refines to
    #: what cleaning did (stages.query.clean.clean_selection's record); None: not cleaned
    #: (--no-clean, or a preview while views are lifted)
    cleaned: dict | None = None
    #: what re-prompting SAM from the answer did (stages.query.reprompt); None: not asked
    revised: dict | None = None

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
            "clean": self.cleaned,
            **({"refine": self.revised} if self.revised is not None else {}),
            **(
                {
                    "refinement": {
                        "n_views": len(self.evidence),
                        "of": self.refines_to,
                        "final": len(self.evidence) >= self.refines_to,
                    }
                }
                if self.refines_to is not None
                else {}
            ),
        }


def view_evidence(rast: Rasterizer, cam: Camera, mask: np.ndarray) -> ViewEvidence:
    """One view's mask lifted onto the Gaussians (a tile walk at full resolution: of the tiles
    around the mask when the view's projection is kept, Rasterizer.lift)."""
    s1, s0 = rast.lift(cam, mask)
    return ViewEvidence.from_dense(cam.name, s1, s0)


def view_visibility(rast: Rasterizer, cam: Camera) -> np.ndarray:
    """[G] each Gaussian's blend weight in the view: the lift of an empty mask."""
    return rast.visibility(cam)


def fit_lifted_plane(
    lifted: Lifted,
    field: Field,
    entry: np.ndarray,
    prompt: str,
    text: np.ndarray,
    hp: HyperplaneParams,
) -> Hyperplane:
    """The OSH fitted on the Gaussians' lifted evidence (per entry: S1 and S0 of its Gaussians,
    S0 of the views whose mask answers); the fixed-threshold plane when the masks claim
    nothing."""
    unit = field.unit_codebook().astype(np.float64)
    S0 = lifted.S0 if lifted.S0_answering is None else lifted.S0_answering
    counts = entry_counts(lifted.S1, S0, entry, field.seen, unit.shape[0])
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
    fit: bool = True,
) -> LiftedAnswer:
    """Vote, fit the OSH on the vote's evidence, and decide with it (a second fuse: the plane
    only changes what unseen entries do, the votes are the same). Without a field the vote
    alone decides: no Gaussian is 'seen' by a field, so the ones below min_evidence are out.
    `fit` False gives a preview (the partial answers while views are lifted): the first fuse,
    the fixed-threshold plane deciding what no view reaches. The OSH's SGD costs ten times
    the vote (0.4 s on the dev room): fitted for every partial, it took half of goi view's
    lifted answer."""
    if field is None or text is None:
        unseen = np.zeros(entry.shape, bool)
        lifted = fuse(evidence, entry, unseen, np.zeros(1, bool), lp)
        return LiftedAnswer(lifted, None, evidence, chosen_by)
    seen = field.seen
    text_plane = threshold_plane(prompt, text, field.unit_codebook(), hp.threshold)
    first = fuse(evidence, entry, seen, text_plane.positive, lp)
    if not fit:
        return LiftedAnswer(first, text_plane, evidence, chosen_by)
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
    refine: RefineParams | None = None,
    on_answer: OnAnswer | None = None,
    revise: Revise | None = None,
) -> LiftedAnswer:
    """The lifted answer of one prompt (see the module doc). A bare Rasterizer (and text None)
    gives the field-free answer. `visibility` may give a cached view_visibility (the eval shares
    it between prompts). `partial(make, done, total)` is called after each view is lifted;
    `make()` gives the answer of the views so far (a preview when every view is lifted:
    `_answer`'s `fit`; the caller decides when it is worth it; `goi view` shows the answer
    refining). On an index that grows, with `refine.progressive`, `on_answer(answer, done,
    total)` gets each answer worth writing before the last (which is returned). `revise`
    (--refine sam) gets the final answer before it is cleaned, with the vote of the answer's
    own fusion, and returns a better one (stages.query.reprompt)."""
    check_params(lp)
    refine = refine or RefineParams()
    check_params(refine)
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
    grows = getattr(source, "grows", False)  # a RES index that grows (ResGrowing)
    pool = source.available(train)
    if not pool and not grows:
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
    if grows:
        if lp.res_views is not None:
            n = lp.res_views
        elif refine.all_views or refine.progressive:
            n = len(train)
        else:
            n = max(len(pool), min(DEFAULT_MODEL_VIEWS, len(train)))
        if n > len(pool):
            vis_of = visibility or (lambda c: view_visibility(rast, c))
            grown = _lift_growing(
                rast, field, entry, source, train, pool, prompt, text, hp, lp, n, refine,
                vis_of, report, partial, on_answer,
            )  # fmt: skip
            grown = _revised(grown, revise, field, entry, prompt, text, hp, lp)
            return _found_nothing(_cleaned(grown, lp, rast.means), source, prompt)
        # the index holds enough views: answered from them as from any index
    if source.every_view and lp.res_views is None:
        evidence: list[ViewEvidence] = []
        for c in report.progress(pool, "lift", show=_name):
            evidence.append(view_evidence(rast, c, source.mask(c)))
            if partial is not None:
                args = (list(evidence), field, entry, prompt, text, hp, lp, "so far")
                make = functools.partial(_answer, *args, fit=False)  # a preview
                partial(make, len(evidence), len(pool))
        everything = "all mask files" if files else f"every indexed view ({source.source})"
        lifted_all = _answer(evidence, field, entry, prompt, text, hp, lp, everything)
        lifted_all = _revised(lifted_all, revise, field, entry, prompt, text, hp, lp)
        return _found_nothing(_cleaned(lifted_all, lp, rast.means), source, prompt)
    k = lp.res_views or (len(pool) if refine.all_views else DEFAULT_MODEL_VIEWS)
    if k > len(pool):
        warn(f"--res-views {k}: only {len(pool)} views have RES masks; lifting all of them")
        k = len(pool)
    vis_of = visibility or (lambda c: view_visibility(rast, c))
    vis = [vis_of(c) for c in report.progress(pool, "visibility", show=_name)]
    S = _start(field, entry, text, hp)
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
    answer = _revised(answer, revise, field, entry, prompt, text, hp, lp)
    return _found_nothing(_cleaned(answer, lp, rast.means), source, prompt)


def _start(
    field: Field | None, entry: np.ndarray, text: np.ndarray | None, hp: HyperplaneParams
) -> np.ndarray:
    """[G] bool: what the coverage aims at before any mask: the field's fixed-threshold
    answer; without a field nothing, so the first view is the one that covers the most of
    the scene, then the views cover the selection the masks build up."""
    if field is None or text is None:
        return np.ones(entry.shape, bool)
    unit = field.unit_codebook().astype(np.float64)
    return provisional(unit @ text.astype(np.float64) - hp.threshold, entry, field.seen)


def _lift_growing(
    rast: Rasterizer,
    field: Field | None,
    entry: np.ndarray,
    source: MaskSource,
    train: list[Camera],
    held: list[Camera],
    prompt: str,
    text: np.ndarray | None,
    hp: HyperplaneParams,
    lp: LiftParams,
    n: int,
    refine: RefineParams,
    visibility: Callable[[Camera], np.ndarray],
    report: Report,
    partial: Partial | None,
    on_answer: OnAnswer | None,
) -> LiftedAnswer:
    """The answer on `n` views of an index that holds fewer (`held`): those first, then the
    views that best cover the selection, one at a time, each indexed as it is chosen (see the
    module doc). The first answer worth writing rests on the held views or
    `refine.refine_every` views, whichever are more; then one every `refine.refine_every`."""
    first = min(n, max(len(held), refine.refine_every)) if refine.progressive else n
    plan = getattr(source, "plan", None)
    if plan is not None:
        plan(n - len(held))
    added = f"{n - len(held)} indexed for it"
    chosen_by = (
        f"the {len(held)} indexed views, then coverage ({added})" if held
        else f"coverage (RES index, {added})"
    )  # fmt: skip
    evidence: list[ViewEvidence] = []
    E = np.zeros(entry.shape[0])
    answer = None

    def step() -> None:
        done = len(evidence)
        if partial is not None:
            partial(functools.partial(_given, answer), done, n)
        due = first <= done < n and (done - first) % refine.refine_every == 0
        if on_answer is not None and due:
            assert answer is not None
            final = _cleaned(answer, lp, rast.means)
            on_answer(_found_nothing(final, source, prompt, quiet=True), done, n)

    vis = {c.name: visibility(c) for c in report.progress(train, "visibility", show=_name)}
    S = _start(field, entry, text, hp)
    for c in report.progress(held, "lift", show=_name):
        evidence.append(view_evidence(rast, c, source.mask(c)))
        E += vis[c.name]
    if held:
        answer = _answer(list(evidence), field, entry, prompt, text, hp, lp, chosen_by)
        answer.refines_to = n
        if answer.selected.any():
            S = answer.selected
        step()
    names = {c.name for c in held}
    left = [c for c in train if c.name not in names]
    dist = camera_distance(train)  # [V, V]
    at = {c.name: i for i, c in enumerate(train)}
    lifted = [at[c.name] for c in held]
    for _ in report.progress(range(n - len(held)), "lift", length=n - len(held)):
        idx = [at[c.name] for c in left]
        apart = dist[np.ix_(idx, lifted)].min(1) if lifted else None
        cam = left.pop(next_view_apart([vis[c.name] for c in left], S, E, apart))
        lifted.append(at[cam.name])
        evidence.append(view_evidence(rast, cam, source.mask(cam)))  # indexes it
        E += vis[cam.name]
        answer = _answer(list(evidence), field, entry, prompt, text, hp, lp, chosen_by)
        answer.refines_to = n
        if answer.selected.any():
            S = answer.selected
        step()
    assert answer is not None  # n > len(held) >= 0
    return answer


def _given(answer: LiftedAnswer | None) -> LiftedAnswer:
    assert answer is not None
    return answer


def _revised(
    answer: LiftedAnswer,
    revise: Revise | None,
    field: Field | None,
    entry: np.ndarray,
    prompt: str,
    text: np.ndarray | None,
    hp: HyperplaneParams,
    lp: LiftParams,
) -> LiftedAnswer:
    """The answer `revise` makes better (--refine sam), voting with the answer's own fusion;
    the answer itself without one, or when every RES mask is empty (nothing to prompt from)."""
    if revise is None or not any(not e.empty for e in answer.evidence):
        return answer

    def revote(evidence: list[ViewEvidence]) -> LiftedAnswer:
        return _answer(evidence, field, entry, prompt, text, hp, lp, answer.chosen_by)

    better, record = revise(answer, revote)
    return dataclasses.replace(better, refines_to=answer.refines_to, revised=record)


def _cleaned(answer: LiftedAnswer, lp: LiftParams, means: np.ndarray) -> LiftedAnswer:
    """The answer without its pieces far from its body (stages.query.clean), recording what
    went, when `lp.clean`; a new answer, the one given is left as it is. means [G, 3]."""
    if not lp.clean:
        return answer
    kept, record = clean_selection(means, answer.selected, answer.lifted.S1)
    lifted = dataclasses.replace(answer.lifted, selected=kept)
    return dataclasses.replace(answer, lifted=lifted, cleaned=record)


def _found_nothing(
    answer: LiftedAnswer, source: MaskSource, prompt: str, quiet: bool = False
) -> LiftedAnswer:
    """When every view's RES mask is empty (the detector found nothing anywhere), the answer is
    empty, with a warning (`quiet`: none, for an answer still refining): not an error, and not
    the field's guess from the text alone."""
    if any(not e.empty for e in answer.evidence):
        return answer
    if quiet:
        answer.lifted.selected = np.zeros_like(answer.lifted.selected)
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


def rgb_and_selection(
    rast: Rasterizer, selected: np.ndarray, cam: Camera
) -> tuple[np.ndarray, np.ndarray]:
    """The RGB render [H, W, 3] and the selection's mask [H, W] bool at `cam` in one tile walk
    (the selection composited as a fourth colour channel): the same pixels as render_rgb and
    lifted_masks, which walk twice (the tests hold them equal)."""
    view = rast.view(cam)
    colors = rast.colors(cam, view.gaussians)  # [V, 3]
    sel = np.asarray(selected, np.float32)[view.gaussians][:, None]  # [V, 1]
    out = rast.render_view(cam, view, np.concatenate([colors, sel], axis=1))
    return out.image[:, :, :3], out.image[:, :, 3] > 0.5 * out.alpha


def _name(cam: Camera | None) -> str | None:
    return cam.name if cam else None

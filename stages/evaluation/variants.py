"""The paper's ablation variants, each a way to answer a prompt from a fitted field:

  full          TFCC field + hyperplane fitted on the RES masks
  without_osh   TFCC field + the fixed cosine threshold
  without_tfcc  field decoded straight to the feature space (no codebook) + hyperplane
  baseline      field decoded straight to the feature space + the fixed threshold

and goi's added mode (not in the paper):

  lifted        TFCC field + OSH + the RES masks of several views lifted onto the Gaussians
                (stages.query.lift_answer): every mask file of the prompt, or K views chosen by goi
                with the room's mask files standing in for a RES model; masks are rendered
                from the 3D selection
  lifted_fieldless  the same views' RES masks lifted, without any field (no features,
                codebook or fit-field): the vote alone decides and the Gaussians no view's
                evidence reaches stay out; measures what the field adds to lifted
  lifted_refined, lifted_fieldless_refined   the same, then SAM prompted back from the 3D
                answer in every lifted view (stages.query.reprompt, --refine sam): its masks
                voted beside the RES masks; needs a bundle with a SAM

The fixed threshold is goi's one documented default (stages.query.osh.THRESHOLD) for every
prompt and room; it is never tuned on test masks.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stages.core.errors import GoiError, warn
from stages.query.hyperplanes import HyperplaneRun, fit_hyperplane
from stages.query.lift_answer import (
    MaskSource,
    Revise,
    lift_prompt,
    lifted_masks,
    view_visibility,
)
from stages.query.lift_math import LiftParams, vote_share
from stages.query.masks import mask_of
from stages.query.osh import Counts, HyperplaneParams, fit_osh, probability, threshold_plane
from stages.query.prompts import Prompt
from stages.query.res import NothingFound, ResFiles, ResSource, choose_views
from stages.query.selection import plane_probability, select
from stages.render.rasterizer import KEEP_VIEWS_BYTES, Rasterizer
from stages.scene.cameras import Camera
from stages.scene.scene import Scene
from stages.semantics.decode import COVERED_ALPHA, DecodedView, SemanticRenderer
from stages.semantics.field import Field

VARIANTS = (
    "full",
    "without_osh",
    "without_tfcc",
    "baseline",
    "lifted",
    "lifted_fieldless",
    "lifted_refined",
    "lifted_fieldless_refined",
)
#: The variants goi eval runs unless --variants names others: the _refined ones need a SAM
#: (--bundle), which a room's eval has not by default.
DEFAULT_VARIANTS = tuple(v for v in VARIANTS if not v.endswith("_refined"))
#: The lifted variants; those ending in _refined prompt SAM back from the answer (--refine sam).
LIFTED = ("lifted", "lifted_fieldless", "lifted_refined", "lifted_fieldless_refined")
#: Which field each variant needs: "tfcc" (the paper's), "direct" (fit-field --no-tfcc) or
#: "none" (the field-free lifted mode).
FIELD_KIND = {
    "full": "tfcc",
    "without_osh": "tfcc",
    "without_tfcc": "direct",
    "baseline": "direct",
    "lifted": "tfcc",
    "lifted_fieldless": "none",
    "lifted_refined": "tfcc",
    "lifted_fieldless_refined": "none",
}
#: Pixels per fitting view the per-pixel (without-TFCC) hyperplane is fitted on.
DIRECT_FIT_PIXELS = 20_000


@dataclass
class Prediction:
    masks: dict[str, np.ndarray]  # test view -> [H, W] bool
    selected: np.ndarray  # [G] bool, the Gaussians of interest
    info: dict = field(default_factory=dict)  # how the answer was reached (fit record)
    # [G] float32 in [0, 1]: the answer as a continuous per-Gaussian score (the plane's
    # probability, or the lifted vote's share), for the protocols built on relevancy maps
    scores: np.ndarray | None = None


@dataclass
class DirectView:
    """A test or fitting view of a --no-tfcc field: rendered features, decoded per prompt."""

    f_hat: np.ndarray  # [M, S] covered pixels only
    covered: np.ndarray  # [H, W] bool

    def scores(self, field: Field, W: np.ndarray, b: float) -> np.ndarray:
        """[H, W] W x + b of each covered pixel's decoded feature (-inf elsewhere)."""
        out = np.full(self.covered.shape, -np.inf, np.float32)
        out[self.covered] = field.decode_direct(self.f_hat) @ W.astype(np.float32) + b
        return out


def render_direct(renderer: SemanticRenderer, cam: Camera) -> DirectView:
    r = renderer.rast.render_features(cam, renderer.field.features)
    covered = r.alpha > COVERED_ALPHA
    return DirectView(r.image[covered], covered)


def fit_direct_plane(
    renderer: SemanticRenderer,
    chosen: list[tuple[Camera, np.ndarray]],
    text: np.ndarray,
    p: HyperplaneParams,
    seed: int,
) -> tuple[np.ndarray, float, dict]:
    """The OSH on a field without codebook: every sampled pixel is its own point."""
    rng = np.random.default_rng(seed)
    xs, ys = [], []
    for cam, m in chosen:
        v = render_direct(renderer, cam)
        y = m[v.covered]
        take = rng.permutation(len(y))[:DIRECT_FIT_PIXELS]
        xs.append(renderer.field.decode_direct(v.f_hat[take]))
        ys.append(y[take])
    x, y = np.concatenate(xs), np.concatenate(ys)
    return fit_osh(Counts(y.astype(np.float64), (~y).astype(np.float64)), x, text, p)


def _fit_record(rec: dict, views: list[str]) -> dict:
    return {**{k: rec[k] for k in ("res_iou_init", "res_iou", "steps_run")}, "fit_views": views}


class RoomModel:
    """A room's RES mask files standing in for a RES model that goi runs on the views it
    chooses: every training view can be asked, and a view without a file answers with an empty
    mask (the room's RES tool writes no file where the targets cover < 0.5% of the view)."""

    def __init__(self, files: ResFiles):
        self.files = files
        self.source = f"{files.source} (as a RES model)"
        self.every_view = False

    def available(self, cams: list[Camera]) -> list[Camera]:
        return cams

    def mask(self, cam: Camera) -> np.ndarray:
        if (self.files.dir / f"{cam.name}.png").is_file():
            return self.files.mask(cam)
        return np.zeros((cam.height, cam.width), bool)


@dataclass
class Question:
    """One prompt as each variant is asked it: the prompt, its embedding, where its RES masks
    come from and the test views to answer on; with the run's training views and settings."""

    prompt: Prompt
    text: np.ndarray  # [D] the prompt's embedding
    source: ResSource
    views: list[str]  # the test views to answer on
    train: list[Camera]
    hp: HyperplaneParams
    lp: LiftParams
    planes: HyperplaneRun
    seed: int


def predict_lifted(
    renderer: SemanticRenderer | Rasterizer,
    visibility: Callable[[Camera], np.ndarray],
    test_cams: dict[str, Camera],
    q: Question,
    with_field: bool,
    entry: np.ndarray | None = None,
    revise: Revise | None = None,
) -> Prediction:
    """The lifted answer (with the field, or field-free from a bare Rasterizer) and its masks
    on the test views; `entry` [G]: the field's decoded entries, when known; `revise`: SAM
    prompted back from the answer (the _refined variants)."""
    source, lp = q.source, q.lp
    # mask files stand in for a model that answers on the views goi picks; a bundle's RES
    # model answers on them itself
    src: MaskSource = source
    if lp.res_views is not None and isinstance(source, ResFiles):
        src = RoomModel(source)
    text = q.text if with_field else None
    ans = lift_prompt(renderer, q.train, src, q.prompt.text, text, q.hp, lp, visibility,
                      revise=revise)  # fmt: skip
    rast = renderer if isinstance(renderer, Rasterizer) else renderer.rast
    masks = lifted_masks(rast, ans.selected, [test_cams[v] for v in q.views])
    rec = ans.record(lp)
    info = {
        "fit_views": rec["views"],
        "views_chosen_by": rec["chosen_by"],
        "view_confidence": {d["view"]: d["confidence"] for d in rec["per_view"]},
        "n_evident": rec["n_evident"],
        "fusion": rec["fusion"],
        "clean": rec["clean"],
        **({"refine": rec["refine"]} if "refine" in rec else {}),
    }
    fallback = None
    if ans.plane is not None and isinstance(renderer, SemanticRenderer):
        if entry is None:
            entry = renderer.decode(renderer.field.features)
        fallback = plane_probability(renderer.field, ans.plane, entry)
    return Prediction(masks, ans.selected, info, vote_share(ans.lifted, lp, fallback))


@dataclass
class VisibilityCache:
    """[G] blend weight per Gaussian in each training view, computed once for all prompts."""

    rast: Rasterizer
    views: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)  # train -> [G]

    def __call__(self, cam: Camera) -> np.ndarray:
        if cam.name not in self.views:
            self.views[cam.name] = view_visibility(self.rast, cam)
        return self.views[cam.name]


@dataclass
class TfccModel:
    """The paper's field, with the test views rendered and decoded once for every prompt."""

    field: Field
    path: Path
    renderer: SemanticRenderer
    views: dict[str, DecodedView]  # test view -> decoded render (with RGB, for the pages)
    cams: dict[str, Camera]  # test view -> camera
    visibility: VisibilityCache
    _entry: np.ndarray | None = None  # [G] each Gaussian's decoded entry, once for all prompts

    @property
    def entry(self) -> np.ndarray:
        if self._entry is None:  # the renderer's kernel: no [G, N] logits
            self._entry = self.renderer.decode(self.field.features)
        return self._entry

    def predict(self, variant: str, q: Question) -> Prediction:
        info: dict = {}
        views = q.views
        if variant == "full":
            try:
                plane, _ = fit_hyperplane(
                    self.renderer, self.path, q.train, q.prompt, q.text, "eval", q.source, q.hp,
                    q.planes,
                )  # fmt: skip
            except NothingFound as e:  # an empty answer, as goi query gives
                warn(f"{e}: the answer is empty")
                masks = {v: np.zeros(self.views[v].covered.shape, bool) for v in views}
                none = np.zeros(self.field.seen.shape, bool)
                return Prediction(masks, none, {"fit_views": []}, none.astype(np.float32))
            info = _fit_record(plane.info, json.loads(plane.info["views"]))
        else:
            plane = threshold_plane(
                q.prompt.text, q.text, self.field.unit_codebook(), q.hp.threshold
            )
        masks = {v: mask_of(plane, self.views[v]) for v in views}
        scores = plane_probability(self.field, plane, self.entry)
        return Prediction(masks, select(self.field, plane), info, scores)


@dataclass
class DirectModel:
    """The without-TFCC field: features decoded straight to the D-dim space."""

    field: Field
    renderer: SemanticRenderer
    views: dict[str, DirectView]  # test view -> rendered features
    gaussians: np.ndarray  # [G, D] each Gaussian's decoded unit feature

    def predict(self, variant: str, q: Question) -> Prediction:
        W, b, info = q.text.astype(np.float64), -q.hp.threshold, {}
        if variant == "without_tfcc":
            chosen = choose_views(q.source, q.train, q.hp)
            W, b, rec = fit_direct_plane(self.renderer, chosen, q.text, q.hp, q.seed)
            info = _fit_record(rec, [c.name for c, _ in chosen])
        masks = {v: self.views[v].scores(self.field, W, b) > 0 for v in q.views}
        z = self.gaussians @ W.astype(np.float32) + b  # [G]
        selected = self.field.seen & (z > 0)
        scores = np.where(self.field.seen, probability(z), 0.0).astype(np.float32)
        return Prediction(masks, selected, info, scores)


@dataclass
class Answerers:
    """What one scene's chosen variants answer with: the paper's field (TFCC) and the direct
    field (None where no chosen variant needs them), and for the lifted modes one rasterizer
    and one visibility cache (the field-free mode needs nothing else)."""

    tfcc: TfccModel | None
    direct: DirectModel | None
    rast: Rasterizer
    visibility: VisibilityCache
    cams: dict[str, Camera]  # test view -> camera
    #: the _refined variants' SAM, given the prompt's RES source (None: no SAM was given)
    refiner: Callable[[ResSource], Revise] | None = None

    @classmethod
    def of(
        cls,
        scene: Scene,
        tfcc: TfccModel | None,
        direct: DirectModel | None,
    ) -> Answerers:
        if tfcc is not None:
            rast, vis = tfcc.renderer.rast, tfcc.visibility
        else:
            rast = direct.renderer.rast if direct else Rasterizer.from_gaussians(scene.gaussians)
            vis = VisibilityCache(rast)
        test = scene.views("test")
        # every prompt lifts the same training views and renders the same test views
        rast.keep_views(KEEP_VIEWS_BYTES, [*scene.views("train"), *test])
        return cls(tfcc, direct, rast, vis, {c.name: c for c in test})

    def predict(self, variant: str, q: Question) -> Prediction:
        """The variant's answer to the question on its test views."""
        if variant in LIFTED:
            renderer: SemanticRenderer | Rasterizer = self.rast
            entry = None
            with_field = FIELD_KIND[variant] == "tfcc"
            if with_field:
                assert self.tfcc is not None
                renderer, entry = self.tfcc.renderer, self.tfcc.entry
            revise = None
            if variant.endswith("_refined"):
                if self.refiner is None:
                    raise GoiError(f"--variants {variant}: needs --bundle DIR with a SAM")
                revise = self.refiner(q.source)
            return predict_lifted(
                renderer, self.visibility, self.cams, q, with_field, entry, revise
            )
        if FIELD_KIND[variant] == "tfcc":
            assert self.tfcc is not None
            return self.tfcc.predict(variant, q)
        assert self.direct is not None
        return self.direct.predict(variant, q)

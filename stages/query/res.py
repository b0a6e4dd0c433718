"""RES masks: where a prompt's 2D referring-expression masks come from, and which views to use.

A source is either mask files made by any external tool (`ResFiles`) or a bundle's RES (a
single model, or a Grounded-SAM pipeline) run on goi's own rendering of a view (`ResModel`).
Both answer `available(cams)` (views it can give a mask for), `mask(cam)` ([H, W] bool) and
`digest(cams)` (changes when any mask would). The masks a model made for a fit are written
beside the fit's outputs (`write_res_masks`).
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from stages.core.artifacts import sha256_file, write_png
from stages.core.errors import GoiError, warn
from stages.core.files import make_dir
from stages.core.report import SILENT, Report
from stages.models.bundle import Bundle, load_bundle
from stages.query.osh import HyperplaneParams
from stages.query.prompts import Prompt, check_plain_name, view_file_name
from stages.query.res_index import (
    INDEX_WAIT_S,
    GrowingIndex,
    ResIndex,
    check_res_index,
    indexable_bundle,
    load_res_index,
)
from stages.render.rasterizer import Rasterizer
from stages.scene.cameras import Camera
from stages.scene.images import read_mask
from stages.scene.scene import Scene


class NothingFound(GoiError):
    """Every RES mask of the prompt is empty (the detector found nothing): a query answers
    with an empty selection and a warning; fitting a plane alone is refused."""


class ResFiles:
    """RES masks made by any external tool: DIR/<view>.png (a prompt's own directory)."""

    every_view = True  # a file costs nothing: the lifted mode lifts them all by default

    def __init__(self, root: Path, prompt: Prompt, index: GrowingIndex | None = None):
        #: the SAM bundle's index that --refine sam takes its image side from (and grows)
        self.index = index
        root = Path(root)
        prompt_id = prompt.id
        if prompt_id is not None:
            check_plain_name(prompt_id, "--prompt-id", "a subdirectory of --res-masks")
        if not root.is_dir():
            raise GoiError(f"--res-masks: {root} is not a directory")
        candidates = [root / prompt_id] if prompt_id else [root / prompt.name, root]
        for c in candidates:
            if c.is_dir() and any(c.glob("*.png")):
                self.dir = c
                break
        else:
            raise GoiError(
                f"--res-masks: no <view>.png masks in {candidates[0]}"
                + ("" if prompt_id else f" nor {root}; pass --prompt-id to name the subdirectory")
            )
        self.source = f"files:{self.dir}"

    def available(self, cams: list[Camera]) -> list[Camera]:
        return [c for c in cams if (self.dir / f"{c.name}.png").is_file()]

    def mask(self, cam: Camera) -> np.ndarray:
        import cv2

        path = self.dir / f"{cam.name}.png"
        if not path.is_file():
            raise GoiError(f"--res-masks: no mask {path} for view '{cam.name}'")
        m = read_mask(path)
        if m.shape != (cam.height, cam.width):
            warn(
                f"{path}: mask is {m.shape[1]}x{m.shape[0]}, the view {cam.width}x{cam.height}; "
                "resized (nearest)"
            )
            m = cv2.resize(
                m.astype(np.uint8), (cam.width, cam.height), interpolation=cv2.INTER_NEAREST
            ).astype(bool)
        return m

    def digest(self, cams: list[Camera]) -> str:
        h = hashlib.sha256()
        for c in cams:
            h.update(c.name.encode() + sha256_file(self.dir / f"{c.name}.png").encode())
        return h.hexdigest()


class ResModel:
    """RES masks from a bundle's RES (a single model such as CLIPSeg, or a Grounded-SAM
    pipeline), run on the RGB goi renders at each view. Each view's mask is computed once;
    `computed` keeps them, so the masks a fit used can be written beside its outputs."""

    every_view = False  # seconds per view: the lifted mode chooses K views

    def __init__(self, bundle_dir: Path | Bundle, prompt: str, rast: Rasterizer):
        # a loaded Bundle lets several prompts share one set of sessions (goi eval)
        self.bundle = bundle_dir if isinstance(bundle_dir, Bundle) else load_bundle(bundle_dir)
        if not self.bundle.has_res:
            raise GoiError(
                f"{bundle_dir}: the bundle has no RES ('res' or 'grounded'); pass --res-masks "
                "DIR instead"
            )
        self.prompt = prompt
        self.rast = rast
        self.source = f"bundle:{self.bundle.name}"
        self.computed: dict[str, np.ndarray] = {}

    def available(self, cams: list[Camera]) -> list[Camera]:
        return cams

    def mask(self, cam: Camera) -> np.ndarray:
        if cam.name not in self.computed:
            self.bundle.check_res()  # every model opened and checked before any work
            rgb = self.rast.render_rgb(cam).image
            rgb8 = (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
            self.computed[cam.name] = self.bundle.segment(rgb8, self.prompt)
        return self.computed[cam.name]

    def digest(self, cams: list[Camera]) -> str:
        return hashlib.sha256(
            (self.bundle.digest() + ",".join(c.name for c in cams)).encode()
        ).hexdigest()


class ResIndexed:
    """RES masks from a bundle's prompt side on a RES index (stages.query.res_index): the
    prompt is encoded once, then each view costs the prompt side alone (a dot product and SAM's
    decoder) on the image side stored for the scene's photo. Cheap, so the lifted mode lifts
    every indexed view by default. Masks are kept in `computed`, like ResModel's."""

    every_view = True

    def __init__(self, index: ResIndex | GrowingIndex, bundle: Bundle, prompt: str, scene: Scene):
        self.index = index
        self.bundle = bundle
        self.prompt = prompt
        self.scene = scene
        self.source = f"index:{index.path} ({bundle.name})"
        self.computed: dict[str, np.ndarray] = {}
        self._prompt = bundle.res_prompt(prompt)  # the text side, once per prompt

    def available(self, cams: list[Camera]) -> list[Camera]:
        return [c for c in cams if c.name in self.index.views]

    def mask(self, cam: Camera) -> np.ndarray:
        if cam.name not in self.computed:
            # only OWLv2 + SAM answers from the image side alone; Grounding DINO meets the text
            # early, so its bundles (and a RES exported whole) also need the photo itself
            photo = self.bundle.res_kind != "owl_sam"
            rgb = self.scene.load_image(cam) if photo else None
            side = self.index.image_side(cam.name)
            g = self.bundle.res_from_image_side(side, (cam.height, cam.width), self._prompt, rgb)
            self.computed[cam.name] = g.mask
        return self.computed[cam.name]

    def digest(self, cams: list[Camera]) -> str:
        return hashlib.sha256(
            (
                self.index.bundle_sha256
                + self.prompt
                + ",".join(f"{c.name}:{self.index.views.get(c.name, '')}" for c in cams)
            ).encode()
        ).hexdigest()


class ResGrowing(ResIndexed):
    """RES masks from an index that grows as they are asked for (a lifted query's --res-index,
    stages.query.res_index.GrowingIndex): `available` are the views the index holds, which
    cost the prompt side; `mask` of any other training view first indexes it (the bundle's
    image side on its photo, kept in the index), and it costs the same from then on. The
    lifted route decides which views to add (stages.query.lift_answer)."""

    grows = True

    def __init__(self, index: GrowingIndex, bundle: Bundle, prompt: str, scene: Scene):
        super().__init__(index, bundle, prompt, scene)
        self.growing = index

    def mask(self, cam: Camera) -> np.ndarray:
        if cam.name not in self.growing.views:
            self.growing.add(cam)
        return super().mask(cam)

    def plan(self, n: int) -> None:
        """About `n` views are to be indexed (the progress lines' time left)."""
        self.growing.plan(n)

    def close(self) -> None:
        """Publish the views indexed so far (the next prompts read them)."""
        self.growing.close()


def growing_index(
    path: Path,
    bundle: Path | Bundle | None,
    scene: Scene,
    report: Report = SILENT,
    wait: float = INDEX_WAIT_S,
) -> GrowingIndex:
    """--res-index FILE of a lifted query, with its --bundle: checked against the scene like
    any index (bundle, scene, image set, arrays and values) but free to lack views, or not to
    exist yet: the query indexes the views it needs."""
    if bundle is None:
        raise GoiError(
            "--res-index needs --bundle DIR: the bundle the index was made with runs the "
            "prompt side"
        )
    return GrowingIndex(path, scene, indexable_bundle(bundle), report, wait)


def checked_index(
    path: Path, bundle: Path | Bundle | None, scene: Scene
) -> tuple[ResIndex, Bundle]:
    """--res-index and its --bundle, checked against the scene's training views (bundle,
    scene, image set, missing views) before any work."""
    if bundle is None:
        raise GoiError(
            "--res-index needs --bundle DIR: the bundle the index was made with runs the "
            "prompt side"
        )
    b = indexable_bundle(bundle)
    index = load_res_index(path)
    check_res_index(index, scene, b, scene.views("train"))
    return index, b


def open_res_index(
    path: Path, bundle: Path | Bundle | None, scene: Scene, prompt: str
) -> ResIndexed:
    """The prompt's masks from a checked --res-index (see checked_index)."""
    index, b = checked_index(path, bundle, scene)
    return ResIndexed(index, b, prompt, scene)


ResSource = ResFiles | ResModel | ResIndexed


def write_res_masks(source: ResSource, views: list[str], directory: Path) -> list[Path]:
    """The masks a RES model made for `views`, as directory/<view>.png (0/255), so the user can
    see what a plane was fitted on. Mask files given with --res-masks are not copied."""
    if not isinstance(source, ResModel | ResIndexed):
        return []
    make_dir(directory, "--out")
    written = []
    for view in views:
        path = directory / f"{view_file_name(view)}.png"
        write_png(path, source.computed[view].astype(np.uint8) * 255, force=True)
        written.append(path)
    return written


def res_source(
    res_masks: Path | None,
    bundle: Path | None,
    prompt: Prompt,
    rast: Rasterizer,
    res_index: Path | None = None,
    scene: Scene | None = None,
    grow: GrowingIndex | None = None,
) -> ResSource:
    """Mask files when given, else the bundle's prompt side on a RES index (with the scene;
    `grow`: the lifted route's, opened by growing_index, which may add views), else the
    bundle's RES model (run on rast's renderings); one of them is needed."""
    if res_masks is not None and res_index is not None and grow is None:
        raise GoiError(
            "give one of --res-masks DIR or --res-index FILE, not both (both only with "
            "--lift --refine sam: the index then keeps SAM's image side for the refinement)"
        )
    if res_masks is not None:
        return ResFiles(res_masks, prompt, grow)
    if res_index is not None:
        assert scene is not None
        if grow is not None:
            return ResGrowing(grow, grow.bundle, prompt.text, scene)
        return open_res_index(res_index, bundle, scene, prompt.text)
    if bundle is not None:
        return ResModel(bundle, prompt.text, rast)
    raise GoiError(
        "fitting a hyperplane needs RES masks: --res-masks DIR, or --bundle DIR with a RES "
        "(res or grounded; or use --mode threshold where there is one)"
    )


def choose_views(
    source: ResSource, cams: list[Camera], p: HyperplaneParams
) -> list[tuple[Camera, np.ndarray]]:
    """The fitting views and their RES masks: named ones, or the largest non-empty masks."""
    by_name = {c.name: c for c in cams}
    if p.fit_on:
        chosen = []
        for name in [v.strip() for v in p.fit_on.split(",") if v.strip()]:
            if name not in by_name:
                raise GoiError(f"--fit-on: the scene has no training view '{name}'")
            if not source.available([by_name[name]]):
                raise GoiError(f"--fit-on: view '{name}' has no RES mask ({source.source})")
            m = source.mask(by_name[name])
            if not m.any():
                raise GoiError(
                    f"--fit-on: the RES mask of view '{name}' is empty ({source.source})"
                )
            chosen.append((by_name[name], m))
        if not chosen:
            raise GoiError("--fit-on: no view named")
        return chosen
    if p.fit_views < 1:
        raise GoiError("--fit-views must be at least 1")
    pool = source.available(cams)
    if not pool:
        names = ", ".join(c.name for c in cams[:3]) + (", ..." if len(cams) > 3 else "")
        raise GoiError(
            f"--res-masks: {source.source.removeprefix('files:')} has no mask for any training "
            f"view (<view>.png for {names})"
        )
    if isinstance(source, ResModel):  # (an index costs little: every view is tried)
        # a model costs a run per view: try evenly spaced views until enough are non-empty
        step = max(1, len(pool) // (3 * p.fit_views))
        pool = pool[::step][: 3 * p.fit_views]
    masks = [(c, source.mask(c)) for c in pool]
    masks = [(c, m) for c, m in masks if m.any()]
    if not masks:
        raise NothingFound(
            f"{source.source}: every RES mask of this prompt is empty; nothing to fit"
        )
    masks.sort(key=lambda cm: (-int(cm[1].sum()), cm[0].name))
    return masks[: p.fit_views]

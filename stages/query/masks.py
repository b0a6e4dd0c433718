"""`goi render-mask`: a prompt's binary mask and an overlay at any camera.

hyperplane mode decides per pixel with the fitted plane (W' x + b' > 0); threshold mode with the
fixed cosine threshold on the prompt's embedding (the baseline). Both are lookups of the pixel's
decoded codebook entry, so a mask costs one render of the field (and the RGB rides along).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import numpy as np

from stages.core.artifacts import write_png
from stages.core.errors import GoiError, check_choice
from stages.core.files import (
    check_output_file,
    check_output_name,
    file_in_the_way,
    make_dir,
    refuse_inputs,
)
from stages.core.params import COSINE, Choice, check_params, name_list
from stages.core.report import SILENT, Report
from stages.query.osh import THRESHOLD, Hyperplane, threshold_plane
from stages.query.prompts import view_file_name
from stages.scene.cameras import Camera
from stages.scene.scene import Scene
from stages.semantics.decode import DecodedView, SemanticRenderer
from stages.semantics.field import Field

MODES = ("hyperplane", "threshold")
HIGHLIGHT = np.array([1.0, 0.15, 0.1], np.float32)


@dataclass
class MaskParams:
    mode: Annotated[str, Choice(MODES)] = "hyperplane"
    """hyperplane: the fitted OSH; threshold: the fixed cosine threshold (the baseline)."""
    threshold: Annotated[float, COSINE] = THRESHOLD
    """Cosine threshold of threshold mode."""


@dataclass
class MaskRun:
    out: Path
    """Directory for <view>.png (0/255 mask) and <view>.overlay.png."""
    views: str | None = None
    """Comma-separated views to render (default: the test split, else every camera)."""
    no_overlay: bool = False
    """Write only the masks, not the overlays on the rendered RGB."""
    force: bool = False
    """Overwrite existing mask files."""


def plane_for(plane: Hyperplane, mode: str, field: Field, threshold: float) -> Hyperplane:
    """The fitted plane (hyperplane mode), or the fixed-threshold plane of its prompt."""
    if check_choice("--mode", mode, MODES) == "threshold":
        return threshold_plane(plane.prompt, plane.text, field.unit_codebook(), threshold)
    return plane


def mask_of(plane: Hyperplane, view: DecodedView) -> np.ndarray:
    """[H, W] bool: covered pixels whose decoded entry is on the positive side."""
    return plane.positive[view.index] & view.covered


def overlay(
    rgb: np.ndarray,
    mask: np.ndarray,
    outline: np.ndarray | None = None,
    outline_color: tuple[int, int, int] = (255, 255, 255),
    width: int = 1,
) -> np.ndarray:
    """RGB (0..1 floats or uint8) with `mask` tinted red and `outline` (default: the mask)
    outlined: [H, W, 3] uint8."""
    import cv2

    out = rgb.astype(np.float32)
    if rgb.dtype == np.uint8:
        out /= 255
    out[mask] = 0.45 * out[mask] + 0.55 * HIGHLIGHT
    img = (np.clip(out, 0, 1) * 255 + 0.5).astype(np.uint8)
    edge = mask if outline is None else outline
    contours, _ = cv2.findContours(edge.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(img, contours, -1, outline_color, width)
    return img


def default_cameras(scene: Scene, views: str | None) -> list[Camera]:
    """--views of the scene, else its test split, else all its cameras."""
    return pick_cameras(scene.by_name, scene.views("test") or scene.cameras, views)


def pick_cameras(cams: dict[str, Camera], default: list[Camera], views: str | None) -> list[Camera]:
    """The cameras --views names (checked), else `default`."""
    if views is None:
        return default
    out = []
    for name in name_list(views, "--views"):
        if name not in cams:
            raise GoiError(f"--views: no camera named '{name}'")
        out.append(cams[name])
    return out


def mask_files(out: Path, cams: list[Camera], overlays: bool) -> list[Path]:
    """The files render_masks writes for `cams`: <view>.png, and <view>.overlay.png."""
    stems = [view_file_name(c.name) for c in cams]
    return [
        out / f"{s}{ext}"
        for s in stems
        for ext in ((".png", ".overlay.png") if overlays else (".png",))
    ]


def check_mask_outputs(
    out: Path, cams: list[Camera], overlays: bool, force: bool, inputs: Iterable[Path | None] = ()
) -> list[Path]:
    """Every file render_masks would write, checked before the first render (all or nothing):
    names the file system takes, no directory or file in the way, none of `inputs`, and
    without `force` none there yet."""
    files = mask_files(out, cams, overlays)
    check_output_name(out, "--out")
    blocker = file_in_the_way(out)
    if blocker is not None:
        raise GoiError(f"--out: {out}: {blocker} is a file, not a directory")
    for f in files:
        check_output_file(f, "--out")
    refuse_inputs({"--out": files}, inputs)
    if not force:
        existing = [f for f in files if f.exists() or f.is_symlink()]
        if existing:
            raise GoiError(f"{existing[0]}: already exists; pass --force to overwrite it")
    return files


def render_masks(
    renderer: SemanticRenderer,
    plane: Hyperplane,
    cams: list[Camera],
    p: MaskParams,
    run: MaskRun,
    report: Report = SILENT,
) -> list[Path]:
    """Write the masks (and overlays) of `cams`; returns the mask paths."""
    check_params(p)
    plane = plane_for(plane, p.mode, renderer.field, p.threshold)
    out = Path(run.out)
    check_mask_outputs(out, cams, not run.no_overlay, run.force)
    make_dir(out, "--out")
    written = []
    for cam in report.progress(cams, "render-mask", show=lambda c: c.name if c else None):
        view = renderer.render(cam, with_rgb=not run.no_overlay)
        m = mask_of(plane, view)
        stem = view_file_name(cam.name)
        write_png(out / f"{stem}.png", m.astype(np.uint8) * 255, run.force)
        if view.rgb is not None:
            write_png(out / f"{stem}.overlay.png", overlay(view.rgb, m), run.force)
        written.append(out / f"{stem}.png")
    return written

"""The lifted mode's files, for the CLI and the viewer: `goi query --lift` (and select /
render-mask / fit-hyperplane with --lift) writes a prompt's lifted answer as the paper's mode
writes its own: masks (rendered from the 3D selection) with overlays, the selection artifact
(recording the views and evidence used), the PLY.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np

from stages.core.artifacts import input_digest, write_png
from stages.core.errors import GoiError, GoiWarning
from stages.core.files import make_dir
from stages.core.report import SILENT, Report
from stages.query.lift_answer import (
    LiftedAnswer,
    MaskSource,
    OnAnswer,
    Partial,
    RefineParams,
    Revise,
    lift_prompt,
    lifted_masks,
    rgb_and_selection,
)
from stages.query.lift_math import LiftParams
from stages.query.masks import overlay
from stages.query.osh import HyperplaneParams
from stages.query.prompts import view_file_name
from stages.query.selection import write_selection
from stages.render.rasterizer import Rasterizer
from stages.scene.cameras import Camera
from stages.scene.scene import Scene
from stages.semantics.decode import SemanticRenderer


def answer_prompt(
    scene: Scene,
    renderer: SemanticRenderer | Rasterizer,
    prompt: str,
    text: np.ndarray | None,
    source: MaskSource,
    hp: HyperplaneParams,
    lp: LiftParams,
    report: Report = SILENT,
    need_positive: bool = False,
    partial: Partial | None = None,
    refine: RefineParams | None = None,
    on_answer: OnAnswer | None = None,
    revise: Revise | None = None,
) -> LiftedAnswer:
    """The lifted answer; with `need_positive` (a plane is to be stored from it) refused when
    no lifted mask has a positive pixel. `partial`, `refine`, `on_answer`, `revise`: see
    lift_prompt."""
    with warnings.catch_warnings():
        if need_positive:  # an empty answer is refused below: its warning would say it twice
            warnings.simplefilter("ignore", GoiWarning)
        ans = lift_prompt(
            renderer,
            scene.views("train"),
            source,
            prompt,
            text,
            hp,
            lp,
            report=report,
            partial=partial,
            refine=refine,
            on_answer=on_answer,
            revise=revise,
        )
    if need_positive:
        require_positive_evidence(ans, source.source)
    rec = ans.record(lp)
    by_field = (
        f", {rec['n_selected_by_semantics']} by the field"
        if ans.plane is not None
        else " (field-free: the Gaussians no view's evidence reaches are out)"
    )
    report.log(
        f"lifted {len(rec['views'])} views ({rec['chosen_by']}): {int(ans.selected.sum())} "
        f"Gaussians, {rec['n_selected_by_masks']} decided by the masks{by_field}"
    )
    return ans


def require_positive_evidence(ans: LiftedAnswer, source: object) -> None:
    """A plane is stored only from evidence with a positive pixel: lifted masks that are all
    empty say where the prompt is not, never where it is, so a plane fitted on them alone
    would be the text's guess presented as a fit."""
    if not any(not e.empty for e in ans.evidence):
        raise GoiError(
            f"{source}: the RES masks of the {len(ans.evidence)} lifted views "
            f"({', '.join(ans.views[:4])}{', ...' if len(ans.views) > 4 else ''}) are all "
            "empty: no pixel shows the prompt, so there is no plane to fit"
        )


def write_masks(
    rast: Rasterizer,
    selected: np.ndarray,
    cams: list[Camera],
    out: Path,
    overlays: bool,
    force: bool,
    report: Report = SILENT,
) -> list[Path]:
    """<view>.png masks rendered from the 3D selection (and overlays on the rendered RGB)."""
    make_dir(out, "--out")
    written = []
    for cam in report.progress(cams, "render-mask", show=lambda c: c.name if c else None):
        if overlays:  # the RGB and the mask in one tile walk
            rgb, m = rgb_and_selection(rast, selected, cam)
        else:
            m = lifted_masks(rast, selected, [cam])[cam.name]
        stem = view_file_name(cam.name)
        write_png(out / f"{stem}.png", m.astype(np.uint8) * 255, force)
        if overlays:
            write_png(out / f"{stem}.overlay.png", overlay(rgb, m), force)
        written.append(out / f"{stem}.png")
    return written


def write_lifted_selection(
    path: Path,
    ans: LiftedAnswer,
    scene: Scene,
    field_path: Path | None,
    lp: LiftParams,
    force: bool,
    prompt: str,
) -> Path:
    """The selection artifact of a lifted answer: the views and evidence go with it (and the
    field's digest and the OSH's fit record, when a field took part)."""
    inputs = {"ply": scene.ply_digest()}
    record = ans.record(lp)
    if field_path is not None:
        inputs.update(input_digest("field", field_path))
    if ans.plane is not None:
        record["plane"] = json.loads(json.dumps(ans.plane.info, default=float))
    return write_selection(
        path,
        ans.selected,
        prompt,
        "lifted",
        scene.ply_digest(),
        inputs,
        force,
        lifted=record,
        evidence=(ans.lifted.S1, ans.lifted.S0),
    )

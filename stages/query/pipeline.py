"""`goi query --prompt TEXT`: fit the hyperplane unless cached, render masks, select, export.

The output directory holds hyperplanes.h5, the prompt cache shared by every query on the same
field, and one directory per prompt (a safe name of it): masks/, selection.h5, <name>.ply, and
res/ with the RES masks the fit used when a bundle's RES model made them.
A query overwrites its own prompt's outputs, so re-running it is always safe.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import numpy as np

from stages.core.artifacts import input_digest
from stages.core.errors import GoiError, warn
from stages.core.files import check_output_file, make_dir, refuse_inputs
from stages.core.params import Choice, check_params
from stages.core.report import SILENT, Report
from stages.query.export_ply import PlyEditParams, PlyExportRun, export_ply, parse_color
from stages.query.hyperplanes import HyperplaneRun, fit_hyperplane, res_masks_dir, wrote_res_masks
from stages.query.lift_answer import LiftedAnswer, RefineParams
from stages.query.lift_math import LiftParams
from stages.query.masks import (
    MODES,
    MaskParams,
    MaskRun,
    check_mask_outputs,
    default_cameras,
    render_masks,
)
from stages.query.osh import HyperplaneParams, threshold_plane
from stages.query.point_files import Points, open_pointer, write_pointed_selection
from stages.query.prompts import Prompt, text_embedding
from stages.query.reprompt import RepromptParams, sam_reviser
from stages.query.res import NothingFound, res_source
from stages.query.res_index import GrowingIndex
from stages.query.selection import Selection, select, write_selection
from stages.render.rasterizer import KEEP_VIEWS_BYTES, Rasterizer
from stages.scene.cameras import Camera
from stages.scene.scene import Scene
from stages.semantics.decode import SemanticRenderer
from stages.semantics.field import load_field_for

EXPORTS = ("subset", "invert", "highlight", "none")


@dataclass
class PromptSources:
    """Where a prompt's embedding and RES masks come from."""

    text_embeddings: Path | None = None
    """JSON {text: [floats]} with the prompt's embedding (e.g. a room's text_embeddings.json)."""
    bundle: Path | None = None
    """Model bundle whose text encoder embeds the prompt (unless --text-embeddings lists it) and
    whose RES, if any (a single model such as CLIPSeg, or Grounded-SAM), makes the RES masks
    (unless --res-masks is given); the masks it made are written to OUT/<prompt>/res/."""
    res_masks: Path | None = None
    """RES masks from any tool: DIR/<view>.png, or DIR/<prompt id>/<view>.png with --prompt-id
    (default subdirectory: the prompt's safe name)."""
    prompt_id: str | None = None
    """Subdirectory of --res-masks holding this prompt's masks."""
    # (the command puts --prompt-id into its Prompt; the stages read Prompt.id)
    res_index: Path | None = None
    """RES index of the scene (goi index-res) made with --bundle: only the bundle's prompt
    side runs (seconds for every training view), on the scene's photos; --lift then lifts
    every indexed view by default. With --res-masks and --refine sam: the index of the SAM
    bundle, which keeps the image side of the views the refinement asks (made and grown as
    the query needs), so that the next query encodes none of them again."""


@dataclass
class QueryParams:
    mode: Annotated[str, Choice(MODES)] = "hyperplane"
    """hyperplane: fit the OSH with RES masks; threshold: the fixed threshold (no RES needed)."""


@dataclass
class QueryRun:
    out: Path
    """Output directory: hyperplanes.h5 (the prompt cache) and one directory per prompt."""
    views: str | None = None
    """Comma-separated views to render masks for (default: the test split, else all)."""
    export: Annotated[str, Choice(EXPORTS)] = "subset"
    """PLY to write: subset (the Gaussians of interest), invert (the scene without them),
    highlight (the scene with them recoloured) or none."""
    color: str = "red"
    """Colour of --export highlight."""
    refit: bool = False
    """Fit the hyperplane again even when hyperplanes.h5 already holds this prompt."""


@dataclass
class QueryResult:
    prompt: str
    directory: Path
    cached: bool
    masks: list[Path]
    selection: Path
    ply: Path | None
    n_selected: int
    info: dict
    res_masks: Path | None = None  # the RES masks a model made for the fit, when one ran


def _check_outputs(
    scene: Scene,
    field_path: Path | None,
    prompt: Prompt,
    sources: PromptSources,
    run: QueryRun,
    cams: list[Camera],
) -> None:
    """Every file the query writes, checked before any work: none is an input (the field, the
    scene, the embeddings, a RES mask), a directory or under a file."""
    inputs = [
        field_path,
        scene.ply_path,
        *scene.camera_files,
        sources.text_embeddings,
        sources.bundle,
        sources.res_masks,
        sources.res_index,
    ]
    pdir = Path(run.out) / prompt.name
    check_mask_outputs(pdir / "masks", cams, True, True, inputs)
    files = [Path(run.out) / "hyperplanes.h5", pdir / "selection.h5"]
    if run.export != "none":
        files.append(pdir / f"{prompt.name}.ply")
    for f in files:
        check_output_file(f, "--out")
    refuse_inputs({"--out": files}, inputs)


def run_query(
    scene: Scene,
    field_path: Path | None,
    prompt: Prompt | None,
    sources: PromptSources,
    hp: HyperplaneParams,
    qp: QueryParams,
    run: QueryRun,
    renderer: SemanticRenderer | None = None,
    report: Report = SILENT,
    lp: LiftParams | None = None,
    refine: RefineParams | None = None,
    points: Points | None = None,
    reprompt: RepromptParams | None = None,
) -> QueryResult:
    """The query of one prompt (checked, `Prompt.checked`). field_path None (with --lift) is
    the field-free lifted mode. `refine`: on a RES index that grows, how the answer refines
    (stages.query.lift_answer). `points`: clicks and boxes answered by SAM, alone (prompt
    None) or refining the prompt's answer (stages.query.pointing)."""
    lp = lp or LiftParams()
    refine = refine or RefineParams()
    reprompt = reprompt or RepromptParams()
    for params in (hp, qp, run, lp, refine, reprompt):
        check_params(params)
    if reprompt.refine != "none" and not lp.lift:
        raise GoiError("--refine: only with --lift (it re-prompts SAM from the lifted answer)")
    lp.check(hp)
    check_refine(refine, lp, sources)
    if points:
        return _run_pointed(scene, field_path, prompt, sources, hp, qp, run, lp, refine, points,
                            report, reprompt)  # fmt: skip
    if prompt is None:
        raise GoiError("--prompt is needed (or --click / --box: clicks and boxes answered by SAM)")
    if field_path is None and renderer is None:
        check_field_free(lp, sources)
        rast = Rasterizer.from_gaussians(scene.gaussians)
        cams = default_cameras(scene, run.views)
        if run.export == "highlight":
            parse_color(run.color, "--color")
        _check_outputs(scene, None, prompt, sources, run, cams)
        make_dir(run.out, "--out")
        return _run_lifted(
            scene, None, prompt, None, sources, hp, lp, run, cams, rast, report, refine, reprompt
        )
    assert field_path is not None
    field = renderer.field if renderer else load_field_for(field_path, scene.ply_digest())
    renderer = renderer or SemanticRenderer(scene.gaussians, field)
    text, text_source = text_embedding(
        prompt.text, field.codebook.shape[1], sources.text_embeddings, sources.bundle
    )
    cams = default_cameras(scene, run.views)  # checked before any work
    if run.export == "highlight":
        parse_color(run.color, "--color")
    _check_outputs(scene, field_path, prompt, sources, run, cams)
    out = make_dir(run.out, "--out")
    if lp.lift:
        return _run_lifted(
            scene, field_path, prompt, text, sources, hp, lp, run, cams, renderer, report, refine,
            reprompt,
        )  # fmt: skip
    res_dir = None
    if qp.mode == "hyperplane":
        masks = res_source(
            sources.res_masks,
            sources.bundle,
            prompt,
            renderer.rast,
            sources.res_index,
            scene,
        )
        try:
            plane, cached = fit_hyperplane(
                renderer,
                field_path,
                scene.views("train"),
                prompt,
                text,
                text_source,
                masks,
                hp,
                HyperplaneRun(out / "hyperplanes.h5", refit=run.refit),
                report,
            )
        except NothingFound as e:
            warn(f"{e}: the answer is empty")
            return _empty_answer(scene, field_path, prompt, qp, run, cams, renderer, report)
        if wrote_res_masks(masks, cached):
            res_dir = res_masks_dir(out / "hyperplanes.h5", prompt)
    else:
        plane = threshold_plane(prompt.text, text, field.unit_codebook(), hp.threshold)
        cached = True
    pdir = out / prompt.name
    masks_written = render_masks(
        renderer, plane, cams, MaskParams(), MaskRun(out=pdir / "masks", force=True), report
    )
    sel = select(field, plane)
    inputs = {"ply": scene.ply_digest(), **input_digest("field", field_path)}
    sel_path = write_selection(
        pdir / "selection.h5", sel, plane.prompt, qp.mode, scene.ply_digest(), inputs, force=True
    )
    ply = _export(scene, sel, prompt, qp.mode, run, pdir)
    n = int(sel.sum())
    info = dict(plane.info)
    return QueryResult(prompt.text, pdir, cached, masks_written, sel_path, ply, n, info, res_dir)


def _empty_answer(
    scene: Scene,
    field_path: Path,
    prompt: Prompt,
    qp: QueryParams,
    run: QueryRun,
    cams: list[Camera],
    renderer: SemanticRenderer,
    report: Report,
) -> QueryResult:
    """The RES found nothing on any view: empty masks (with overlays), an empty selection."""
    from stages.query.lift_files import write_masks

    pdir = Path(run.out) / prompt.name
    none = np.zeros(scene.gaussians.count, bool)
    written = write_masks(renderer.rast, none, cams, pdir / "masks", True, True, report)
    inputs = {"ply": scene.ply_digest(), **input_digest("field", field_path)}
    sel_path = write_selection(
        pdir / "selection.h5", none, prompt.text, qp.mode, scene.ply_digest(), inputs, force=True
    )
    ply = _export(scene, none, prompt, qp.mode, run, pdir)
    info = {"res": "found nothing"}
    return QueryResult(prompt.text, pdir, False, written, sel_path, ply, 0, info)


def check_field_free(lp: LiftParams, sources: PromptSources) -> None:
    """Without --field only the lifted mode answers, from a RES source."""
    if not lp.lift:
        raise GoiError(
            "--field is needed (or --lift with --res-masks or a bundle's RES: the field-free "
            "lifted mode)"
        )
    if sources.res_index is not None and sources.bundle is None:
        raise GoiError(
            "--res-index needs --bundle DIR: the bundle the index was made with runs the "
            "prompt side"
        )
    if sources.res_masks is None and sources.bundle is None:
        raise GoiError(
            "--lift without --field answers from RES masks alone: give --res-masks DIR, "
            "--bundle DIR (a bundle with a RES) or --res-index FILE with its --bundle"
        )


def check_refine(refine: RefineParams, lp: LiftParams, sources: PromptSources) -> None:
    """--progressive (and --res-views all) only where they mean something."""
    refine.check(lp.lift)
    if refine.progressive and (sources.res_index is None or sources.res_masks is not None):
        raise GoiError(
            "--progressive: only with --res-index FILE and no --res-masks (the answer refines "
            "as the views it rests on are indexed)"
        )


def open_growing(
    sources: PromptSources,
    scene: Scene,
    refine: RefineParams,
    report: Report,
    reprompt: RepromptParams | None = None,
) -> GrowingIndex | None:
    """The lifted route's RES index, which grows (None without --res-index). Beside
    --res-masks it keeps SAM's image side for --refine sam only: the masks come from the
    files, and the index spares a later query the views' image encodings (res_source
    refuses the pair otherwise)."""
    if sources.res_index is None:
        return None
    if sources.res_masks is not None and (reprompt is None or reprompt.refine != "sam"):
        return None
    from stages.query.res import growing_index

    return growing_index(sources.res_index, sources.bundle, scene, report, refine.index_wait)


def _run_lifted(
    scene: Scene,
    field_path: Path | None,
    prompt: Prompt,
    text: np.ndarray | None,
    sources: PromptSources,
    hp: HyperplaneParams,
    lp: LiftParams,
    run: QueryRun,
    cams: list[Camera],
    renderer: SemanticRenderer | Rasterizer,
    report: Report,
    refine: RefineParams,
    reprompt: RepromptParams,
) -> QueryResult:
    """--lift: the RES masks of several views lifted onto the Gaussians (stages.query.lift_answer);
    a bare Rasterizer (no field) gives the field-free answer. On a RES index that grows, with
    --progressive, each answer before the last is written as the last is (masks, selection,
    PLY), in place, and the views indexed are published when the query ends, however it
    ends."""
    from stages.query.lift_files import answer_prompt

    rast = renderer if isinstance(renderer, Rasterizer) else renderer.rast
    grow = open_growing(sources, scene, refine, report, reprompt)
    pdir = Path(run.out) / prompt.name

    def write(ans: LiftedAnswer, done: int = 0, total: int = 0) -> QueryResult:
        from stages.core.staging import current_stage
        from stages.query.lift_files import write_lifted_selection, write_masks

        written = write_masks(rast, ans.selected, cams, pdir / "masks", True, True, report)
        sel_path = write_lifted_selection(
            pdir / "selection.h5", ans, scene, field_path, lp, True, prompt.text
        )
        ply = _export(scene, ans.selected, prompt, "lifted", run, pdir)
        info = {"views": ans.views, "chosen_by": ans.chosen_by}
        if done:
            stage = current_stage()
            if stage is not None:  # this answer's files in place now, together
                stage.commit()
            report.log(
                f"answer written ({done} of {total} views, {int(ans.selected.sum())} "
                f"Gaussians): {sel_path}; refining"
            )
        n = int(ans.selected.sum())
        return QueryResult(prompt.text, pdir, False, written, sel_path, ply, n, info)

    try:
        masks = res_source(
            sources.res_masks, sources.bundle, prompt, rast, sources.res_index, scene, grow,
        )  # fmt: skip
        on_answer = write if refine.progressive else None
        revise = sam_reviser(reprompt, scene, rast, sources.bundle, masks, report=report)
        ans = answer_prompt(
            scene, renderer, prompt.text, text, masks, hp, lp, report, refine=refine,
            on_answer=on_answer, revise=revise,
        )  # fmt: skip
    finally:
        if grow is not None:
            grow.close()
    return write(ans)


def _export(
    scene: Scene, sel: np.ndarray, prompt: Prompt, mode: str, run: QueryRun, pdir: Path
) -> Path | None:
    """The PLY the query exports (`run.export`) for the selection sel [G] bool, if any."""
    if run.export == "none" or (not sel.any() and run.export == "subset"):
        return None
    edit = PlyEditParams(
        invert=run.export == "invert",
        highlight=run.color if run.export == "highlight" else None,
    )
    selection = Selection(sel, prompt.text, mode, scene.ply_digest())
    ply, _ = export_ply(
        scene.gaussians,
        selection,
        scene.ply_digest(),
        edit,
        PlyExportRun(pdir / f"{prompt.name}.ply", force=True),
    )
    return ply


def _run_pointed(
    scene: Scene,
    field_path: Path | None,
    prompt: Prompt | None,
    sources: PromptSources,
    hp: HyperplaneParams,
    qp: QueryParams,
    run: QueryRun,
    lp: LiftParams,
    refine: RefineParams,
    points: Points,
    report: Report,
    reprompt: RepromptParams,
) -> QueryResult:
    """Clicks and boxes, alone or refining the prompt's answer: the text answer first (any
    route, nothing written), then SAM's answers added and taken out; the masks are rendered
    from the 3D selection, as a lifted answer's are."""
    from stages.query.lift_files import answer_prompt, write_masks

    if refine.progressive:
        raise GoiError("--progressive: not with --click/--box (the answer is written once)")
    named = prompt or Prompt.checked(points.text(), option="--click/--box")
    cams = default_cameras(scene, run.views)
    if run.export == "highlight":
        parse_color(run.color, "--color")
    _check_outputs(scene, field_path, named, sources, run, cams)
    out = make_dir(run.out, "--out")
    pdir = out / named.name
    base, mode, lifted, evidence = None, "pointed", None, None
    inputs: dict = {"ply": scene.ply_digest()}
    if prompt is None:
        if field_path is not None:
            raise GoiError("--field: only with --prompt (clicks and boxes alone are SAM's)")
        lp.check()
        rast = Rasterizer.from_gaussians(scene.gaussians)
    elif field_path is None:
        check_field_free(lp, sources)
        rast = Rasterizer.from_gaussians(scene.gaussians)
    else:
        inputs.update(input_digest("field", field_path))
        field = load_field_for(field_path, scene.ply_digest())
        renderer = SemanticRenderer(scene.gaussians, field)
        rast = renderer.rast
    if prompt is not None and lp.lift:
        text = None
        if field_path is not None:
            text, _ = text_embedding(prompt.text, renderer.field.codebook.shape[1],
                                     sources.text_embeddings, sources.bundle)  # fmt: skip
        grow = open_growing(sources, scene, refine, report, reprompt)
        try:
            masks = res_source(sources.res_masks, sources.bundle, prompt, rast,
                               sources.res_index, scene, grow)  # fmt: skip
            revise = sam_reviser(reprompt, scene, rast, sources.bundle, masks, report=report)
            ans = answer_prompt(scene, renderer if field_path else rast, prompt.text, text,
                                masks, hp, lp, report, refine=refine, revise=revise)  # fmt: skip
        finally:
            if grow is not None:
                grow.close()
        base, mode = ans.selected, "lifted"
        lifted, evidence = ans.record(lp), (ans.lifted.S1, ans.lifted.S0)
    elif prompt is not None:
        assert field_path is not None  # the paper's routes need one (load_field_for above)
        text, text_source = text_embedding(prompt.text, field.codebook.shape[1],
                                           sources.text_embeddings, sources.bundle)  # fmt: skip
        if qp.mode == "hyperplane":
            masks = res_source(sources.res_masks, sources.bundle, prompt, rast,
                               sources.res_index, scene)  # fmt: skip
            plane, _ = fit_hyperplane(renderer, field_path, scene.views("train"), prompt, text,
                                      text_source, masks, hp,
                                      HyperplaneRun(out / "hyperplanes.h5", refit=run.refit),
                                      report)  # fmt: skip
        else:
            plane = threshold_plane(prompt.text, text, field.unit_codebook(), hp.threshold)
        base, mode = select(field, plane), qp.mode
    if not rast.keeping:
        # a one-shot command: each round of a click walks its views again (the answer seen
        # from each, SAM's mask lifted), on the same projections, and a kept view's lifts
        # walk only the tiles around the mask
        rast.keep_views(KEEP_VIEWS_BYTES, scene.views("train"))
    with open_pointer(scene, rast, points, sources.bundle, sources.res_index, report,
                      refine.index_wait) as pointer:  # fmt: skip
        answer = pointer.answer(points.clicks, points.boxes, base)
    sel = answer.selected
    written = write_masks(rast, sel, cams, pdir / "masks", True, True, report)
    sel_path = write_pointed_selection(pdir / "selection.h5", answer, scene, named.text, mode,
                                       inputs, True, lifted, evidence)  # fmt: skip
    ply = _export(scene, sel, named, mode, run, pdir)
    info = {"pointed": answer.record}
    return QueryResult(named.text, pdir, False, written, sel_path, ply, int(sel.sum()), info)

"""Subcommands of the query half: fit-hyperplane, render-mask, select, export-ply, query."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import click

from goi_cli.options import (
    EXISTING,
    build,
    dataclass_options,
    load_scene_from,
    path_option,
    scene_options,
    stack,
)
from goi_cli.report import TERMINAL
from stages.core.staging import staged_outputs
from stages.query.export_ply import PlyEditParams, PlyExportRun
from stages.query.hyperplanes import HyperplaneRun
from stages.query.lift_answer import RefineParams
from stages.query.lift_math import LiftParams
from stages.query.masks import MaskParams, MaskRun
from stages.query.osh import HyperplaneParams
from stages.query.pipeline import PromptSources, QueryParams, QueryRun
from stages.query.pointing import PointParams
from stages.query.reprompt import RepromptParams

field_option = click.option(
    "--field", type=EXISTING, required=True, help="Field artifact (goi fit-field)."
)
#: query / select / render-mask: with --lift and a RES source the field is optional.
field_or_lift_option = click.option(
    "--field",
    type=EXISTING,
    help="Field artifact (goi fit-field). Optional with --lift and a RES source (--res-masks "
    "or a bundle's RES): then the RES masks alone decide (field-free lifted mode) and the "
    "Gaussians no view's evidence reaches stay out.",
)
prompt_option = click.option("--prompt", required=True, help="The text query.")
#: select / query: the text query, or clicks and boxes, or both.
prompt_or_points_option = click.option(
    "--prompt",
    help="The text query (optional with --click/--box: they then refine its answer).",
)


def _clicks(ctx: click.Context, param: click.Parameter, values: tuple[str, ...]) -> list:
    from stages.core.errors import GoiError
    from stages.query.pointing import parse_click

    try:
        return [parse_click(v) for v in values]
    except GoiError as e:
        raise click.BadParameter(str(e).removeprefix("--click: ")) from None


def _boxes(ctx: click.Context, param: click.Parameter, values: tuple[str, ...]) -> list:
    from stages.core.errors import GoiError
    from stages.query.pointing import parse_box

    try:
        return [parse_box(v) for v in values]
    except GoiError as e:
        raise click.BadParameter(str(e).removeprefix("--box: ")) from None


#: select / query: clicks and boxes answered by a bundle's SAM (stages.query.pointing).
point_options = stack(
    click.option(
        "--click",
        "clicks",
        multiple=True,
        metavar="VIEW:U,V[:+|-]",
        callback=_clicks,
        help="A click at pixel column U, row V of VIEW's image (a training view, or a camera "
        "of --camera-file): + (default) adds what is there, grown to --granularity; - takes "
        "the part clicked out. Repeatable; alone or refining --prompt's answer. Needs --bundle "
        "with a SAM (and uses --res-index's image side when given).",
    ),
    click.option(
        "--box",
        "boxes",
        multiple=True,
        metavar="VIEW:X0,Y0,X1,Y1",
        callback=_boxes,
        help="A box at VIEW (pixels of its image): what SAM outlines in it is added. Repeatable.",
    ),
    path_option(
        "--camera-file",
        "Cameras (cameras.json, transforms.json or COLMAP) a --click or --box may name besides "
        "the scene's: a click at any novel view (the 3D point is goi's render's surface there).",
    ),
    dataclass_options(PointParams),
)


def build_points(kw: dict):  # noqa: ANN201
    """The clicks and boxes from the parsed keyword arguments (removing them); the pointing
    options without a click or box are refused, never ignored."""
    from stages.core.errors import GoiError
    from stages.query.point_files import Points

    pts = Points(kw.pop("clicks"), kw.pop("boxes"), build(PointParams, kw), kw.pop("camera_file"))
    if not pts and (pts.params != PointParams() or pts.camera_file is not None):
        raise GoiError("--granularity, --point-views, ..., --camera-file: only with --click/--box")
    return pts


hyperplanes_option = click.option(
    "--hyperplanes", type=EXISTING, required=True, help="Hyperplanes artifact (fit-hyperplane)."
)
#: select / render-mask: the plane is not needed with --lift (it answers from RES masks).
plane_or_lift_option = click.option(
    "--hyperplanes",
    type=EXISTING,
    help="Hyperplanes artifact (fit-hyperplane); not used with --lift.",
)
#: Where the prompt's embedding and RES masks come from: the fields of PromptSources.
source_options = dataclass_options(PromptSources)


class ResViews(click.ParamType):
    """--res-views: a number of views (at least 1) or `all`."""

    name = "K|all"

    def convert(self, value, param, ctx):  # noqa: ANN001, ANN201
        if isinstance(value, int) or value == "all":
            return value
        text = str(value).strip().lower()
        if text == "all":
            return "all"
        try:
            k = int(text)
        except ValueError:
            self.fail(f"{value!r} is not a number of views nor 'all'", param, ctx)
        if k < 1:
            self.fail(f"{k} is below 1 (it must be >= 1, or all)", param, ctx)
        return k


#: The lifted mode's options: LiftParams and RefineParams, with --res-views taking `all` too.
lift_options = stack(
    dataclass_options(LiftParams, skip=("res_views",)),
    click.option(
        "--res-views",
        "res_views",
        type=ResViews(),
        default=None,
        help="With --lift: how many views' RES masks to lift, K or all. Default: every mask "
        "file of the prompt (--res-masks); with --res-index every view the index holds, and "
        "at least 8: views it lacks are indexed, chosen to cover the selection (with "
        "--progressive: all views); or 8 views chosen to cover the provisional selection when "
        "a RES model runs.",
    ),
    dataclass_options(RefineParams, skip=("all_views",)),
    dataclass_options(RepromptParams),
)


def build_lift(kw: dict) -> tuple[LiftParams, RefineParams]:
    """The lifted mode's options from the parsed keyword arguments (removing them; --refine's
    are left for `build_reprompt`)."""
    views = kw.pop("res_views", None)
    lp, refine = build(LiftParams, kw), build(RefineParams, kw)
    if views == "all":
        refine.all_views = True
    else:
        lp.res_views = views
    return lp, refine


def build_reprompt(kw: dict, lift: bool) -> RepromptParams:
    """--refine and its options (removing them): only on the lifted routes."""
    from stages.core.errors import GoiError

    rp = build(RepromptParams, kw)
    if not lift and rp != RepromptParams():
        raise GoiError("--refine, --refine-rounds, --refine-settle: only with --lift")
    return rp


#: render-mask / select: the scene and one prompt's answer, from a plane or lifted.
answer_options = stack(
    scene_options,
    field_or_lift_option,
    prompt_option,
    plane_or_lift_option,
    source_options,
    lift_options,
)


def _lifted_answer(  # noqa: ANN202
    scene,  # noqa: ANN001
    field: Path | None,
    text: str,
    kw: dict,
    need_positive: bool = False,
    on_answer: Callable | None = None,
    progressive: bool = False,
):
    """The lifted answer of a prompt for select / render-mask / fit-hyperplane --lift, and the
    rasterizer it was made with; field None is the field-free lifted mode. A --res-index may
    grow (the views indexed are kept when the answer is made, however it ends); with
    --progressive (`progressive`: the command rewrites its output) `on_answer` gets each
    answer before the last."""
    from stages.core.errors import GoiError
    from stages.query.lift_files import answer_prompt
    from stages.query.pipeline import check_field_free, check_refine, open_growing
    from stages.query.prompts import Prompt, text_embedding
    from stages.query.reprompt import sam_reviser
    from stages.query.res import res_source
    from stages.render.rasterizer import Rasterizer
    from stages.semantics.decode import SemanticRenderer
    from stages.semantics.field import load_field_for

    src = build(PromptSources, kw)
    lp, refine = build_lift(kw)
    rp = build_reprompt(kw, lp.lift)
    hp = build(HyperplaneParams, kw) if "loss" in kw else HyperplaneParams()
    lp.check(hp)
    check_refine(refine, lp, src)
    if refine.progressive and not progressive:
        raise GoiError(
            "--progressive: only goi query and goi select rewrite their answer as it refines"
        )
    prompt = Prompt.checked(text, src.prompt_id)
    embedding = None
    renderer: Rasterizer | SemanticRenderer
    if field is None:
        check_field_free(lp, src)
        renderer = rast = Rasterizer.from_gaussians(scene.gaussians)
    else:
        f = load_field_for(field, scene.ply_digest())
        embedding, _ = text_embedding(
            prompt.text, f.codebook.shape[1], src.text_embeddings, src.bundle
        )
        renderer = SemanticRenderer(scene.gaussians, f)
        rast = renderer.rast
    grow = open_growing(src, scene, refine, TERMINAL, rp)
    try:
        masks = res_source(src.res_masks, src.bundle, prompt, rast, src.res_index, scene, grow)
        revise = sam_reviser(rp, scene, rast, src.bundle, masks, report=TERMINAL)
        ans = answer_prompt(
            scene, renderer, prompt.text, embedding, masks, hp, lp, TERMINAL, need_positive,
            refine=refine, on_answer=on_answer if refine.progressive else None, revise=revise,
        )  # fmt: skip
    finally:
        if grow is not None:
            grow.close()
    return ans, rast, lp


def _not_lifted(kw: dict) -> None:
    """Without --lift: the lifted mode's options are refused (LiftParams.check)."""
    lp, refine = build_lift(kw)
    lp.check()
    refine.check(lp.lift)
    build_reprompt(kw, lp.lift)


def _need_field(field: Path | None) -> Path:
    from stages.core.errors import GoiError

    if field is None:
        raise GoiError(
            "--field is needed (or --lift with --res-masks or a bundle's RES: the field-free "
            "lifted mode)"
        )
    return field


def _source_paths(kw: dict) -> list[Path | None]:
    """The prompt's input files (embeddings, bundle, RES masks): never an output."""
    return [kw.get("text_embeddings"), kw.get("bundle"), kw.get("res_masks"), kw.get("res_index")]


def _scene_files(scene) -> list[Path]:  # noqa: ANN001
    return [scene.ply_path, *scene.camera_files]


def _need_plane(hyperplanes: Path | None) -> Path:
    from stages.core.errors import GoiError

    if hyperplanes is None:
        raise GoiError("--hyperplanes is needed (or --lift, which answers from the RES masks)")
    return hyperplanes


@click.command("fit-hyperplane", short_help="Fit the prompt's hyperplane (OSH) against RES masks.")
@scene_options
@field_option
@prompt_option
@source_options
@dataclass_options(HyperplaneRun)
@dataclass_options(HyperplaneParams)
@lift_options
def fit_hyperplane_cmd(field: Path, prompt: str, **kw) -> None:
    """Fit the prompt's Optimizable Semantic-space Hyperplane against RES masks (paper 3.5).

    W starts as the prompt's embedding and b as -threshold; SGD on the paper's weighted logistic
    loss (or the authors' hinge loss) until the plane's mask agrees with the RES mask. The plane
    is added to the hyperplanes artifact; the same prompt, field and masks are never refitted.
    When the bundle's RES model makes the masks, the ones used are written beside the artifact
    (<out's directory>/<prompt>/res/<view>.png). With --lift the plane is fitted on the RES
    masks of many views lifted onto the Gaussians; an empty mask ("nothing of the prompt here")
    is not one of its negatives, as the paper's one mask always answers.
    """
    from stages.core.files import refuse_inputs
    from stages.query.hyperplanes import add_plane, fit_hyperplane, res_masks_dir, wrote_res_masks
    from stages.query.prompts import Prompt, text_embedding
    from stages.query.res import res_source
    from stages.semantics.decode import SemanticRenderer
    from stages.semantics.field import load_field_for

    scene = load_scene_from(kw)
    if kw["lift"]:
        from stages.query.hyperplanes import check_plane_out

        run = build(HyperplaneRun, kw)
        check_plane_out(run.out, [field, *_source_paths(kw), *_scene_files(scene)])
        ans, _, lp = _lifted_answer(scene, field, prompt, kw, need_positive=True)
        assert ans.plane is not None  # a field took part
        with staged_outputs():
            add_plane(run.out, ans.plane, field, {**ans.record(lp), "mode": "lifted"})
        n = int(ans.plane.positive.sum())
        click.echo(
            f"hyperplane (lifted, {len(ans.views)} views, {n} of {ans.plane.scores.size} "
            f"entries positive): {run.out}"
        )
        return
    _not_lifted(kw)
    src = build(PromptSources, kw)
    p, run = build(HyperplaneParams, kw), build(HyperplaneRun, kw)
    q = Prompt.checked(prompt, src.prompt_id)
    inputs = [field, src.text_embeddings, src.bundle, src.res_masks, src.res_index, scene.ply_path]
    refuse_inputs({"--out": run.out}, [*inputs, *scene.camera_files])
    f = load_field_for(field, scene.ply_digest())
    text, text_source = text_embedding(q.text, f.codebook.shape[1], src.text_embeddings, src.bundle)
    renderer = SemanticRenderer(scene.gaussians, f)
    masks = res_source(src.res_masks, src.bundle, q, renderer.rast, src.res_index, scene)
    with staged_outputs():  # the plane and the RES masks it was fitted on, or neither
        train = scene.views("train")
        plane, cached = fit_hyperplane(
            renderer, field, train, q, text, text_source, masks, p, run, TERMINAL
        )
    n = int(plane.positive.sum())
    state = "cached" if cached else "fitted"
    click.echo(f"hyperplane ({state}, {n} of {plane.scores.size} entries positive): {run.out}")
    if wrote_res_masks(masks, cached):
        click.echo(f"RES masks it was fitted on: {res_masks_dir(run.out, q)}")


@click.command("render-mask", short_help="Render the prompt's mask and an overlay at any camera.")
@answer_options
@path_option(
    "--camera-file",
    "Render these cameras (cameras.json, transforms.json or COLMAP) instead of the scene's: "
    "any novel view.",
)
@dataclass_options(MaskRun)
@dataclass_options(MaskParams)
def render_mask_cmd(
    field: Path | None, prompt: str, hyperplanes: Path | None, camera_file, **kw
) -> None:  # noqa: ANN001
    """Render the prompt's binary mask (PNG) and an overlay on the rendered RGB at any views.
    With --lift the mask is the 3D selection lifted from RES masks, seen from the view (a pixel
    is in when the selected Gaussians carry more than half of its blend weight)."""
    from stages.query.hyperplanes import load_plane
    from stages.query.masks import check_mask_outputs, default_cameras, pick_cameras, render_masks
    from stages.scene.formats import load_cameras
    from stages.semantics.decode import SemanticRenderer
    from stages.semantics.field import load_field_for

    scene = load_scene_from(kw)
    p, run = build(MaskParams, kw), build(MaskRun, kw)
    if camera_file is not None:
        cams = load_cameras(camera_file)
        chosen = pick_cameras({c.name: c for c in cams}, cams, run.views)
    else:
        chosen = default_cameras(scene, run.views)
    inputs = [field, hyperplanes, camera_file, *_source_paths(kw), *_scene_files(scene)]
    check_mask_outputs(run.out, chosen, not run.no_overlay, run.force, inputs)
    if kw["lift"]:
        from stages.query.lift_files import write_masks

        ans, rast, _ = _lifted_answer(scene, field, prompt, kw)
        with staged_outputs():
            written = write_masks(
                rast, ans.selected, chosen, run.out, not run.no_overlay, run.force, TERMINAL
            )
        click.echo(f"masks ({len(written)} views, lifted from {len(ans.views)} views): {run.out}")
        return
    build(PromptSources, kw)
    _not_lifted(kw)
    field = _need_field(field)
    f = load_field_for(field, scene.ply_digest())
    n_entries, dim = f.codebook.shape
    plane = load_plane(_need_plane(hyperplanes), prompt, field, n_entries, dim)
    renderer = SemanticRenderer(scene.gaussians, f)
    with staged_outputs():  # every mask and overlay, or none
        written = render_masks(renderer, plane, chosen, p, run, TERMINAL)
    click.echo(f"masks ({len(written)} views, {p.mode} mode): {run.out}")


@click.command("select", short_help="Select the prompt's 3D Gaussians of interest.")
@stack(scene_options, field_or_lift_option, prompt_or_points_option, plane_or_lift_option,
       source_options, lift_options, point_options)  # fmt: skip
@click.option(
    "--mode",
    type=click.Choice(("hyperplane", "threshold")),
    default="hyperplane",
    show_default=True,
    help="hyperplane (the fitted OSH) or threshold (the fixed cosine threshold).",
)
@path_option("--out", "Selection artifact.", required=True)
@click.option("--force", is_flag=True, help="Overwrite an existing output.")
def select_cmd(
    field: Path | None,
    prompt: str | None,
    hyperplanes: Path | None,
    mode: str,
    out: Path,
    force: bool,
    **kw,
) -> None:
    """Select the 3D Gaussians of interest: those whose decoded feature is on the plane's
    positive side (with --lift: the RES masks of many views lifted onto the Gaussians and
    fused with the field). Writes a selection artifact for export-ply.

    With --click/--box (and a --bundle with a SAM): what SAM outlines at each click or box in
    the training views that see it, lifted onto the Gaussians and voted, grown from the part
    clicked to the object (--granularity); alone, or added to (+) and taken out of (-) the
    prompt's answer. No field or index is needed.
    """
    from stages.core.artifacts import check_writable, input_digest
    from stages.core.files import refuse_inputs
    from stages.query.hyperplanes import load_plane
    from stages.query.masks import plane_for
    from stages.query.osh import THRESHOLD
    from stages.query.selection import select, write_selection
    from stages.semantics.field import load_field_for

    scene = load_scene_from(kw)
    points = build_points(kw)
    check_writable(out, force, "--out")
    refuse_inputs({"--out": out}, [field, hyperplanes, points.camera_file, *_source_paths(kw),
                                   *_scene_files(scene)])  # fmt: skip
    if points:
        _select_pointed(scene, field, prompt, hyperplanes, mode, out, force, points, kw)
        return
    if prompt is None:
        from stages.core.errors import GoiError

        raise GoiError("--prompt is needed (or --click / --box: clicks and boxes answered by SAM)")
    if kw["lift"]:
        from stages.query.lift_files import write_lifted_selection

        written = [False]

        recorded, _ = build_lift(dict(kw))  # the lifted options, as the answer records them

        def rewrite(a, done: int, total: int) -> None:  # noqa: ANN001
            # --progressive: the selection as it refines, replaced atomically each time
            write_lifted_selection(out, a, scene, field, recorded, force or written[0], prompt)
            written[0] = True
            click.echo(f"selection ({done} of {total} views, refining): {out}", err=True)

        ans, _, lp = _lifted_answer(scene, field, prompt, kw, on_answer=rewrite, progressive=True)
        write_lifted_selection(out, ans, scene, field, lp, force or written[0], prompt)
        click.echo(
            f"selection (lifted from {len(ans.views)} views, {int(ans.selected.sum())} of "
            f"{ans.selected.size} Gaussians): {out}"
        )
        return
    build(PromptSources, kw)
    _not_lifted(kw)
    hyperplanes = _need_plane(hyperplanes)
    field = _need_field(field)
    f = load_field_for(field, scene.ply_digest())
    n_entries, dim = f.codebook.shape
    plane = plane_for(load_plane(hyperplanes, prompt, field, n_entries, dim), mode, f, THRESHOLD)
    sel = select(f, plane)
    inputs = {"ply": scene.ply_digest(), **input_digest("field", field)}
    write_selection(out, sel, plane.prompt, mode, scene.ply_digest(), inputs, force)
    click.echo(f"selection ({int(sel.sum())} of {sel.size} Gaussians): {out}")


def _select_pointed(  # noqa: ANN202
    scene,  # noqa: ANN001
    field: Path | None,
    prompt: str | None,
    hyperplanes: Path | None,
    mode: str,
    out: Path,
    force: bool,
    points,  # noqa: ANN001
    kw: dict,
):
    """goi select with clicks and boxes: the prompt's answer first (when there is one), then
    SAM's answers added and taken out."""
    from stages.core.artifacts import input_digest
    from stages.core.errors import GoiError
    from stages.query.hyperplanes import load_plane
    from stages.query.masks import plane_for
    from stages.query.osh import THRESHOLD
    from stages.query.point_files import open_pointer, write_pointed_selection
    from stages.query.selection import select
    from stages.render.rasterizer import Rasterizer
    from stages.semantics.field import load_field_for

    src = build(PromptSources, dict(kw))
    if kw["lift"]:
        _, refine = build_lift(dict(kw))
        if refine.progressive:
            raise GoiError("--progressive: not with --click/--box (the answer is written once)")
    inputs: dict = {"ply": scene.ply_digest()}
    base, how, lifted, evidence = None, "pointed", None, None
    if prompt is None:
        if field is not None or hyperplanes is not None:
            raise GoiError(
                "--field/--hyperplanes: only with --prompt (clicks and boxes alone are SAM's)"
            )
        _not_lifted(kw)
        rast = Rasterizer.from_gaussians(scene.gaussians)
    elif kw["lift"]:
        ans, rast, lp = _lifted_answer(scene, field, prompt, kw)
        base, how = ans.selected, "lifted"
        lifted, evidence = ans.record(lp), (ans.lifted.S1, ans.lifted.S0)
        if field is not None:
            inputs.update(input_digest("field", field))
    else:
        _not_lifted(kw)
        field = _need_field(field)
        f = load_field_for(field, scene.ply_digest())
        n_entries, dim = f.codebook.shape
        plane = load_plane(_need_plane(hyperplanes), prompt, field, n_entries, dim)
        base, how = select(f, plane_for(plane, mode, f, THRESHOLD)), mode
        inputs.update(input_digest("field", field))
        rast = Rasterizer.from_gaussians(scene.gaussians)
    with open_pointer(scene, rast, points, src.bundle, src.res_index, TERMINAL) as pointer:
        answer = pointer.answer(points.clicks, points.boxes, base)
    text = prompt if prompt is not None else points.text()
    write_pointed_selection(out, answer, scene, text, how, inputs, force, lifted, evidence)
    n = int(answer.selected.sum())
    was = "" if base is None else f", the prompt's answer {int(base.sum())}"
    click.echo(
        f"selection ({len(points.clicks)} clicks, {len(points.boxes)} boxes{was}; {n} of "
        f"{answer.selected.size} Gaussians): {out}"
    )


@click.command("export-ply", short_help="Write a selection, or the scene's labels, as a PLY.")
@scene_options
@click.option("--selection", type=EXISTING, help="Selection artifact (goi select).")
@click.option(
    "--labels",
    "labels",
    multiple=True,
    metavar="NAME=SELECTION.h5",
    help="Instead of --selection: write the whole scene with a label and a score per Gaussian, "
    "one id per named selection (repeat the option: ids 1, 2, ... in the order given; where "
    "selections overlap the higher score wins, then the first given).",
)
@click.option("--field", type=EXISTING, help="Field artifact, for --semantics.")
@dataclass_options(PlyExportRun)
@dataclass_options(PlyEditParams)
def export_ply_cmd(
    selection: Path | None, labels: tuple[str, ...], field: Path | None, **kw
) -> None:
    """Write the selection as an INRIA-layout PLY: only the Gaussians of interest (default),
    the scene without them (--invert), with them recoloured (--highlight) or moved
    (--translate); or, with --labels, the whole scene with the named selections as `label`
    and `score` properties. Readable by splat viewers and by goi."""
    from stages.core.files import refuse_inputs
    from stages.query.export_ply import export_ply
    from stages.query.selection import load_selection
    from stages.semantics.field import load_field_for

    scene = load_scene_from(kw)
    p, run = build(PlyEditParams, kw), build(PlyExportRun, kw)
    if labels:
        from stages.query.ply_labels import export_labels

        _not_with_labels(selection, field, p)
        refuse_inputs({"--out": run.out}, [scene.ply_path, *scene.camera_files])
        out, lab, overlapping = export_labels(
            scene.gaussians, scene.ply_digest(), labels, run.out, run.force
        )
        counts = lab.counts()
        named = ", ".join(f"{i} {nm!r} {counts[i]}" for i, nm in enumerate(lab.names, start=1))
        click.echo(f"ply ({counts.sum()} Gaussians; labels {named}; {counts[0]} in none): {out}")
        if overlapping:
            click.echo(
                f"{overlapping} Gaussians are in several selections: each took the label with "
                "the higher score (of equal scores, the one given first)"
            )
        return
    if selection is None:
        raise click.UsageError("Missing option '--selection' (or give --labels NAME=SELECTION.h5).")
    refuse_inputs({"--out": run.out}, [selection, field, scene.ply_path, *scene.camera_files])
    f = load_field_for(field, scene.ply_digest()) if field is not None else None
    sel = load_selection(selection)
    out, n = export_ply(scene.gaussians, sel, scene.ply_digest(), p, run, f)
    click.echo(f"ply ({n} Gaussians): {out}")


def _not_with_labels(selection: Path | None, field: Path | None, p: PlyEditParams) -> None:
    """export-ply --labels: the edits and --selection mean nothing there; refused, not ignored."""
    from dataclasses import fields

    from stages.core.errors import GoiError

    given = ["--selection"] if selection is not None else []
    given += ["--field"] if field is not None else []
    given += [
        "--" + f.name.replace("_", "-")
        for f in fields(PlyEditParams)
        if getattr(p, f.name) != f.default
    ]
    if given:
        raise GoiError(
            f"{given[0]}: not with --labels, which writes the whole scene unchanged with a "
            "label and a score per Gaussian"
        )


@click.command("query", short_help="Answer a prompt: hyperplane, masks, selection and PLY.")
@scene_options
@field_or_lift_option
@prompt_or_points_option
@source_options
@point_options
@dataclass_options(QueryRun)
@dataclass_options(QueryParams)
@dataclass_options(HyperplaneParams)
@lift_options
def query_cmd(field: Path | None, prompt: str | None, **kw) -> None:
    """Query the scene with a text prompt: fit the hyperplane unless cached, render masks,
    select the Gaussians of interest and export them as a PLY. Prints where everything went.

    With --click/--box (and a --bundle with a SAM) the answer is SAM's at the clicks and
    boxes, lifted onto the Gaussians (see goi select), alone or refining the prompt's; its
    masks are rendered from the 3D selection.
    """
    from stages.query.pipeline import run_query
    from stages.query.prompts import Prompt

    scene = load_scene_from(kw)
    points = build_points(kw)
    src = build(PromptSources, kw)
    hp, qp, run = build(HyperplaneParams, kw), build(QueryParams, kw), build(QueryRun, kw)
    lp, refine = build_lift(kw)
    rp = build_reprompt(kw, lp.lift)
    q = Prompt.checked(prompt, src.prompt_id) if prompt is not None else None
    with staged_outputs():  # masks, selection, PLY and the plane appear together, or not at all
        r = run_query(scene, field, q, src, hp, qp, run, report=TERMINAL, lp=lp, refine=refine,
                      points=points, reprompt=rp)  # fmt: skip
    click.echo(f"prompt:     {r.prompt}")
    if points:
        answers = r.info["pointed"]["answers"]
        views = sorted({v for a in answers for v in a["views"]})
        click.echo(f"pointed:    {len(answers)} clicks/boxes, SAM in {len(views)} views")
    elif lp.lift:
        click.echo(f"lifted:     {len(r.info['views'])} views ({r.info['chosen_by']})")
    elif qp.mode == "threshold":
        click.echo(f"hyperplane: none (--mode threshold: cosine > {hp.threshold})")
    else:
        state = "cached" if r.cached else "fitted"
        click.echo(f"hyperplane: {run.out / 'hyperplanes.h5'} ({state})")
    click.echo(f"masks:      {r.masks[0].parent} ({len(r.masks)} views, overlays beside them)")
    if r.res_masks is not None:
        click.echo(f"RES masks:  {r.res_masks} (made by the bundle's RES, the fit used them)")
    click.echo(f"selection:  {r.selection} ({r.n_selected} Gaussians)")
    click.echo(f"ply:        {r.ply if r.ply else '(none)'}")


def register(group: click.Group) -> None:
    for cmd in (fit_hyperplane_cmd, render_mask_cmd, select_cmd, export_ply_cmd, query_cmd):
        group.add_command(cmd)

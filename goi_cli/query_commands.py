"""Subcommands of the query half: fit-hyperplane, render-mask, select, export-ply, query."""

from __future__ import annotations

from pathlib import Path

import click

from goi_cli.options import build, dataclass_options, load_scene_from, scene_options, stack
from stages.demo import DemoOptions
from stages.eval import EvalOptions
from stages.hyperplane import HyperplaneOptions
from stages.masks import MaskOptions
from stages.query import QueryOptions
from stages.selection import ExportOptions

EXISTING = click.Path(exists=True, dir_okay=False, path_type=Path)


field_option = click.option(
    "--field", type=EXISTING, required=True, help="Field artifact (goi fit-field)."
)
prompt_option = click.option("--prompt", required=True, help="The text query.")
text_options = stack(
    click.option(
        "--text-embeddings",
        type=click.Path(path_type=Path),
        help="JSON {text: [floats]} with the prompt's embedding (e.g. a room's "
        "text_embeddings.json).",
    ),
    click.option(
        "--bundle",
        type=click.Path(path_type=Path),
        help="Model bundle whose text encoder embeds the prompt (and whose res model, if "
        "any, makes the RES masks).",
    ),
)
res_options = stack(
    click.option(
        "--res-masks",
        type=click.Path(path_type=Path),
        help="RES masks from any tool: DIR/<view>.png, or DIR/<prompt id>/<view>.png with "
        "--prompt-id (default subdirectory: the prompt's safe name).",
    ),
    click.option("--prompt-id", help="Subdirectory of --res-masks holding this prompt's masks."),
)


def _report(msg: str) -> None:
    click.echo(msg, err=True)


@click.command("fit-hyperplane")
@scene_options
@field_option
@prompt_option
@text_options
@res_options
@dataclass_options(HyperplaneOptions)
def fit_hyperplane_cmd(
    field: Path, prompt: str, text_embeddings, bundle, res_masks, prompt_id, **kw
):  # noqa: ANN001, E501
    """Fit the prompt's Optimizable Semantic-space Hyperplane against RES masks (paper 3.5).

    W starts as the prompt's embedding and b as -threshold; SGD on the paper's weighted logistic
    loss (or the authors' hinge loss) until the plane's mask agrees with the RES mask. The plane
    is added to the hyperplanes artifact; the same prompt, field and masks are never refitted.
    """
    from stages.field import load_field_for
    from stages.hyperplane import ResFiles, ResModel, fit_hyperplane
    from stages.prompts import check_prompt, text_embedding
    from stages.semantic_render import SemanticRenderer

    scene = load_scene_from(kw)
    o = build(HyperplaneOptions, kw)
    prompt = check_prompt(prompt)
    f = load_field_for(field, scene.ply_digest())
    text, source = text_embedding(prompt, f.codebook.shape[1], text_embeddings, bundle)
    renderer = SemanticRenderer(scene.gaussians, f)
    if res_masks is not None:
        masks: ResFiles | ResModel = ResFiles(res_masks, prompt_id, prompt)
    elif bundle is not None:
        masks = ResModel(bundle, prompt, renderer)
    else:
        raise click.UsageError("give --res-masks DIR, or --bundle DIR with a res model")
    plane, cached = fit_hyperplane(
        renderer, field, scene.views("train"), prompt, text, source, masks, o, _report
    )
    n = int(plane.positive.sum())
    state = "cached" if cached else "fitted"
    click.echo(f"hyperplane ({state}, {n} of {plane.scores.size} entries positive): {o.out}")


hyperplanes_option = click.option(
    "--hyperplanes", type=EXISTING, required=True, help="Hyperplanes artifact (fit-hyperplane)."
)


@click.command("render-mask")
@scene_options
@field_option
@prompt_option
@hyperplanes_option
@click.option(
    "--camera-file",
    type=click.Path(path_type=Path),
    help="Render these cameras (cameras.json, transforms.json or COLMAP) instead of the scene's: "
    "any novel view.",
)
@dataclass_options(MaskOptions)
def render_mask_cmd(field: Path, prompt: str, hyperplanes: Path, camera_file, **kw) -> None:  # noqa: ANN001
    """Render the prompt's binary mask (PNG) and an overlay on the rendered RGB at any views."""
    from stages.cameras import load_cameras
    from stages.field import load_field_for
    from stages.hyperplane import load_plane
    from stages.masks import default_cameras, pick_cameras, render_masks
    from stages.semantic_render import SemanticRenderer

    scene = load_scene_from(kw)
    o = build(MaskOptions, kw)
    plane = load_plane(hyperplanes, prompt)
    if camera_file is not None:
        cams = load_cameras(camera_file)
        chosen = pick_cameras({c.name: c for c in cams}, cams, o.views)
    else:
        chosen = default_cameras(scene, o.views)
    renderer = SemanticRenderer(scene.gaussians, load_field_for(field, scene.ply_digest()))
    written = render_masks(renderer, plane, chosen, o)
    click.echo(f"masks ({len(written)} views, {o.mode} mode): {o.out}")


@click.command("select")
@scene_options
@field_option
@prompt_option
@hyperplanes_option
@click.option(
    "--mode",
    default="hyperplane",
    show_default=True,
    help="hyperplane (the fitted OSH) or threshold (the fixed cosine threshold).",
)
@click.option("--out", type=click.Path(path_type=Path), required=True, help="Selection artifact.")
@click.option("--force", is_flag=True, help="Overwrite an existing output.")
def select_cmd(
    field: Path, prompt: str, hyperplanes: Path, mode: str, out: Path, force: bool, **kw
) -> None:  # noqa: E501
    """Select the 3D Gaussians of interest: those whose decoded feature is on the plane's
    positive side. Writes a selection artifact for export-ply."""
    from stages.artifacts import input_digest
    from stages.field import load_field_for
    from stages.hyperplane import THRESHOLD, load_plane
    from stages.masks import plane_for
    from stages.selection import select, write_selection

    scene = load_scene_from(kw)
    f = load_field_for(field, scene.ply_digest())
    plane = plane_for(load_plane(hyperplanes, prompt), mode, f, THRESHOLD)
    sel = select(f, plane)
    inputs = {"ply": scene.ply_digest(), **input_digest("field", field)}
    write_selection(out, sel, plane, mode, scene.ply_digest(), inputs, force)
    click.echo(f"selection ({int(sel.sum())} of {sel.size} Gaussians): {out}")


@click.command("export-ply")
@scene_options
@click.option("--selection", type=EXISTING, required=True, help="Selection artifact (goi select).")
@click.option("--field", type=EXISTING, help="Field artifact, for --semantics.")
@dataclass_options(ExportOptions)
def export_ply_cmd(selection: Path, field: Path | None, **kw) -> None:
    """Write the selection as an INRIA-layout PLY: only the Gaussians of interest (default),
    the scene without them (--invert), with them recoloured (--highlight) or moved
    (--translate). Readable by splat viewers and by goi."""
    from stages.field import load_field_for
    from stages.selection import export_ply, load_selection

    scene = load_scene_from(kw)
    o = build(ExportOptions, kw)
    f = load_field_for(field, scene.ply_digest()) if field is not None else None
    out, n = export_ply(scene.gaussians, load_selection(selection), scene.ply_digest(), o, f)
    click.echo(f"ply ({n} Gaussians): {out}")


@click.command("query")
@scene_options
@field_option
@prompt_option
@text_options
@res_options
@dataclass_options(QueryOptions)
@dataclass_options(HyperplaneOptions, skip=("out",))
def query_cmd(
    field: Path, prompt: str, text_embeddings, bundle, res_masks, prompt_id, **kw
) -> None:  # noqa: ANN001, E501
    """Query the scene with a text prompt: fit the hyperplane unless cached, render masks,
    select the Gaussians of interest and export them as a PLY. Prints where everything went."""
    from stages.query import run_query

    scene = load_scene_from(kw)
    q = build(QueryOptions, kw)
    hp = build(HyperplaneOptions, {**kw, "out": q.out / "hyperplanes.h5"})
    r = run_query(
        scene,
        field,
        prompt,
        text_embeddings,
        bundle,
        res_masks,
        prompt_id,
        hp,
        q,
        report=_report,
    )
    click.echo(f"prompt:     {r.prompt}")
    if q.mode == "threshold":
        click.echo(f"hyperplane: none (--mode threshold: cosine > {hp.threshold})")
    else:
        state = "cached" if r.cached else "fitted"
        click.echo(f"hyperplane: {q.out / 'hyperplanes.h5'} ({state})")
    click.echo(f"masks:      {r.masks[0].parent} ({len(r.masks)} views, overlays beside them)")
    click.echo(f"selection:  {r.selection} ({r.n_selected} Gaussians)")
    click.echo(f"ply:        {r.ply if r.ply else '(none)'}")


@click.command("eval")
@click.argument("room", type=click.Path(path_type=Path))
@click.option(
    "--features",
    type=click.Path(path_type=Path),
    required=True,
    help="Directory of per-view feature files for the training views (<view>.npy or .pt).",
)
@click.option(
    "--res-masks",
    type=click.Path(path_type=Path),
    required=True,
    help="RES masks: DIR/<prompt id>/<view>.png on training views.",
)
@dataclass_options(EvalOptions)
def eval_cmd(room: Path, features: Path, res_masks: Path, **kw) -> None:
    """Run the whole pipeline on a benchmark ROOM (layout: a room README) and score the masks on
    its TEST views with the paper's metrics, for the four ablation variants."""
    from stages.eval import run_eval

    o = build(EvalOptions, kw)
    r = run_eval(room, features, res_masks, o, say=_report)
    click.echo(f"{'variant':14s} {'mIoU':>7s} {'mPA':>7s} {'mP':>7s} {'mIoU3D':>7s}")
    for v, s in r["variants"].items():
        cells = [s["miou"], s["mpa"], s["mp"], s.get("miou_3d")]
        click.echo(f"{v:14s} " + " ".join("      -" if c is None else f"{c:7.4f}" for c in cells))
    click.echo(f"report: {o.out}" + (f"\nhtml:   {o.html}" if o.html else ""))


@click.command("demo")
@dataclass_options(DemoOptions)
def demo_cmd(**kw) -> None:
    """Run goi end to end on the scene shipped with it: import features, initialise the
    codebook, fit the field, then query several prompts; writes masks, overlays, one PLY per
    prompt and OUT/index.html."""
    from stages.demo import run_demo, summary_lines

    o = build(DemoOptions, kw)
    res = run_demo(o, say=_report)
    click.echo("\n".join(["", "goi demo made:", *summary_lines(res)]))
    click.echo(f"  page: {res['index']}   (open it in a browser)")
    click.echo(
        "\nOn your own scene (INRIA layout: point_cloud.ply, cameras.json, images/):\n"
        "  goi extract --scene S --from FEATURES_DIR --out work/features.h5   "
        "(or --bundle DIR, see docs/models.md)\n"
        "  goi init-codebook --features work/features.h5 --out work/codebook.h5\n"
        "  goi fit-field --scene S --features work/features.h5 --codebook work/codebook.h5 "
        "--out work/field.h5\n"
        '  goi query --scene S --field work/field.h5 --prompt "the red chair" '
        "--text-embeddings T.json --res-masks RES_DIR --out work/queries"
    )


def register(group: click.Group) -> None:
    for cmd in (
        fit_hyperplane_cmd,
        render_mask_cmd,
        select_cmd,
        export_ply_cmd,
        query_cmd,
        eval_cmd,
        demo_cmd,
    ):
        group.add_command(cmd)

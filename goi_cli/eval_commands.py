"""Subcommands that run the whole pipeline: eval (a benchmark room, scored) and demo."""

from __future__ import annotations

from pathlib import Path

import click

from goi_cli.options import build, dataclass_options
from goi_cli.report import TERMINAL
from stages.evaluation.demo import DemoParams, DemoRun
from stages.evaluation.pipeline import EvalParams, EvalRun


@click.command("eval")
@click.argument("room", type=click.Path(path_type=Path))
@click.option(
    "--features",
    type=click.Path(path_type=Path),
    default=None,
    help="Directory of per-view feature files for the training views (<view>.npy or .pt); "
    "needed by every variant but lifted_fieldless.",
)
@click.option(
    "--res-masks",
    type=click.Path(path_type=Path),
    default=None,
    help="RES masks: DIR/<prompt id>/<view>.png on training views (or --bundle DIR).",
)
@dataclass_options(EvalRun)
@dataclass_options(EvalParams)
def eval_cmd(room: Path, features: Path | None, res_masks: Path | None, **kw) -> None:
    """Run the whole pipeline on a benchmark ROOM (layout: a room README) and score the masks on
    its TEST views with the paper's metrics, for the four ablation variants and goi's lifted
    modes (lifted, with the field; lifted_fieldless, from the RES masks alone). The RES masks are
    files (--res-masks) or made by a bundle's RES model (--bundle)."""
    from stages.evaluation.pipeline import run_eval

    p, run = build(EvalParams, kw), build(EvalRun, kw)
    r = run_eval(room, features, res_masks, p, run, TERMINAL)
    click.echo(f"{'variant':14s} {'mIoU':>7s} {'mPA':>7s} {'mP':>7s} {'mIoU3D':>7s}")
    for v, s in r.report["variants"].items():
        cells = [s["miou"], s["mpa"], s["mp"], s.get("miou_3d")]
        click.echo(f"{v:14s} " + " ".join("      -" if c is None else f"{c:7.4f}" for c in cells))
    click.echo(f"report: {r.out}" + (f"\nhtml:   {r.html}" if r.html else ""))


@click.command("demo")
@dataclass_options(DemoRun)
@dataclass_options(DemoParams)
def demo_cmd(**kw) -> None:
    """Run goi end to end on the scene shipped with it: import features, initialise the
    codebook, fit the field, then query several prompts; writes masks, overlays, one PLY per
    prompt and OUT/index.html."""
    from stages.evaluation.demo import run_demo, summary_lines

    res = run_demo(build(DemoParams, kw), build(DemoRun, kw), TERMINAL)
    click.echo("\n".join(["", "goi demo made:", *summary_lines(res)]))
    click.echo(f"  page: {res.index}   (open it in a browser)")
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
    group.add_command(eval_cmd)
    group.add_command(demo_cmd)

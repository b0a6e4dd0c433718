"""Subcommands that run the whole pipeline: eval (a benchmark room, scored) and demo."""

from __future__ import annotations

from pathlib import Path

import click

from goi_cli.options import build, dataclass_options, path_option
from goi_cli.report import TERMINAL
from stages.evaluation.benchmarks.run import BENCHMARKS
from stages.evaluation.demo import DemoParams, DemoRun
from stages.evaluation.pipeline import EvalParams, EvalRun


@click.command("eval", short_help="Run the whole pipeline on a room and score its test views.")
@click.argument("room", type=click.Path(path_type=Path))
@path_option(
    "--features",
    "Directory of per-view feature files for the training views (<view>.npy or .pt); "
    "needed by every variant but lifted_fieldless.",
)
@path_option(
    "--res-masks", "RES masks: DIR/<prompt id>/<view>.png on training views (or --bundle DIR)."
)
@click.option(
    "--benchmark",
    type=click.Choice(BENCHMARKS),
    default=None,
    help="Score a public benchmark instead of a room: ROOM is its downloaded copy "
    "(docs/benchmarks.md, 'Public benchmarks'); needs --scene and --text-embeddings.",
)
@click.option(
    "--scene",
    "scenes",
    multiple=True,
    help="With --benchmark: a trained 3DGS scene, NAME=DIR (NAME the benchmark's scene; "
    "repeatable). --features and --res-masks then hold one NAME/ folder per scene.",
)
@dataclass_options(EvalRun)
@dataclass_options(EvalParams)
def eval_cmd(
    room: Path,
    features: Path | None,
    res_masks: Path | None,
    benchmark: str | None,
    scenes: tuple[str, ...],
    **kw,
) -> None:
    """Run the whole pipeline on a benchmark ROOM (layout: a room README) and score the masks on
    its TEST views with the paper's metrics, for the four ablation variants and goi's lifted
    modes (lifted, with the field; lifted_fieldless, from the RES masks alone). The RES masks are
    files (--res-masks) or made by a bundle's RES model (--bundle). With --benchmark NAME, ROOM
    is a public benchmark (lerf-ovs, lerf-mask, 3d-ovs, goi-m360, replica-goi) scored by its
    own protocol and by goi's metrics."""
    from stages.evaluation.pipeline import run_eval

    p, run = build(EvalParams, kw), build(EvalRun, kw)
    if benchmark is not None or scenes:
        _benchmark(benchmark, room, scenes, features, res_masks, p, run)
        return
    r = run_eval(room, features, res_masks, p, run, TERMINAL)
    click.echo(
        f"{'variant':16s} {'mIoU':>7s} {'mPA':>7s} {'mP':>7s} {'mIoU3D':>7s}  "
        f"{'worst prompt':17s} {'<full':>5s}  worst / exact answer"
    )
    for v, s in r.report["variants"].items():
        cells = [s["miou"], s["mpa"], s["mp"], s.get("miou_3d")]
        click.echo(
            f"{v:16s} "
            + " ".join("      -" if c is None else f"{c:7.4f}" for c in cells)
            + f"  {_floor(s)}"
        )
    click.echo(f"report: {r.out}" + (f"\nhtml:   {r.html}" if r.html else ""))


def _floor(s: dict) -> str:
    """A variant's worst prompt, its count of prompts more than the margin below `full`, and its
    worst prompt against the exact 3D answer (stages.evaluation.worst)."""
    w, b, x = s.get("worst_prompt"), s.get("below_full"), s.get("against_exact")
    worst = f"{w['id'][:10]} {w['iou']:.3f}" if w else "-"
    xw = x["worst"] if x else None
    exact = f"{xw['id']} {xw['iou']:.3f} / {xw['exact']:.3f} = {xw['share']:.2f}" if xw else "-"
    return f"{worst:17s} {b['count'] if b else '-':>5}  {exact}"


def _benchmark(
    name: str | None,
    root: Path,
    scenes: tuple[str, ...],
    features: Path | None,
    res_masks: Path | None,
    p: EvalParams,
    run: EvalRun,
) -> None:
    from stages.core.errors import GoiError
    from stages.evaluation.benchmarks.run import run_benchmark

    if name is None:
        raise GoiError("--scene: only with --benchmark NAME")
    if features is None:
        raise GoiError("--features: a public benchmark is scored with the field; give its features")
    r = run_benchmark(name, root, scenes, features, res_masks, p, run, TERMINAL)
    b = r.report["benchmark"]
    click.echo(f"{name}: protocol {b['protocol']}; mean over {len(b['scenes'])} scene(s)")
    for v, s in r.report["variants"].items():
        proto = " ".join(f"{k} {_cell(x)}" for k, x in s["protocol"].items())
        click.echo(f"{v:14s} {proto} | goi mIoU {_cell(s['goi']['miou'])}")
    if "seeds" in b:
        sd = b["seeds"]
        click.echo(
            f"{sd['variant']} over seeds {','.join(map(str, sd['seeds']))} (mean over scenes):"
        )
        for k, sp in {**sd["mean"]["protocol"], "goi mIoU": sd["mean"]["goi_miou"]}.items():
            vals = " ".join(_cell(x) for x in sp["values"])
            click.echo(f"  {k:30s} {vals}  range {_cell(sp['range'])}  sd {_cell(sp['sd'])}")
        for scene, e in b["scenes"].items():
            for q, qs in list(e["seeds"]["queries"].items())[:1]:  # the widest first
                click.echo(
                    f"  {scene}: widest query {q!r}: IoU "
                    + " ".join(_cell(x) for x in qs["values"])
                    + f" (range {_cell(qs['range'])})"
                )
    click.echo(f"report: {r.out}" + (f"\nhtml:   {r.html}" if r.html else ""))


def _cell(x: float | None) -> str:
    return "-" if x is None else f"{x:.4f}"


@click.command("demo", short_help="Run the whole pipeline on the scene goi ships with.")
@dataclass_options(DemoRun)
@dataclass_options(DemoParams)
def demo_cmd(**kw) -> None:
    """Run goi end to end on the scene shipped with it: import features, initialise the
    codebook, fit the field, then query several prompts; writes masks, overlays, one PLY per
    prompt and OUT/index.html."""
    from stages.evaluation.demo import run_demo, summary_lines, view_command

    res = run_demo(build(DemoParams, kw), build(DemoRun, kw), TERMINAL)
    click.echo("\n".join(["", "goi demo made:", *summary_lines(res)]))
    click.echo(f"  page: {res.index}   (open it in a browser)")
    click.echo(
        "\nAsk your own prompts and see the answers in 3D, in the browser (goi view):\n"
        f"  {view_command(res)}"
    )
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

"""`goi view`: the scene and a prompt's answers in the browser (stages.view, on viser)."""

from __future__ import annotations

import math
import time
from pathlib import Path

import click

from goi_cli.options import EXISTING, build, dataclass_options, load_scene_from, scene_options
from goi_cli.report import TERMINAL
from stages.core.errors import GoiError
from stages.query.pipeline import PromptSources
from stages.query.pointing import PointParams
from stages.view.access import is_loopback
from stages.view.session import ViewRun

#: What anyone who reaches a non-loopback --host (and has the page's address) gets.
EXPOSED = (
    "the scene's Gaussians, every training photo, the prompts and answers of every page, and "
    "the right to ask prompts and write exports into --out"
)


@click.command("view", short_help="Ask prompts and see the answers in 3D, in the browser.")
@scene_options
@click.option(
    "--field",
    type=EXISTING,
    help="Field artifact (goi fit-field): the field's answers, the paper's OSH and the lifted "
    "route. Without it only the field-free lifted route answers (from RES masks).",
)
@dataclass_options(PromptSources, skip=("prompt_id",))
@dataclass_options(ViewRun)
@dataclass_options(PointParams, skip=("new_views",))
@click.option(
    "--for-seconds",
    type=click.FloatRange(min=0, min_open=True),
    help="Stop serving after this many seconds (for scripts and tests); default: until Ctrl-C.",
)
def view_cmd(field: Path | None, for_seconds: float | None, **kw) -> None:
    """Ask prompts and look at the answers in 3D, in the browser, while they refine.

    Serves a page (viser) with the scene's Gaussians as splats, the training cameras (click
    one to fly to it and see its photo) and a prompt box. Enter answers at once with the
    field's answer (the prompt's cached OSH, else the fixed threshold), then with the chosen
    route's: the paper's OSH, the fixed threshold, lifted, or field-free lifted, whichever the
    inputs allow. The selection is lit up in 3D (tint, isolate or hide); when the camera rests,
    goi's renderer draws the mask at that camera, which is what `goi render-mask
    --camera-file` writes for it ("Save camera" writes such a file). Answers stay in a
    history; exports (selection.h5, PLYs, the test views' masks) go under --out.

    With a --bundle that has a SAM (a SAM alone, Grounded-SAM, OWLv2 + SAM): click on the
    scene to add (+) or remove (-) what is there, or drag a box; SAM answers in the training
    views that see it and the masks are lifted onto the Gaussians (as goi select --click).
    Answers can be kept under names, combined (union, intersection, difference, invert),
    undone and redone, and exported as the labels of the scene's PLY.

    Binds 127.0.0.1 by default and prints the page's address with a secret token: only a
    page opened from it, at the server's own origin, is served (--no-token drops the token on
    a trusted machine). Needs `pip install 'goi[view]'`.
    """
    from stages.view.session import ViewSession

    try:
        import viser  # noqa: F401
    except ImportError:
        raise GoiError(
            "goi view needs viser: run it as `bash scripts/goi.sh view ...` from goi's "
            "repository (which installs it on first use), or pip install 'goi[view]'"
        ) from None
    if for_seconds is not None and not math.isfinite(for_seconds):
        raise GoiError(f"--for-seconds: {for_seconds} is not a finite number of seconds")
    run = build(ViewRun, kw)
    points = build(PointParams, kw)
    from stages.view.server import servable_port

    servable_port(run.host, run.port)  # before any work: the page must be servable
    sources = build(PromptSources, kw)
    scene = load_scene_from(kw)
    session = ViewSession(scene, field, sources, run, TERMINAL, points)
    session.default_route()  # refuses inputs that can answer nothing, before serving
    if not is_loopback(run.host):
        who = "anyone" if run.no_token else "anyone with the page's address (its token)"
        click.echo(
            f"goi: warning: serving on {run.host}: {who} who can reach the port gets {EXPOSED}; "
            "the traffic is not encrypted",
            err=True,
        )
    from stages.view.app import ViewerApp

    app = ViewerApp(session, TERMINAL)
    # a Ctrl-C the moment the address is printed (or while the server starts) must still stop
    # the server's threads, or they keep the process alive
    try:
        url = app.start()
        mib = app.sent_bytes / 2**20
        click.echo(
            f"goi view: {url}  ({app.splats.count:,} of {scene.gaussians.count:,} Gaussians sent "
            f"to each page, {mib:.1f} MiB; Ctrl-C stops)",
            err=True,
        )
        serve_until(time.monotonic() + for_seconds if for_seconds is not None else math.inf)
    finally:
        app.stop()


def serve_until(deadline: float) -> None:
    """Sleep in short steps until `deadline` (time.monotonic()): a Ctrl-C stops the viewer at
    its next step even when the KeyboardInterrupt was raised, and swallowed, elsewhere
    (stages.core.interrupts)."""
    from stages.core.interrupts import check

    while True:
        check()
        left = deadline - time.monotonic()
        if left <= 0:
            return
        time.sleep(min(left, 0.2))


def register(group: click.Group) -> None:
    group.add_command(view_cmd)

"""`goi demo`: the main job end to end on the scene shipped with goi (goi_cli/demo_scene).

extract (import) -> init-codebook -> fit-field -> query for each prompt, both as the paper does
(one RES view, OSH) and lifted (every RES mask of the prompt lifted onto the Gaussians, goi's
added mode), then an index.html with both answers' overlays per prompt and their IoU against
the scene's ground truth.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import numpy as np

from stages.core.errors import GoiError
from stages.core.files import check_out_dir, make_dir
from stages.core.params import AT_LEAST_1, check_params
from stages.core.report import SILENT, Report
from stages.evaluation.metrics import image_scores, mean_scores, stray_share
from stages.evaluation.report import esc, rel, res_row, write_page
from stages.evaluation.room import Prompt, load_prompts
from stages.models.bundle import load_bundle
from stages.query.lift_math import LiftParams
from stages.query.osh import HyperplaneParams
from stages.query.pipeline import PromptSources, QueryParams, QueryResult, QueryRun, run_query
from stages.query.prompts import safe_name, view_file_name
from stages.query.res import checked_index
from stages.query.selection import load_selection
from stages.scene.cameras import Camera
from stages.scene.images import read_mask
from stages.scene.scene import Scene, load_scene
from stages.semantics.codebook import CodebookParams, CodebookRun, init_codebook
from stages.semantics.decode import SemanticRenderer
from stages.semantics.extract import ExtractParams, ExtractRun, import_features
from stages.semantics.field import load_field
from stages.semantics.field_params import FieldParams, FieldRun

DEMO_SCENE = Path(__file__).resolve().parents[2] / "goi_cli" / "demo_scene"


@dataclass
class DemoParams:
    iterations: Annotated[int, AT_LEAST_1] = 1500
    """fit-field iterations (paper: 1500)."""
    prompts: str | None = None
    """Comma-separated prompt ids of the demo scene to run (default: all of them)."""


@dataclass
class DemoRun:
    out: Path = Path("goi-demo")
    """Directory for everything the demo makes (index.html, artifacts, masks, PLYs)."""
    bundle: Path | None = None
    """Model bundle whose RES (docs/models.md) makes the RES masks on goi's rendering, instead
    of the demo scene's mask files; the page shows the masks the fits used."""
    force: bool = False
    """Write into an --out directory that holds files the demo did not make (they may be
    replaced); a new, empty or earlier demo's directory needs no --force."""
    res_index: Path | None = None
    """RES index of the demo scene made with --bundle (goi index-res --scene
    goi_cli/demo_scene): only the bundle's prompt side runs, on the scene's photos."""


#: Marks a directory as the demo's own output, so that running the demo again may replace it.
DEMO_MARKER = "goi-demo.txt"


def _check_out(out: Path, force: bool) -> None:
    """--out is the demo's: new, empty, or an earlier demo's (marked); a directory of the
    user's files is refused without --force, before anything is written."""
    ours = (out / DEMO_MARKER).is_file
    check_out_dir(out, force, "the demo", ours, "the demo would replace them")


@dataclass
class DemoAnswer:
    prompt: Prompt
    result: QueryResult
    iou: float | None  # mean test-view IoU against the scene's ground truth
    lifted: QueryResult | None = None  # the same prompt answered with --lift
    lifted_iou: float | None = None
    #: each answer's stray share (stages.evaluation.metrics.stray_share): the paper's, lifted
    strays: tuple[float, float | None] | None = None


@dataclass
class DemoResult:
    index: Path  # the page
    field: Path
    answers: list[DemoAnswer]


def _chosen_prompts(prompts: list[Prompt], wanted: str | None) -> list[Prompt]:
    if wanted is None:
        return prompts
    ids = [p.strip() for p in wanted.split(",") if p.strip()]
    if not ids:
        raise GoiError(
            f"--prompts: {wanted!r} names no prompt; give ids separated by commas, e.g. "
            f"{prompts[0].id}, or leave the option out for all of them"
        )
    unknown = [w for w in ids if w not in {p.id for p in prompts}]
    if unknown:
        raise GoiError(
            f"--prompts: unknown id(s) {', '.join(unknown)}; the demo has "
            + ", ".join(f"{p.id} ({p.text})" for p in prompts)
        )
    return [p for p in prompts if p.id in ids]


def run_demo(p: DemoParams, run: DemoRun, report: Report = SILENT) -> DemoResult:
    # torch comes with the fit, not with every goi command that imports this module
    from stages.semantics.fit_field import fit_field

    check_params(p)
    scene_dir = DEMO_SCENE
    if not (scene_dir / "point_cloud.ply").is_file():
        raise GoiError(f"{scene_dir}: the demo scene is missing from this installation")
    if run.res_index is not None and run.bundle is None:
        raise GoiError("--res-index needs --bundle DIR, the bundle the index was made with")
    if run.bundle is not None:  # opened and checked before the field is fitted
        bundle = load_bundle(run.bundle)
        if not bundle.has_res:
            raise GoiError(f"--bundle: {run.bundle} has no RES ('res' or 'grounded')")
        bundle.check_res()
        del bundle
    out = Path(run.out)
    prompts = _chosen_prompts(load_prompts(scene_dir), p.prompts)  # before --out is made
    scene = load_scene(scene_dir)
    if run.res_index is not None:  # checked against the scene before the field is fitted
        checked_index(run.res_index, run.bundle, scene)
    _check_out(out, run.force)
    make_dir(out, "--out")
    (out / DEMO_MARKER).write_text("written by goi demo; running the demo again replaces it\n")
    report.log(f"demo: {scene.gaussians.count} Gaussians, {len(scene.train)} training views")
    feats = import_features(
        scene,
        scene_dir / "features",
        ExtractParams(),
        ExtractRun(out / "features.h5", force=True),
        report,
    )
    cb = init_codebook(
        feats, CodebookParams(), CodebookRun(out / "codebook.h5", force=True), report
    )
    report.log("demo: fitting the semantic field (the longest step)")
    field_path = fit_field(
        scene,
        feats,
        cb,
        FieldParams(iterations=p.iterations),
        FieldRun(out / "field.h5", checkpoint_every=0, force=True),
        report,
    )
    renderer = SemanticRenderer(scene.gaussians, load_field(field_path))
    ids = np.load(scene_dir / "gaussian_ids.npy", allow_pickle=False)  # [G] instance ids
    answers = []
    for prompt in prompts:
        report.log(f"demo: query {prompt.text!r}")
        sources = PromptSources(
            scene_dir / "text_embeddings.json",
            run.bundle,
            None if run.bundle else scene_dir / "res",
            res_index=run.res_index,
        )
        both = [
            run_query(
                scene,
                field_path,
                prompt.query,
                sources,
                HyperplaneParams(),
                QueryParams(),
                QueryRun(out=out / name),
                renderer=renderer,
                lp=LiftParams(lift=name == "lifted"),
            )
            for name in ("queries", "lifted")
        ]
        ious = []
        for r in both:
            scores = []
            for v in prompt.test_views:
                gt = read_mask(scene_dir / "eval" / "masks" / prompt.id / f"{v}.png")
                pred = read_mask(r.directory / "masks" / f"{view_file_name(v)}.png")
                scores.append(image_scores(pred, gt))
            ious.append(mean_scores(scores).iou if scores else None)
        target = np.isin(ids, prompt.targets)
        paper, lifted = (
            stray_share(load_selection(r.selection).selected, target, scene.gaussians.means)
            for r in both
        )
        answers.append(DemoAnswer(prompt, both[0], ious[0], both[1], ious[1], (paper, lifted)))
    page = out / "index.html"
    _index(page, answers, scene.views("test"), _res_masks(answers, renderer, scene))
    return DemoResult(page, field_path, answers)


def _res_masks(answers: list[DemoAnswer], renderer: SemanticRenderer, scene: Scene) -> dict:
    """The RES masks a model made and the fits used (OUT/queries/<prompt>/res/), with the
    rendering the model ran on: {prompt id: (source, {view: (rgb, mask)})}."""
    out = {}
    for a in answers:
        r = a.result
        source = str(r.info.get("mask_source", ""))
        if not source.startswith(("bundle:", "index:")):
            continue
        photo = source.startswith("index:")  # an index ran on the photos, a model on renders
        # a cached plane ran no model; its fit's masks are still in the prompt's res/
        res_dir = r.res_masks or r.directory / "res"
        figs = {}
        for view in json.loads(r.info["views"]):
            path = res_dir / f"{view_file_name(view)}.png"
            if path.is_file():
                if photo:
                    rgb8 = scene.load_image(scene.camera(view))
                else:
                    rgb = renderer.rast.render_rgb(scene.camera(view)).image
                    rgb8 = (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
                figs[view] = (rgb8, read_mask(path))
        if figs:
            out[a.prompt.id] = (source, figs)
    return out


def _index(
    page: Path, answers: list[DemoAnswer], views: list[Camera], res: dict | None = None
) -> None:
    res = res or {}
    body = [
        "<p>goi found the 3D Gaussians of interest of each prompt in the demo scene (a living "
        "room, 121k Gaussians). Masks are rendered on test views the field never saw: red is "
        "goi's mask on its own rendering. IoU is against the scene's ground truth. Two answers "
        "per prompt: the paper's (the OSH fitted on one RES view, masks decoded per pixel) and "
        "goi's lifted mode (every RES mask of the prompt lifted onto the Gaussians and fused "
        "with the field; masks rendered from that 3D selection). Strays: the share of the "
        "answer's Gaussians farther than 3 % of the scene's extent from every Gaussian of the "
        "target, specks an exported PLY would show floating in the room."
        + (
            " RES: the masks the bundle's RES model made on goi's rendering, which the "
            "hyperplane was fitted on."
            if res
            else ""
        )
        + "</p>"
        "<table><tr><th class='l'>prompt</th><th class='l'>answer</th><th>IoU</th>"
        "<th>Gaussians</th><th>strays</th><th class='l'>PLY</th></tr>"
    ]
    for a in answers:
        for label, r, iou_, strays in _both(a):
            ply = f"<a href='{rel(r.ply, page)}'>{esc(r.ply.name)}</a>" if r.ply else "-"
            iou = "-" if iou_ is None else f"{iou_:.3f}"
            stray = "-" if strays is None else f"{100 * strays:.1f} %"
            body.append(
                f"<tr><td class='l'>{esc(r.prompt)}</td><td class='l'>{label}</td><td>{iou}</td>"
                f"<td>{r.n_selected}</td><td>{stray}</td><td class='l'>{ply}</td></tr>"
            )
    body.append("</table>")
    for a in answers:
        body.append(f"<h2>{esc(a.result.prompt)}</h2>")
        if a.prompt.id in res:
            files = page.with_name(page.stem + "_files")
            make_dir(files, "--out")
            body.append(res_row(res[a.prompt.id], files, page, safe_name(a.prompt.id)))
        for label, r, _, _ in _both(a):
            body.append(f"<div><b>{label}</b><br>")
            for cam in views:
                img = r.directory / "masks" / f"{view_file_name(cam.name)}.overlay.png"
                if img.is_file():
                    body.append(
                        f"<figure><img src='{rel(img, page)}' alt='{esc(cam.name)}'>"
                        f"{esc(cam.name)}</figure>"
                    )
            body.append("</div>")
    write_page(page, "goi demo", "".join(body))


def _both(a: DemoAnswer) -> list[tuple[str, QueryResult, float | None, float | None]]:
    """(label, result, IoU, stray share) of the paper's answer and the lifted one."""
    paper, lifted = a.strays if a.strays is not None else (None, None)
    out = [("paper (one view)", a.result, a.iou, paper)]
    if a.lifted is not None:
        out.append(("lifted", a.lifted, a.lifted_iou, lifted))
    return out


def view_command(res: DemoResult) -> str:
    """The `goi view` command that shows the demo's answers in the browser, as it runs from
    here: through scripts/goi.sh, which installs the view extra (viser) on its first use, when
    goi runs from its repository; else `goi view` (after `pip install 'goi[view]'`)."""
    scene = _shown(DEMO_SCENE)
    script = DEMO_SCENE.parents[1] / "scripts" / "goi.sh"
    program = f"bash {_shown(script)} view" if script.is_file() else "goi view"
    return (
        f"{program} --scene {scene} --field {_shown(res.field)} --text-embeddings "
        f"{scene}/text_embeddings.json --res-masks {scene}/res --prompts {scene}/prompts.json "
        f"--out {_shown(res.field.parent / 'view')}"
    )


def _shown(path: Path) -> str:
    """A path as short as it is unambiguous from here: relative below the working directory."""
    try:
        return str(Path(path).resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


def summary_lines(res: DemoResult) -> list[str]:
    lines = []
    for a in res.answers:
        for label, r, iou_, strays in _both(a):
            iou = "  -  " if iou_ is None else f"{iou_:.3f}"
            stray = "  -  " if strays is None else f"{100 * strays:4.1f} %"
            lines.append(
                f"  {r.prompt[:32]:32s} {label:16s} IoU {iou}  {r.n_selected:6d} Gaussians  "
                f"strays {stray}  {r.ply or ''}"
            )
    return lines

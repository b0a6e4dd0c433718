"""`goi demo`: the main job end to end on the scene shipped with goi (goi_cli/demo_scene).

extract (import) -> init-codebook -> fit-field -> query for each prompt, then an index.html with
the overlays per prompt and their IoU against the scene's ground truth.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from stages.codebook import CodebookOptions, init_codebook
from stages.errors import GoiError
from stages.eval import load_prompts
from stages.extract import ExtractOptions, import_features
from stages.field import FieldOptions, fit_field, load_field
from stages.hyperplane import HyperplaneOptions
from stages.metrics import image_scores, mean_scores
from stages.prompts import view_file_name
from stages.query import QueryOptions, run_query
from stages.report import esc, rel, write_page
from stages.scene import load_scene, read_mask
from stages.semantic_render import SemanticRenderer

DEMO_SCENE = Path(__file__).resolve().parents[1] / "goi_cli" / "demo_scene"


@dataclass
class DemoOptions:
    out: Path = Path("goi-demo")
    """Directory for everything the demo makes (index.html, artifacts, masks, PLYs)."""
    iterations: int = 1500
    """fit-field iterations (paper: 1500)."""
    prompts: str | None = None
    """Comma-separated prompt ids of the demo scene to run (default: all of them)."""


def run_demo(o: DemoOptions, say: Callable[[str], None] = print) -> dict:
    scene_dir = DEMO_SCENE
    if not (scene_dir / "point_cloud.ply").is_file():
        raise GoiError(f"{scene_dir}: the demo scene is missing from this installation")
    out = Path(o.out)
    out.mkdir(parents=True, exist_ok=True)
    scene = load_scene(scene_dir)
    prompts = load_prompts(scene_dir)
    if o.prompts:
        wanted = [p.strip() for p in o.prompts.split(",") if p.strip()]
        unknown = [w for w in wanted if w not in {p.id for p in prompts}]
        if unknown:
            raise GoiError(
                f"--prompts: unknown id(s) {', '.join(unknown)}; the demo has "
                + ", ".join(f"{p.id} ({p.text})" for p in prompts)
            )
        prompts = [p for p in prompts if p.id in wanted]
    say(f"demo: {scene.gaussians.count} Gaussians, {len(scene.train)} training views")
    feats = import_features(
        scene, scene_dir / "features", ExtractOptions(out / "features.h5", force=True)
    )
    cb = init_codebook(feats, CodebookOptions(out / "codebook.h5", force=True))
    say("demo: fitting the semantic field (the longest step)")
    field_path = fit_field(
        scene,
        feats,
        cb,
        FieldOptions(out / "field.h5", iterations=o.iterations, checkpoint_every=0, force=True),
    )
    renderer = SemanticRenderer(scene.gaussians, load_field(field_path))
    results = []
    for p in prompts:
        say(f"demo: query {p.text!r}")
        r = run_query(
            scene,
            field_path,
            p.text,
            scene_dir / "text_embeddings.json",
            None,
            scene_dir / "res",
            p.id,
            HyperplaneOptions(out=out / "hyperplanes.h5"),
            QueryOptions(out=out / "queries"),
            renderer=renderer,
            report=lambda s: None,
        )
        scores = []
        for v in p.test_views:
            gt = read_mask(scene_dir / "eval" / "masks" / p.id / f"{v}.png")
            pred = read_mask(r.directory / "masks" / f"{view_file_name(v)}.png")
            scores.append(image_scores(pred, gt))
        iou = mean_scores(scores).iou if scores else None
        results.append({"prompt": p, "result": r, "iou": iou})
    page = out / "index.html"
    _index(page, results, scene.views("test"))
    return {"index": page, "field": field_path, "results": results}


def _index(page: Path, results: list[dict], views: list) -> None:  # noqa: ANN001
    body = [
        "<p>goi found the 3D Gaussians of interest of each prompt in the demo scene (a living "
        "room, 121k Gaussians). Masks are rendered on test views the field never saw: red is "
        "goi's mask on its own rendering. IoU is against the scene's ground truth.</p>"
        "<table><tr><th class='l'>prompt</th><th>IoU</th><th>Gaussians</th>"
        "<th class='l'>PLY</th></tr>"
    ]
    for e in results:
        r = e["result"]
        ply = f"<a href='{rel(r.ply, page)}'>{esc(r.ply.name)}</a>" if r.ply else "-"
        iou = "-" if e["iou"] is None else f"{e['iou']:.3f}"
        body.append(
            f"<tr><td class='l'>{esc(r.prompt)}</td><td>{iou}</td><td>{r.n_selected}</td>"
            f"<td class='l'>{ply}</td></tr>"
        )
    body.append("</table>")
    for e in results:
        r = e["result"]
        body.append(f"<h2>{esc(r.prompt)}</h2><div>")
        for cam in views:
            img = r.directory / "masks" / f"{view_file_name(cam.name)}.overlay.png"
            if img.is_file():
                body.append(
                    f"<figure><img src='{rel(img, page)}' alt='{esc(cam.name)}'>"
                    f"{esc(cam.name)}</figure>"
                )
        body.append("</div>")
    write_page(page, "goi demo", "".join(body))


def summary_lines(res: dict) -> list[str]:
    lines = []
    for e in res["results"]:
        r = e["result"]
        iou = "  -  " if e["iou"] is None else f"{e['iou']:.3f}"
        lines.append(f"  {r.prompt[:32]:32s} IoU {iou}  {r.n_selected:6d} Gaussians  {r.ply or ''}")
    return lines

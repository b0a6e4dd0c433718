"""`goi query --prompt TEXT`: fit the hyperplane unless cached, render masks, select, export.

The output directory holds hyperplanes.h5, the prompt cache shared by every query on the same
field, and one directory per prompt (a safe name of it): masks/, selection.h5 and <name>.ply.
A query overwrites its own prompt's outputs, so re-running it is always safe.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

from stages.artifacts import input_digest
from stages.errors import GoiError
from stages.field import load_field_for
from stages.hyperplane import (
    HyperplaneOptions,
    ResFiles,
    ResModel,
    fit_hyperplane,
    threshold_plane,
)
from stages.masks import MODES, MaskOptions, default_cameras, render_masks
from stages.prompts import check_prompt, safe_name, text_embedding
from stages.scene import Scene
from stages.selection import ExportOptions, Selection, export_ply, select, write_selection
from stages.semantic_render import SemanticRenderer

EXPORTS = ("subset", "invert", "highlight", "none")


@dataclass
class QueryOptions:
    out: Path
    """Output directory: hyperplanes.h5 (the prompt cache) and one directory per prompt."""
    mode: str = "hyperplane"
    """hyperplane: fit the OSH with RES masks; threshold: the fixed threshold (no RES needed)."""
    views: str | None = None
    """Comma-separated views to render masks for (default: the test split, else all)."""
    export: str = "subset"
    """PLY to write: subset (the Gaussians of interest), invert (the scene without them),
    highlight (the scene with them recoloured) or none."""
    color: str = "red"
    """Colour of --export highlight."""


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


def run_query(
    scene: Scene,
    field_path: Path,
    prompt: str,
    text_embeddings: Path | None,
    bundle: Path | None,
    res_masks: Path | None,
    prompt_id: str | None,
    hp: HyperplaneOptions,
    q: QueryOptions,
    renderer: SemanticRenderer | None = None,
    report=print,  # noqa: ANN001
) -> QueryResult:
    prompt = check_prompt(prompt)
    if q.mode not in MODES:
        raise GoiError(f"--mode: {q.mode!r} is not one of {', '.join(MODES)}")
    if q.export not in EXPORTS:
        raise GoiError(f"--export: {q.export!r} is not one of {', '.join(EXPORTS)}")
    field = renderer.field if renderer else load_field_for(field_path, scene.ply_digest())
    renderer = renderer or SemanticRenderer(scene.gaussians, field)
    text, text_source = text_embedding(prompt, field.codebook.shape[1], text_embeddings, bundle)
    cams = default_cameras(scene, q.views)  # checked before any work
    out = Path(q.out)
    out.mkdir(parents=True, exist_ok=True)
    train = scene.views("train")
    hp = replace(hp, out=out / "hyperplanes.h5")
    if q.mode == "hyperplane":
        if res_masks is not None:
            source: ResFiles | ResModel = ResFiles(res_masks, prompt_id, prompt)
        elif bundle is not None:
            source = ResModel(bundle, prompt, renderer)
        else:
            raise GoiError(
                "hyperplane mode needs RES masks: --res-masks DIR, or --bundle DIR with a res "
                "model (or use --mode threshold)"
            )
        plane, cached = fit_hyperplane(
            renderer, field_path, train, prompt, text, text_source, source, hp, report
        )
    else:
        plane, cached = threshold_plane(prompt, text, field, hp.threshold), True
    pdir = out / safe_name(prompt)
    masks = render_masks(
        renderer, plane, cams, MaskOptions(out=pdir / "masks", mode="hyperplane", force=True)
    )
    sel = select(field, plane)
    inputs = {"ply": scene.ply_digest(), **input_digest("field", field_path)}
    sel_path = write_selection(
        pdir / "selection.h5", sel, plane, q.mode, scene.ply_digest(), inputs, force=True
    )
    ply = None
    if q.export != "none":
        eo = ExportOptions(
            out=pdir / f"{safe_name(prompt)}.ply",
            invert=q.export == "invert",
            highlight=q.color if q.export == "highlight" else None,
            force=True,
        )
        if sel.any() or q.export != "subset":
            selection = Selection(sel, prompt, q.mode, scene.ply_digest())
            ply, _ = export_ply(scene.gaussians, selection, scene.ply_digest(), eo)
    return QueryResult(prompt, pdir, cached, masks, sel_path, ply, int(sel.sum()), dict(plane.info))

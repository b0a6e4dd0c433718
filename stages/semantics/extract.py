"""`goi extract`: the features artifact, from an ONNX image encoder or imported files.

Views are written one by one into `<out>.partial`; an interrupted run resumes there (views
already done are skipped) and the finished file is renamed to `<out>` only at the end.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import h5py
import numpy as np

from stages.core.artifacts import check_writable, put, sha256_files, stamp
from stages.core.errors import GoiError
from stages.core.files import (
    check_output_name,
    create_partial,
    finish_partial,
    output_lock,
    partial_exists,
    refuse_inputs,
)
from stages.core.hdf5 import read_h5
from stages.core.params import AT_LEAST_1, Choice, check_params
from stages.core.report import SILENT, Report
from stages.core.staging import kept_on_interrupt
from stages.scene.scene import Scene
from stages.semantics.feature_files import (
    find_feature_file,
    load_feature_file,
    resample,
    to_float16,
)
from stages.semantics.features import SCHEMA


@dataclass
class ExtractParams:
    split: Annotated[str, Choice(("train", "test", "all"))] = "train"
    """Which views to extract: train, test or all."""
    max_side: Annotated[int, AT_LEAST_1] = 160
    """Feature maps larger than this on their longer side are area-downsampled to it: fit-field
    trains on feature cells, and finer cells cost time without adding language detail."""


@dataclass
class ExtractRun:
    out: Path
    """Features artifact to write (HDF5, schema goi.features)."""
    force: bool = False
    """Replace an existing output."""


@dataclass
class _Views:
    """What an extraction writes: the scene's views `names`, each one's features [h, w, D]
    made by `make`, recorded as coming from `source` with the inputs' digests."""

    scene: Scene
    names: list[str]
    source: str
    inputs: dict[str, str]
    make: Callable[[str], np.ndarray]


def _write_views(run: ExtractRun, job: _Views, report: Report) -> Path:
    out = run.out
    check_writable(out, run.force, "--out")
    check_output_name(_partial(out), "--out")
    with output_lock(out, "--out"):  # one run per output, or its partial file is shared
        partial = _partial(out)
        mode = "w"
        if partial_exists(partial, "--out"):
            try:
                with read_h5(partial) as f:
                    same = json.loads(f.attrs.get("inputs", "{}")) == job.inputs
            except (OSError, ValueError, TypeError):
                same = False
            mode = "r+" if same else "w"
            if same:
                report.log(f"resuming {partial}")
        if mode == "w":
            create_partial(partial, "--out")
        return _write_partial(partial, mode, out, job, report)


def _write_partial(partial: Path, mode: str, out: Path, job: _Views, report: Report) -> Path:
    scene, names, inputs = job.scene, job.names, job.inputs
    # On a failure nothing of this run is worth keeping, so a partial file it created goes.
    # An interruption (Ctrl-C, a crash) keeps it, so that the next run resumes it.
    with kept_on_interrupt(partial, created=mode == "w"):
        dim = None
        with h5py.File(partial, mode, track_order=True) as f:
            if mode == "w":
                stamp(f, SCHEMA, inputs)
                f.attrs["source"] = job.source
                f.create_group("views", track_order=True)
            views = f["views"]
            for v in [n for n in names if n in views]:
                if views[v].get("features") is None:
                    del views[v]  # a view cut off while being written
            todo = [n for n in names if n not in views]
            for name in report.progress(todo, "extract", length=len(todo)):
                hwd = job.make(name)
                if dim is None:
                    dim = int(f.attrs.get("dim", hwd.shape[2]))
                if hwd.shape[2] != dim:
                    raise GoiError(
                        f"features of view '{name}' have dimension {hwd.shape[2]}, "
                        f"the other views {dim}"
                    )
                cam = scene.camera(name)
                g = views.create_group(name)
                g.attrs.update(image_width=cam.width, image_height=cam.height)
                put(g, "features", to_float16(hwd), compress=True)
                f.attrs["dim"] = dim
                f.flush()
            if "dim" not in f.attrs:
                raise GoiError("no views to extract")
            stamp(f, SCHEMA, inputs)  # `created` becomes the time the last view was written
    finish_partial(partial, out)
    return out


def _partial(out: Path) -> Path:
    return out.with_name(out.name + ".partial")


def feature_files(scene: Scene, src: Path, split: str, option: str = "--from") -> dict[str, Path]:
    """The feature file of every view of the split in `src` (each one must have one)."""
    if not src.is_dir():
        raise GoiError(f"{option}: {src} is not a directory")
    cams = scene.views(split)
    found = {c.name: find_feature_file(src, c.name, c.image) for c in cams}
    missing = [n for n, f in found.items() if f is None]
    if len(missing) == len(found):
        raise GoiError(
            f"{option}: {src} has no <view>.npy or <view>.pt for any of the "
            f"{len(found)} {split} views (e.g. {cams[0].name}.npy): do the "
            "feature files belong to this scene?"
        )
    if missing:
        raise GoiError(
            f"{option}: {src} has no features for view(s) {', '.join(missing[:5])}"
            f"{' ...' if len(missing) > 5 else ''}"
        )
    return {n: f for n, f in found.items() if f is not None}


def import_features(
    scene: Scene, src: Path, p: ExtractParams, run: ExtractRun, report: Report = SILENT
) -> Path:
    """Write the features artifact from per-image `.npy` / `.pt` files in `src`."""
    check_params(p)
    files = feature_files(scene, src, p.split)
    outputs = {"--out": [run.out, _partial(run.out)]}
    refuse_inputs(outputs, [*files.values(), scene.ply_path, *scene.camera_files])
    inputs = {
        "cameras": scene.cameras_digest(),
        # Every byte: a file edited in place must not pass for the one a field was fitted on.
        "features_dir": sha256_files(list(files.values())),
    }

    def make(name: str) -> np.ndarray:
        path = files[name]
        chw = load_feature_file(path)
        if not np.isfinite(chw).all():
            raise GoiError(f"{path}: holds {int((~np.isfinite(chw)).sum())} NaN/inf values")
        cam = scene.camera(name)
        if chw.shape[1] > cam.height or chw.shape[2] > cam.width:
            raise GoiError(
                f"{path}: map {chw.shape[2]}x{chw.shape[1]} is larger than its image "
                f"{cam.width}x{cam.height}"
            )
        return resample(chw, p.max_side)

    return _write_views(run, _Views(scene, list(files), f"import:{src}", inputs, make), report)


def encode_views(
    scene: Scene, bundle_dir: Path, p: ExtractParams, run: ExtractRun, report: Report = SILENT
) -> Path:
    """Write the features artifact by running a bundle's image encoder on the images."""
    check_params(p)
    from stages.models.bundle import load_bundle

    bundle = load_bundle(bundle_dir)
    names = [c.name for c in scene.views(p.split)]
    # fail before any work on a missing or mis-sized image
    images = [scene.image_path(scene.camera(n)) for n in names]
    outputs = {"--out": [run.out, _partial(run.out)]}
    refuse_inputs(outputs, [scene.ply_path, *scene.camera_files, bundle_dir, *images])
    inputs = {"cameras": scene.cameras_digest(), "bundle": bundle.digest()}

    def make(name: str) -> np.ndarray:
        chw = bundle.encode_image(scene.load_image(scene.camera(name)))
        if not np.isfinite(chw).all():
            raise GoiError(f"{bundle_dir}: image encoder returned NaN/inf for view '{name}'")
        return resample(chw, p.max_side)

    return _write_views(run, _Views(scene, names, f"bundle:{bundle.name}", inputs, make), report)

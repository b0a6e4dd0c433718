"""`goi extract`: the features artifact, from an ONNX image encoder or imported files.

Views are written one by one into `<out>.partial`; an interrupted run resumes there (views
already done are skipped) and the finished file is renamed to `<out>` only at the end.
"""

from __future__ import annotations

import contextlib
import json
import os
import pickle
import warnings
import zipfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from stages.artifacts import check_writable, put, sha256_file, stamp
from stages.errors import GoiError
from stages.features import SCHEMA
from stages.progress import progress
from stages.scene import Scene

MAX_FEATURE_VALUES = 1 << 31  # one map of more than 2^31 values (8 GiB) is refused


@dataclass
class ExtractOptions:
    out: Path
    """Features artifact to write (HDF5, schema goi.features)."""
    split: str = "train"
    """Which views to extract: train, test or all."""
    max_side: int = 160
    """Feature maps larger than this on their longer side are area-downsampled to it: fit-field
    trains on feature cells, and finer cells cost time without adding language detail."""
    force: bool = False
    """Replace an existing output."""


def _find_file(src: Path, view: str, image: str | None) -> Path | None:
    names = [view, *([Path(image).name] if image else [])]
    for base in names:
        for ext in (".npy", ".pt"):
            cand = src / f"{base}{ext}"
            if cand.is_file():
                return cand
    return None


def load_feature_file(path: Path) -> np.ndarray:
    """A [D, h, w] map from `.npy` or from the authors' APE `.pt` (a tensor, nothing else)."""
    if path.suffix == ".npy":
        try:
            arr = np.load(path, allow_pickle=False, mmap_mode="r")
        except ValueError as e:
            raise GoiError(f"{path}: not a plain numeric .npy array ({e})") from None
        except OSError as e:
            raise GoiError(f"{path}: cannot read ({e})") from None
    else:
        import torch

        try:
            with warnings.catch_warnings():  # torch warns about the file's pickle protocol
                warnings.simplefilter("ignore")
                t = torch.load(path, map_location="cpu", weights_only=True)
        except (pickle.UnpicklingError, RuntimeError, EOFError, zipfile.BadZipFile) as e:
            first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise GoiError(f"{path}: refused: not a plain tensor file ({first[:160]})") from None
        if not isinstance(t, torch.Tensor):
            raise GoiError(f"{path}: holds a {type(t).__name__}, expected one [D, H, W] tensor")
        arr = t.float().numpy()
    if arr.ndim != 3:
        raise GoiError(f"{path}: shape {tuple(arr.shape)}, expected [D, h, w]")
    if arr.dtype.kind not in "fiu":
        raise GoiError(f"{path}: dtype {arr.dtype} is not numeric")
    if int(np.prod(arr.shape, dtype=np.int64)) > MAX_FEATURE_VALUES:
        raise GoiError(f"{path}: shape {tuple(arr.shape)} is too large")
    return np.asarray(arr, dtype=np.float32)


def resample(chw: np.ndarray, max_side: int) -> np.ndarray:
    """[D, h, w] -> [h', w', D] with max(h', w') <= max_side (area average, aspect kept)."""
    import cv2

    d, h, w = chw.shape
    hwd = np.ascontiguousarray(chw.transpose(1, 2, 0))
    scale = max_side / max(h, w)
    if scale >= 1:
        return hwd
    nh, nw = max(1, round(h * scale)), max(1, round(w * scale))
    # cv2 resizes at most 512 channels at once.
    parts = [
        cv2.resize(hwd[:, :, c : c + 256], (nw, nh), interpolation=cv2.INTER_AREA)
        for c in range(0, d, 256)
    ]
    parts = [p[:, :, None] if p.ndim == 2 else p for p in parts]
    return np.concatenate(parts, axis=2)


def _write_views(
    opts: ExtractOptions,
    scene: Scene,
    names: list[str],
    source: str,
    inputs: dict[str, str],
    make: Callable[[str], np.ndarray],
) -> Path:
    out = opts.out
    check_writable(out, opts.force)
    partial = out.with_name(out.name + ".partial")
    mode = "w"
    if partial.is_file():
        try:
            with h5py.File(partial, "r") as f:
                same = json.loads(f.attrs.get("inputs", "{}")) == inputs
        except OSError:
            same = False
        mode = "r+" if same else "w"
        if same:
            print(f"goi: resuming {partial}", flush=True)
    # On bad input nothing of this run is worth keeping, so a partial file it created goes.
    # An interruption (Ctrl-C, a crash) keeps it, so that the next run resumes it.
    with _removed_on_bad_input(partial, created=mode == "w"):
        dim = None
        with h5py.File(partial, mode, track_order=True) as f:
            if mode == "w":
                stamp(f, SCHEMA, inputs)
                f.attrs["source"] = source
                f.create_group("views", track_order=True)
            views = f["views"]
            for v in [n for n in names if n in views]:
                if views[v].get("features") is None:
                    del views[v]  # a view cut off while being written
            todo = [n for n in names if n not in views]
            for name in progress(todo, "extract", length=len(todo)):
                hwd = make(name)
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
                put(g, "features", hwd.astype(np.float16), compress=True)
                f.attrs["dim"] = dim
                f.flush()
            if "dim" not in f.attrs:
                raise GoiError("no views to extract")
            stamp(f, SCHEMA, inputs)  # `created` becomes the time the last view was written
    with open(partial, "rb+") as fh:
        os.fsync(fh.fileno())
    os.replace(partial, out)
    return out


@contextlib.contextmanager
def _removed_on_bad_input(path: Path, created: bool) -> Iterator[None]:
    try:
        yield
    except GoiError:
        if created:
            path.unlink(missing_ok=True)
        raise


def import_features(scene: Scene, src: Path, opts: ExtractOptions) -> Path:
    """Write the features artifact from per-image `.npy` / `.pt` files in `src`."""
    if not src.is_dir():
        raise GoiError(f"--from: {src} is not a directory")
    cams = scene.views(opts.split)
    files = {c.name: _find_file(src, c.name, c.image) for c in cams}
    missing = [n for n, p in files.items() if p is None]
    if len(missing) == len(files):
        raise GoiError(
            f"--from: {src} has no <view>.npy or <view>.pt for any of the "
            f"{len(files)} {opts.split} views (e.g. {cams[0].name}.npy): do the "
            "feature files belong to this scene?"
        )
    if missing:
        raise GoiError(
            f"--from: {src} has no features for view(s) {', '.join(missing[:5])}"
            f"{' ...' if len(missing) > 5 else ''}"
        )
    inputs = {
        "cameras": scene.cameras_digest(),
        "features_dir": _dir_digest([p for p in files.values() if p is not None]),
    }

    def make(name: str) -> np.ndarray:
        path = files[name]
        assert path is not None
        chw = load_feature_file(path)
        if not np.isfinite(chw).all():
            raise GoiError(f"{path}: holds {int((~np.isfinite(chw)).sum())} NaN/inf values")
        cam = scene.camera(name)
        if chw.shape[1] > cam.height or chw.shape[2] > cam.width:
            raise GoiError(
                f"{path}: map {chw.shape[2]}x{chw.shape[1]} is larger than its image "
                f"{cam.width}x{cam.height}"
            )
        return resample(chw, opts.max_side)

    return _write_views(opts, scene, list(files), f"import:{src}", inputs, make)


def _dir_digest(paths: list[Path]) -> str:
    from hashlib import sha256

    h = sha256()
    for p in sorted(paths):
        st = p.stat()
        # Names, sizes and the first file's content: hashing gigabytes of features would
        # dominate the run; the per-view files are checked when read.
        h.update(f"{p.name}:{st.st_size};".encode())
    if paths:
        h.update(sha256_file(sorted(paths)[0]).encode())
    return h.hexdigest()


def encode_views(scene: Scene, bundle_dir: Path, opts: ExtractOptions) -> Path:
    """Write the features artifact by running a bundle's image encoder on the images."""
    from stages.bundle import load_bundle

    bundle = load_bundle(bundle_dir)
    names = [c.name for c in scene.views(opts.split)]
    for n in names:  # fail before any work on a missing or mis-sized image
        scene.image_path(scene.camera(n))
    inputs = {"cameras": scene.cameras_digest(), "bundle": bundle.digest()}

    def make(name: str) -> np.ndarray:
        chw = bundle.encode_image(scene.load_image(scene.camera(name)))
        if not np.isfinite(chw).all():
            raise GoiError(f"{bundle_dir}: image encoder returned NaN/inf for view '{name}'")
        return resample(chw, opts.max_side)

    return _write_views(opts, scene, names, f"bundle:{bundle.name}", inputs, make)

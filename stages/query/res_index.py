"""The per-scene RES index (artifact goi.res_index): a bundle's RES image side, run once per
training view on the scene's photos, so a new prompt costs only the prompt side.

Almost all of a RES model's work does not depend on the prompt (SAM's image encoder; OWLv2's
ViT, box and objectness heads; CLIPSeg's visual activations). `build_res_index` runs that part
(`Bundle.res_image_side`) on each training image and stores the named arrays per view, in the
dtypes the bundle declares (`Bundle.res_image_side_spec`: float16 where exact enough). A query
then runs `Bundle.res_prompt` once and `Bundle.res_from_image_side` per view.

The index is built view by view into `<out>.partial` (a cut-off run resumes with the views it
finished, when it was made from the same bundle and images) and renamed into place at the end.
It records the bundle's digest and each view's image digest; `check_res_index` refuses an index
made with another bundle, from another scene or image set, or lacking views, naming what
differs.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from stages.core.artifacts import check_writable, open_h5, put, sha256_file, stamp
from stages.core.errors import GoiError
from stages.core.files import (
    check_output_name,
    create_partial,
    output_lock,
    partial_exists,
    refuse_inputs,
)
from stages.core.report import SILENT, Report
from stages.core.staging import kept_on_interrupt
from stages.models.bundle import Bundle, load_bundle
from stages.scene.cameras import Camera
from stages.scene.scene import Scene

SCHEMA = "goi.res_index"

#: The per-view attribute written after a view's arrays: its presence marks the view complete.
DONE_ATTR = "image_sha256"


@dataclass
class ResIndexRun:
    bundle: Path
    """Model bundle whose RES image side is indexed (a RES with a prompt-independent image
    side: Grounded-SAM's SAM, OWLv2 + SAM, CLIPSeg; docs/models.md)."""
    out: Path
    """The index to write (HDF5, schema goi.res_index); a cut-off run resumes from
    <out>.partial."""
    force: bool = False
    """Replace an existing output."""


def image_digests(scene: Scene, cams: list[Camera]) -> dict[str, str]:
    """view -> SHA-256 of its image file (a missing image is named here, before any work)."""
    return {c.name: sha256_file(scene.image_path(c)) for c in cams}


def _combined(digests: dict[str, str]) -> str:
    import hashlib

    h = hashlib.sha256()
    for view, d in digests.items():
        h.update(f"{view}\0{d}\0".encode())
    return h.hexdigest()


def indexable_bundle(bundle_dir: Path | Bundle, option: str = "--bundle") -> Bundle:
    """The bundle, its RES opened and checked; refused when it has no image side to index."""
    bundle = bundle_dir if isinstance(bundle_dir, Bundle) else load_bundle(bundle_dir)
    if not bundle.has_res:
        raise GoiError(
            f"{option}: {bundle.root} has no RES ('res' or 'grounded'); nothing to index"
        )
    if not bundle.res_indexable:
        raise GoiError(
            f"{option}: the RES of {bundle.root} has no prompt-independent image side to index; "
            "use it directly (--bundle) instead of --res-index"
        )
    bundle.check_res()
    return bundle


def _partial(out: Path) -> Path:
    return out.with_name(out.name + ".partial")


def build_res_index(scene: Scene, run: ResIndexRun, report: Report = SILENT) -> Path:
    """Run the bundle's RES image side on every training image and write the index (module
    doc). Returns the index's path."""
    out = Path(run.out)
    check_writable(out, run.force, "--out")
    partial = _partial(out)
    check_output_name(partial, "--out")
    cams = scene.views("train")
    images = [scene.image_path(c) for c in cams]  # every photo found before any work
    refuse_inputs(
        {"--out": [out, partial]}, [scene.ply_path, *scene.camera_files, run.bundle, *images]
    )
    bundle = indexable_bundle(Path(run.bundle))
    digests = image_digests(scene, cams)
    spec = {k: (tuple(int(n) for n in s), str(np.dtype(d))) for k, (s, d) in
            bundle.res_image_side_spec().items()}  # fmt: skip
    inputs = {
        "bundle": bundle.digest(),
        "images": _combined(digests),
        "cameras": scene.cameras_digest(),
    }
    with output_lock(out, "--out"):  # one run per output, or its partial file is shared
        return _build(scene, cams, bundle, spec, inputs, digests, out, partial, report)


def _build(
    scene: Scene,
    cams: list[Camera],
    bundle: Bundle,
    spec: dict[str, tuple[tuple[int, ...], str]],
    inputs: dict[str, str],
    digests: dict[str, str],
    out: Path,
    partial: Path,
    report: Report,
) -> Path:
    mode = "w"
    # the one checked path for partial files: a regular file of this user, never a link or
    # an input
    if partial_exists(partial, "--out"):
        try:
            with h5py.File(partial, "r") as f:
                same = json.loads(f.attrs.get("inputs", "{}")) == inputs
        except (OSError, ValueError):
            same = False
        mode = "r+" if same else "w"
        if same:
            report.log(f"resuming {partial}")
    if mode == "w":
        create_partial(partial, "--out")
    t0 = time.perf_counter()
    with kept_on_interrupt(partial, created=mode == "w"):
        with h5py.File(partial, mode, track_order=True) as f:
            if mode == "w":
                stamp(f, SCHEMA, inputs)
                f.attrs.update(
                    bundle_name=bundle.name,
                    bundle_sha256=inputs["bundle"],
                    images_sha256=inputs["images"],
                    cameras_sha256=inputs["cameras"],
                    res_kind=str(bundle.res_kind),
                    arrays=json.dumps({k: [list(s), d] for k, (s, d) in spec.items()}),
                )
                f.create_group("views", track_order=True)
            views = f["views"]
            for v in list(views):
                if DONE_ATTR not in views[v].attrs:
                    del views[v]  # cut off while being written
            todo = [c for c in cams if c.name not in views]
            if len(todo) < len(cams):
                report.log(f"{len(cams) - len(todo)} of {len(cams)} views already indexed")
            for cam in report.progress(todo, "index-res", show=_name):
                arrays = bundle.res_image_side(scene.load_image(cam))
                _check_arrays(arrays, spec, f"{bundle.where}: res_image_side of view {cam.name}")
                g = views.create_group(cam.name)
                g.attrs.update(width=cam.width, height=cam.height)
                for key in spec:
                    put(g, key, arrays[key])
                g.attrs[DONE_ATTR] = digests[cam.name]
                f.flush()
            f.attrs["n_views"] = len(cams)
            stamp(f, SCHEMA, inputs)  # `created` becomes the time the last view was written
    with open(partial, "rb+") as fh:
        os.fsync(fh.fileno())
    os.replace(partial, out)
    report.log(
        f"RES index: {len(cams)} views in {time.perf_counter() - t0:.1f} s "
        f"({out.stat().st_size / 2**20:.1f} MiB at {out})"
    )
    return out


def _check_arrays(
    arrays: dict[str, np.ndarray], spec: dict[str, tuple[tuple[int, ...], str]], where: str
) -> None:
    """The image side's arrays against the declared spec (shape and dtype per key)."""
    for key, (shape, dtype) in spec.items():
        a = arrays.get(key)
        if a is None:
            raise GoiError(f"{where}: array '{key}' is missing")
        if tuple(a.shape) != shape or str(a.dtype) != dtype:
            raise GoiError(
                f"{where}: array '{key}' is {a.dtype} {list(a.shape)}, the bundle declares "
                f"{dtype} {list(shape)}"
            )


@dataclass
class ResIndex:
    """An opened index: which views it holds, with what, and each view's arrays on demand."""

    path: Path
    bundle_name: str
    bundle_sha256: str
    views: dict[str, str]  # view -> image SHA-256, in the index's order
    sizes: dict[str, tuple[int, int]]  # view -> (width, height)
    spec: dict[str, tuple[tuple[int, ...], str]]

    def image_side(self, view: str) -> dict[str, np.ndarray]:
        """The view's stored image-side arrays (as res_image_side returned them)."""
        if view not in self.views:
            raise GoiError(f"--res-index: {self.path} holds no view '{view}'")
        with h5py.File(self.path, "r") as f:
            g = f["views"][view]
            arrays = {k: g[k][()] for k in self.spec}
        _check_arrays(arrays, self.spec, f"{self.path}: view '{view}'")
        return arrays


def load_res_index(path: str | os.PathLike[str]) -> ResIndex:
    """Open and validate an index (schema, version, every view complete)."""
    p = Path(path)
    with open_h5(p, SCHEMA) as f:
        try:
            raw = json.loads(str(f.attrs["arrays"]))
            spec = {k: (tuple(int(n) for n in s), str(np.dtype(d))) for k, (s, d) in raw.items()}
        except (ValueError, TypeError, KeyError) as e:
            raise GoiError(f"{p}: attribute 'arrays' is not a valid array spec ({e})") from None
        views: dict[str, str] = {}
        sizes: dict[str, tuple[int, int]] = {}
        for name, g in f["views"].items():
            if DONE_ATTR not in g.attrs:
                raise GoiError(f"{p}: view '{name}' is incomplete; build the index again")
            for key, (shape, dtype) in spec.items():
                ds = g.get(key)
                if not isinstance(ds, h5py.Dataset) or ds.shape != shape or ds.dtype != dtype:
                    raise GoiError(f"{p}: view '{name}' array '{key}' is not {dtype} {list(shape)}")
            views[name] = str(g.attrs[DONE_ATTR])
            sizes[name] = (int(g.attrs["width"]), int(g.attrs["height"]))
        if not views:
            raise GoiError(f"{p}: the index holds no view")
        return ResIndex(
            p, str(f.attrs["bundle_name"]), str(f.attrs["bundle_sha256"]), views, sizes, spec
        )


def check_res_index(index: ResIndex, scene: Scene, bundle: Bundle, cams: list[Camera]) -> None:
    """Refuse an index that does not answer for these views of this scene with this bundle,
    naming what differs (bundle, scene, image set, missing views)."""
    where = f"--res-index: {index.path}"
    digest = bundle.digest()
    if digest != index.bundle_sha256:
        raise GoiError(
            f"{where} was made with bundle '{index.bundle_name}' (sha256 "
            f"{index.bundle_sha256[:12]}), not with {bundle.root} (sha256 {digest[:12]}); "
            "build the index with this bundle (goi index-res)"
        )
    held = [c for c in cams if c.name in index.views]
    if not held:
        raise GoiError(
            f"{where} holds none of this scene's {len(cams)} training views (it has e.g. "
            f"'{next(iter(index.views))}'): it was made from another scene"
        )
    missing = [c.name for c in cams if c.name not in index.views]
    if missing:
        more = f" and {len(missing) - 1} more" if len(missing) > 1 else ""
        raise GoiError(
            f"{where} lacks view '{missing[0]}'{more} of the {len(cams)} asked for; build the "
            "index again for this scene (goi index-res)"
        )
    now = image_digests(scene, held)
    changed = [c for c in held if now[c.name] != index.views[c.name]]
    if changed:
        more = f" (and {len(changed) - 1} more views)" if len(changed) > 1 else ""
        raise GoiError(
            f"{where}: the image of view '{changed[0].name}' ({scene.image_path(changed[0])}) "
            f"is not the one indexed{more}: it was made from another image set; build the "
            "index again (goi index-res)"
        )


def _name(cam: Camera | None) -> str | None:
    return cam.name if cam else None

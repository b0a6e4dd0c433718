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

An index is read like every artifact: its links all hard links inside the file (no external
or soft link, no dataset stored in another file), views as groups, each array of the declared
dtype and shape, which must be the bundle's, and finite values (a NaN in an index is an index
error, not "the RES found nothing"). A resumed `.partial` keeps only views that pass the same
reader, and the finished file is read once more before it is renamed into place.
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
    regular_file,
)
from stages.core.report import SILENT, Report
from stages.core.staging import kept_on_interrupt
from stages.models.bundle import Bundle, load_bundle
from stages.scene.cameras import Camera
from stages.scene.scene import Scene

SCHEMA = "goi.res_index"

#: The per-view attribute written after a view's arrays: its presence marks the view complete.
DONE_ATTR = "image_sha256"
#: No RES image side stores more than this per array (SAM ViT-H: 2 MiB, OWLv2 large: ~10 MiB):
#: a spec declaring more is refused before any array is read.
MAX_ARRAY_BYTES = 1 << 30


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


def bundle_spec(bundle: Bundle) -> dict[str, tuple[tuple[int, ...], str]]:
    """The arrays the bundle's RES image side returns: key -> (shape, dtype name)."""
    return {k: (tuple(int(n) for n in s), str(np.dtype(d))) for k, (s, d) in
            bundle.res_image_side_spec().items()}  # fmt: skip


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
    spec = bundle_spec(bundle)
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
        problem = _unsound_partial(partial, spec, digests) if same else None
        mode = "r+" if same and problem is None else "w"
        if problem is not None:
            report.log(f"{partial}: {problem}; building the index again")
        elif same:
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
        # read back as a query will read it (resumed views included) before it is renamed
        check_values(load_res_index(partial), spec)
    with open(partial, "rb+") as fh:
        os.fsync(fh.fileno())
    os.replace(partial, out)
    report.log(
        f"RES index: {len(cams)} views in {time.perf_counter() - t0:.1f} s "
        f"({out.stat().st_size / 2**20:.1f} MiB at {out})"
    )
    return out


def _unsound_partial(
    partial: Path, spec: dict[str, tuple[tuple[int, ...], str]], digests: dict[str, str]
) -> str | None:
    """Why the finished views of a partial index (same inputs) cannot be kept, or None: they
    must pass the index's own reader, hold this bundle's arrays and this image's digest."""
    try:
        _links_inside(partial)
        with h5py.File(partial, "r") as f:
            views = f.get("views", getlink=True)
            if not isinstance(views, h5py.HardLink) or not isinstance(f["views"], h5py.Group):
                return "'views' is not a group"
            for name in f["views"]:
                g = f["views"][name]
                if not isinstance(g, h5py.Group):
                    return f"'views/{name}' is not a group"
                if DONE_ATTR not in g.attrs:
                    continue  # cut off while being written: made again
                if str(g.attrs[DONE_ATTR]) != digests.get(name):
                    return f"view '{name}' was indexed from another image"
                arrays = {k: g[k][()] for k in spec if isinstance(g.get(k), h5py.Dataset)}
                _check_arrays(arrays, spec, f"view '{name}'")
    except GoiError as e:
        return str(e)
    except (OSError, KeyError, ValueError, TypeError, RuntimeError) as e:
        return f"unreadable ({str(e)[:120]})"
    return None


def _check_arrays(
    arrays: dict[str, np.ndarray], spec: dict[str, tuple[tuple[int, ...], str]], where: str
) -> None:
    """The image side's arrays against the declared spec (shape and dtype per key), and
    their values finite."""
    for key, (shape, dtype) in spec.items():
        a = arrays.get(key)
        if a is None:
            raise GoiError(f"{where}: array '{key}' is missing")
        if tuple(a.shape) != shape or str(a.dtype) != dtype:
            raise GoiError(
                f"{where}: array '{key}' is {a.dtype} {list(a.shape)}, the bundle declares "
                f"{dtype} {list(shape)}"
            )
        if a.dtype.kind in "fc" and not np.isfinite(a).all():
            raise GoiError(
                f"{where}: array '{key}' holds NaN or infinite values; build the index again "
                "(goi index-res)"
            )


def _links_inside(path: Path) -> None:
    """Every object of the index reached by a hard link and stored in the file: an external
    link, a soft link or a dataset whose data lives in another file (external storage, a
    virtual dataset) would make a reader open what the index names."""
    try:
        with h5py.File(path, "r") as f:
            todo: list[tuple[str, h5py.Group]] = [("", f)]
            while todo:
                prefix, g = todo.pop()
                for name in g:
                    where = f"{prefix}{name}"
                    link = g.get(name, getlink=True)
                    if not isinstance(link, h5py.HardLink):
                        raise GoiError(
                            f"{path}: '{where}' is a {type(link).__name__} (to "
                            f"{getattr(link, 'filename', '') or getattr(link, 'path', '?')}); "
                            "an index holds its arrays itself"
                        )
                    obj = g[name]
                    if isinstance(obj, h5py.Group):
                        todo.append((f"{where}/", obj))
                    elif isinstance(obj, h5py.Dataset) and (obj.external or obj.is_virtual):
                        raise GoiError(
                            f"{path}: dataset '{where}' keeps its data in another file; an "
                            "index holds its arrays itself"
                        )
    except (OSError, KeyError, ValueError, RuntimeError, TypeError) as e:
        raise GoiError(f"{path}: not a readable HDF5 file ({str(e)[:200]})") from None


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
    """Open and validate an index (links, schema, version, every view complete and of the
    declared arrays); the values are read by `check_values`."""
    p = Path(path)
    regular_file(p, "RES index")
    _links_inside(p)  # before the validator follows any link
    with open_h5(p, SCHEMA) as f:
        try:
            raw = json.loads(str(f.attrs["arrays"]))
            spec = {k: (tuple(int(n) for n in s), str(np.dtype(d))) for k, (s, d) in raw.items()}
        except (ValueError, TypeError, KeyError, AttributeError) as e:
            raise GoiError(f"{p}: attribute 'arrays' is not a valid array spec ({e})") from None
        for key, (shape, dtype) in spec.items():
            if (
                min(shape, default=1) < 0
                or np.prod(shape, dtype=object) * np.dtype(dtype).itemsize > MAX_ARRAY_BYTES
            ):
                raise GoiError(
                    f"{p}: attribute 'arrays' declares '{key}' {dtype} {list(shape)}, beyond "
                    f"any RES image side ({MAX_ARRAY_BYTES >> 20} MiB an array)"
                )
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


def check_values(index: ResIndex, spec: dict[str, tuple[tuple[int, ...], str]]) -> None:
    """Every view's arrays read once: the bundle's `spec` (key, shape, dtype), finite values."""
    if index.spec != spec:
        key = next(
            (k for k in sorted({*spec, *index.spec}) if index.spec.get(k) != spec.get(k)), "?"
        )
        have, want = index.spec.get(key), spec.get(key)
        raise GoiError(
            f"{index.path}: array '{key}' is declared "
            f"{f'{have[1]} {list(have[0])}' if have else 'nowhere'}, but the bundle's image "
            f"side is {f'{want[1]} {list(want[0])}' if want else 'without it'}; build the index "
            "again (goi index-res)"
        )
    for view in index.views:
        index.image_side(view)


def check_res_index(index: ResIndex, scene: Scene, bundle: Bundle, cams: list[Camera]) -> None:
    """Refuse an index that does not answer for these views of this scene with this bundle,
    naming what differs (bundle, scene, image set, missing views, the arrays and their
    values)."""
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
    odd = next((c for c in held if index.sizes[c.name] != (c.width, c.height)), None)
    if odd is not None:
        w, h = index.sizes[odd.name]
        raise GoiError(
            f"{where}: view '{odd.name}' was indexed at {w}x{h}, the scene's camera is "
            f"{odd.width}x{odd.height}: it was made from another scene"
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
    try:
        check_values(index, bundle_spec(bundle))
    except GoiError as e:
        raise GoiError(f"--res-index: {e}") from None


def _name(cam: Camera | None) -> str | None:
    return cam.name if cam else None

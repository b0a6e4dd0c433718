"""The per-scene RES index (artifact goi.res_index): a bundle's RES image side, run once per
training view on the scene's photos, so a new prompt costs only the prompt side.

Almost all of a RES model's work does not depend on the prompt (SAM's image encoder; OWLv2's
ViT, box and objectness heads; CLIPSeg's visual activations). Indexing a view runs that part
(`Bundle.image_side`) on its photo and stores the named arrays, in the dtypes the bundle
declares (`Bundle.image_side_spec`: float16 where exact enough). A query then runs
`Bundle.res_prompt` once and `Bundle.res_from_image_side` per view.

An index grows: it may hold some of the scene's training views (schema 1.1). A lifted query
indexes the views it needs and keeps them (`GrowingIndex`, stages.query.lift_answer), and
`goi index-res` fills in the rest in `index_order`, so an index cut off at any point holds
views that see the scene from many sides. Views are added by one process at a time
(`IndexWriter`): it holds `<out>.lock` (a second one waits up to --wait seconds, then is
refused), writes into `<out>.partial` (a copy of the index, or a cut-off run's partial of the
same inputs, resumed), one view at a time (a view's digest attribute, written last, marks it
complete), and publishes it on close: read back as a query reads it, then renamed over
`<out>`. A reader never sees a half-written view, and a process killed while writing loses
only the view it was writing (the next writer resumes the partial).

It records the bundle's digest and each view's image digest; `check_res_index` refuses an
index made with another bundle, from another scene or image set, or (where every view is
needed) lacking views, naming what differs.

An index is read like every artifact: its links all hard links inside the file (no external
or soft link, no dataset stored in another file), views as groups, each array of the declared
dtype and shape, which must be the bundle's, and finite values (a NaN in an index is an index
error, not "the RES found nothing"). A resumed `.partial` keeps only views that pass the same
reader, and the finished file is read once more before it is renamed into place.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import h5py
import numpy as np

from stages.core.artifacts import check_writable, open_h5, put, sha256_file, stamp
from stages.core.errors import GoiError
from stages.core.files import (
    OutputBusy,
    check_output_name,
    create_partial,
    finish_partial,
    output_lock,
    partial_exists,
    refuse_inputs,
    regular_file,
)
from stages.core.hdf5 import read_h5
from stages.core.params import Range
from stages.core.report import SILENT, Report
from stages.models.bundle import Bundle, load_bundle
from stages.scene.cameras import Camera
from stages.scene.scene import Scene

SCHEMA = "goi.res_index"

#: The per-view attribute written after a view's arrays: its presence marks the view complete.
DONE_ATTR = "image_sha256"
#: No RES image side stores more than this per array (SAM ViT-H: 2 MiB, OWLv2 large: ~10 MiB):
#: a spec declaring more is refused before any array is read.
MAX_ARRAY_BYTES = 1 << 30


#: Seconds a process waits while another adds views to the same index (--wait, --index-wait).
INDEX_WAIT_S = 600.0


@dataclass
class ResIndexRun:
    bundle: Path
    """Model bundle whose RES image side is indexed (a RES with a prompt-independent image
    side: Grounded-SAM's SAM, OWLv2 + SAM, CLIPSeg; docs/models.md)."""
    out: Path
    """The index to write (HDF5, schema goi.res_index). An index of the same bundle and photos
    that lacks views (a lifted query's, or one cut off) is filled in; a cut-off run's
    <out>.partial is resumed."""
    force: bool = False
    """Build the index anew over an existing one (of any bundle or scene)."""
    part: str | None = None
    """K/N: index only part K of N of the views (every N-th view of the index order, from the
    K-th) into --out, so that N processes index one scene at once; `--merge` joins the parts
    (goi batch's index_jobs)."""
    threads: Annotated[int | None, Range(ge=1, le=4096)] = None
    """onnxruntime threads of this process (default: one per core). Processes indexing at
    once (--part) each take a share of the cores."""
    wait: Annotated[float, Range(ge=0, le=86_400)] = INDEX_WAIT_S
    """Seconds to wait while another goi process adds views to the same index before giving up
    (0: refuse at once)."""


def index_order(cams: list[Camera], held: Iterable[str] = ()) -> list[Camera]:
    """The views in the order an index is filled when no prompt guides the choice: the ones it
    holds (in `held`'s order), then farthest-point sampling on the camera poses
    (`camera_distance`), so that any prefix sees the scene from as many sides as that many
    views can: the next view is the one farthest from every view taken. With nothing held the
    first is the medoid (the view nearest to all others), so the order does not depend on how
    the views are named."""
    if not cams:
        return []
    dist = camera_distance(cams)  # [V, V]
    index = {c.name: i for i, c in enumerate(cams)}
    order = list(dict.fromkeys(index[v] for v in held if v in index))
    if not order:
        order = [int(np.argmin(dist.sum(1)))]
    taken = np.zeros(len(cams), bool)
    taken[order] = True
    nearest = dist[order].min(0)  # [V] distance to the nearest view taken
    while len(order) < len(cams):
        j = int(np.argmax(np.where(taken, -np.inf, nearest)))
        order.append(j)
        taken[j] = True
        nearest = np.minimum(nearest, dist[j])
    return [cams[i] for i in order]


def camera_distance(cams: list[Camera]) -> np.ndarray:
    """[V, V] the cameras' pose distance (stages.query.views.pose_distance)."""
    from stages.query.views import pose_distance

    centers = np.array([c.center for c in cams], np.float64)  # [V, 3]
    axes = np.array([c.R[2] for c in cams], np.float64)  # [V, 3] optical axes, world frame
    axes /= np.maximum(np.linalg.norm(axes, axis=1, keepdims=True), 1e-12)
    return pose_distance(centers, axes)


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
    """The bundle, its RES (or SAM alone) opened and checked; refused when it has no image
    side to index."""
    bundle = bundle_dir if isinstance(bundle_dir, Bundle) else load_bundle(bundle_dir)
    if not bundle.has_res and not bundle.has_sam:
        raise GoiError(
            f"{option}: {bundle.root} has no RES ('res', 'grounded', 'owl_sam', 'clipseg') nor "
            "SAM ('sam'); nothing to index"
        )
    if not bundle.indexable:
        raise GoiError(
            f"{option}: the RES of {bundle.root} has no prompt-independent image side to index; "
            "use it directly (--bundle) instead of --res-index"
        )
    bundle.check_index()
    return bundle


def bundle_spec(bundle: Bundle) -> dict[str, tuple[tuple[int, ...], str]]:
    """The arrays the bundle's RES image side returns: key -> (shape, dtype name)."""
    return {k: (tuple(int(n) for n in s), str(np.dtype(d))) for k, (s, d) in
            bundle.image_side_spec().items()}  # fmt: skip


def _partial(out: Path) -> Path:
    return out.with_name(out.name + ".partial")


def _duration(seconds: float) -> str:
    s = max(0, round(seconds))
    return f"{s} s" if s < 90 else f"{s // 60} min {s % 60:02d} s"


@contextlib.contextmanager
def _index_lock(
    out: Path, option: str, wait: float, report: Report, wait_option: str
) -> Iterator[None]:
    """`output_lock` on the index, waiting up to `wait` seconds while another goi process
    holds it (it is adding views: they are there when it lets go)."""
    deadline = time.monotonic() + wait
    told = False
    while True:
        stack = contextlib.ExitStack()
        try:
            stack.enter_context(output_lock(out, option))
        except OutputBusy as e:
            left = deadline - time.monotonic()
            if left <= 0:
                if wait <= 0:
                    raise
                raise GoiError(f"{e} (waited {_duration(wait)}; {wait_option})") from None
            if not told:
                report.log(f"{e.args[0].split('; ')[0]}: waiting for it (up to {_duration(wait)})")
                told = True
            time.sleep(min(0.25, left))
            continue
        with stack:
            yield
        return


class IndexWriter:
    """Adds views to the index at `out`, one process at a time (see the module doc): used as a
    context manager, it holds the lock, writes into `<out>.partial` and publishes it as `out`
    when the block ends, however it ends, when it holds a view `out` lacks. `fresh` starts from
    nothing instead of from `out` (goi index-res --force)."""

    def __init__(
        self,
        scene: Scene,
        bundle: Bundle,
        out: Path,
        report: Report = SILENT,
        wait: float = 0.0,
        fresh: bool = False,
        option: str = "--out",
        wait_option: str = "--wait",
    ):
        self.scene = scene
        self.cams = scene.views("train")
        self.bundle = bundle
        self.out = Path(out)
        self.partial = _partial(self.out)
        self.report = report
        self.wait = wait
        self.fresh = fresh
        self.option = option
        self.wait_option = wait_option
        check_output_name(self.out, option)
        _not_a_link(self.out, option)
        check_output_name(self.partial, option)
        self.spec = bundle_spec(bundle)
        self.digests = image_digests(scene, self.cams)
        self.inputs = {
            "bundle": bundle.digest(),
            "images": _combined(self.digests),
            "cameras": scene.cameras_digest(),
        }
        self.views: dict[str, str] = {}  # the complete views of the partial file, in its order
        self.planned: int | None = None  # views the caller means to add: the time left
        self.seconds: list[float] = []  # each view indexed by this writer
        self._f: h5py.File | None = None
        self._stack = contextlib.ExitStack()

    def __enter__(self) -> IndexWriter:
        self._stack.enter_context(
            _index_lock(self.out, self.option, self.wait, self.report, self.wait_option)
        )
        try:
            self._prepare()
        except BaseException:
            self._stack.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            self._finish()
        finally:
            self._stack.close()

    def _published(self) -> ResIndex | None:
        """The index at `out` when it exists and may be added to (this bundle, these photos;
        checked like any index), else None (refused: another bundle, scene or image set)."""
        if self.fresh or not (self.out.exists() or self.out.is_symlink()):
            return None
        index = load_res_index(self.out)
        check_res_index(index, self.scene, self.bundle, self.cams, complete=False,
                        option=self.option)  # fmt: skip
        return index

    def _prepare(self) -> None:
        published = self._published()  # read once the lock is held: no one else adds now
        mode = "w"
        if partial_exists(self.partial, self.option):
            try:
                with read_h5(self.partial) as f:
                    same = json.loads(f.attrs.get("inputs", "{}")) == self.inputs
            except (OSError, ValueError):
                same = False
            problem = _unsound_partial(self.partial, self.spec, self.digests) if same else None
            if problem is not None:
                self.report.log(f"{self.partial}: {problem}; building the index again")
            elif same:
                self.report.log(f"resuming {self.partial}")
                mode = "r+"
        if mode == "w":
            create_partial(self.partial, self.option)
            if published is not None:  # start from the published views
                _copy_into(self.out, self.partial)
                mode = "r+"
        self._f = h5py.File(self.partial, mode, track_order=True)
        f = self._f
        if mode == "w":
            f.attrs.update(
                bundle_name=self.bundle.name,
                res_kind=self.bundle.index_kind,
                arrays=json.dumps({k: [list(s), d] for k, (s, d) in self.spec.items()}),
            )
            f.create_group("views", track_order=True)
        views = f["views"]
        for v in list(views):
            if DONE_ATTR not in views[v].attrs:
                del views[v]  # cut off while being written
        self.views = {v: str(views[v].attrs[DONE_ATTR]) for v in views}
        if published is not None:  # a resumed partial lacking views of the published index
            for v in published.views:
                if v not in self.views:
                    self._write(v, published.image_side(v), published.sizes[v])
        self._stamp()

    def _stamp(self) -> None:
        assert self._f is not None
        stamp(self._f, SCHEMA, self.inputs)
        self._f.attrs.update(
            bundle_sha256=self.inputs["bundle"],
            images_sha256=self.inputs["images"],
            cameras_sha256=self.inputs["cameras"],
            n_views=len(self.cams),
        )

    def image_side(self, view: str) -> dict[str, np.ndarray]:
        """A view's arrays from the partial file (a view this writer holds)."""
        assert self._f is not None
        g = self._f["views"][view]
        arrays = {k: g[k][()] for k in self.spec}
        _check_arrays(arrays, self.spec, f"{self.partial}: view '{view}'")
        return arrays

    def add(self, cam: Camera) -> dict[str, np.ndarray]:
        """Index one view (the bundle's image side on its photo), or read it when held."""
        if cam.name in self.views:
            return self.image_side(cam.name)
        t = time.perf_counter()
        arrays = self.bundle.image_side(self.scene.load_image(cam))
        _check_arrays(arrays, self.spec, f"{self.bundle.where}: image side of view {cam.name}")
        self._write(cam.name, arrays, (cam.width, cam.height))
        self.seconds.append(time.perf_counter() - t)
        n = len(self.seconds)
        eta = ""
        if self.planned is not None and self.planned > n:
            eta = f"; about {_duration(float(np.mean(self.seconds)) * (self.planned - n))} left"
        of = f" of {self.planned}" if self.planned is not None else ""
        self.report.log(
            f"indexed view {cam.name} ({n}{of}, {self.seconds[-1]:.1f} s; {len(self.views)} of "
            f"{len(self.cams)} views in the index{eta})"
        )
        return arrays

    def copy_from(self, index: ResIndex, view: str) -> None:
        """A view of another index of the same bundle and photos (a part), copied in."""
        if view in self.views:
            return
        if index.views[view] != self.digests.get(view):
            raise GoiError(f"--merge: {index.path}: view '{view}' was indexed from another image")
        self._write(view, index.image_side(view), index.sizes[view])

    def _write(self, view: str, arrays: dict[str, np.ndarray], size: tuple[int, int]) -> None:
        assert self._f is not None
        g = self._f["views"].create_group(view)
        g.attrs.update(width=size[0], height=size[1])
        for key in self.spec:
            put(g, key, arrays[key])
        g.attrs[DONE_ATTR] = self.digests[view]
        self._f.flush()
        self.views[view] = self.digests[view]

    def _finish(self) -> None:
        """Publish the partial file when it holds a view the index lacks; else remove it."""
        if self._f is None:
            return
        self._stamp()  # `created` becomes the time the last view was written
        self._f.close()
        self._f = None
        try:
            held = set(load_res_index(self.out).views) if self.out.is_file() and not self.fresh \
                else set()  # fmt: skip
        except GoiError:
            held = set()
        if not self.views or (set(self.views) <= held and not self.fresh):
            self.partial.unlink(missing_ok=True)  # nothing new: the index stays as it is
            return
        # read back as a query will read it (resumed views included) before it is renamed
        check_values(load_res_index(self.partial), self.spec)
        finish_partial(self.partial, self.out)


def _not_a_link(path: Path, option: str) -> None:
    """An index that views are added to is a regular file: publishing renames the grown index
    over `path`, which would replace a symbolic link, not follow it."""
    if path.is_symlink():
        raise GoiError(
            f"{option}: {path} is a symbolic link; goi adds views to an index only as a "
            "regular file (name the file it points to)"
        )


def _copy_into(src: Path, partial: Path) -> None:
    """The published index's bytes into the (new, empty) partial file, never through a link."""
    fd = os.open(partial, os.O_WRONLY | os.O_TRUNC | os.O_NOFOLLOW)
    try:
        with open(src, "rb") as fin, os.fdopen(fd, "wb", closefd=False) as fout:
            shutil.copyfileobj(fin, fout, 1 << 22)
    finally:
        os.close(fd)


def _part(part: str | None, cams: list[Camera]) -> list[Camera]:
    """The views of --part K/N: every N-th view of the index order, from the K-th."""
    if part is None:
        return cams
    try:
        k, n = (int(x) for x in part.split("/"))
    except ValueError:
        raise GoiError(f"--part: {part!r} is not K/N (e.g. 1/4)") from None
    if not 1 <= k <= n:
        raise GoiError(f"--part: {part!r}: K must be between 1 and N")
    if k > len(cams):
        raise GoiError(
            f"--part: {part!r}: the scene has {len(cams)} training views, so part {k} holds "
            f"none (K must be at most {len(cams)})"
        )
    return index_order(cams)[k - 1 :: n]


def build_res_index(
    scene: Scene, run: ResIndexRun, report: Report = SILENT, merge: Sequence[Path] = ()
) -> Path:
    """Index the scene's training views (or --part of them) in `index_order`, adding to an
    index of the same bundle and photos at `run.out`; the views of the `merge` indexes (parts)
    are copied, not computed. Returns the index's path."""
    out = Path(run.out)
    check_output_name(out, "--out")
    check_writable(out, True, "--out")  # not a directory, not an input, its directory there
    partial = _partial(out)
    check_output_name(partial, "--out")
    cams = scene.views("train")
    images = [scene.image_path(c) for c in cams]  # every photo found before any work
    refuse_inputs(
        {"--out": [out, partial]},
        [scene.ply_path, *scene.camera_files, run.bundle, *images, *merge],
    )
    target = _part(run.part, cams)
    if run.threads is not None:
        from stages.models.onnx_io import set_threads

        set_threads(run.threads)
    bundle = indexable_bundle(Path(run.bundle))
    parts = []
    for path in merge:
        index = load_res_index(path)
        check_res_index(index, scene, bundle, cams, complete=False, option="--merge")
        parts.append(index)
    if not run.force and (out.exists() or out.is_symlink()):
        try:
            held = load_res_index(out)
            check_res_index(held, scene, bundle, cams, complete=False, option="--out")
        except GoiError as e:
            raise GoiError(f"{e}; or pass --force to build it again over it") from None
        if all(c.name in held.views for c in target):
            raise GoiError(
                f"--out: {out} already exists and holds all {len(target)} views; pass --force "
                "to build it again"
            )
    t0 = time.perf_counter()
    with IndexWriter(scene, bundle, out, report, run.wait, fresh=run.force) as w:
        want = {c.name for c in target}
        todo = [c for c in index_order(cams, w.views) if c.name in want and c.name not in w.views]
        copied = 0
        for c in list(todo):  # the parts' views, in the index's order
            part = next((p for p in parts if c.name in p.views), None)
            if part is not None:
                w.copy_from(part, c.name)
                todo.remove(c)
                copied += 1
        if copied:
            report.log(f"{copied} views from {len(parts)} parts (--merge)")
        if len(w.views) > copied:
            report.log(f"{len(w.views) - copied} of {len(cams)} views already indexed")
        if todo:
            report.log(f"indexing {len(todo)} views into {out} (the RES image side of each photo)")
        w.planned = len(todo)
        for cam in todo:
            w.add(cam)
        n = len(w.views)
    report.log(
        f"RES index: {n} of {len(cams)} views, {len(todo)} indexed in "
        f"{time.perf_counter() - t0:.1f} s ({out.stat().st_size / 2**20:.1f} MiB at {out})"
    )
    return out


def _unsound_partial(
    partial: Path, spec: dict[str, tuple[tuple[int, ...], str]], digests: dict[str, str]
) -> str | None:
    """Why the finished views of a partial index (same inputs) cannot be kept, or None: they
    must pass the index's own reader, hold this bundle's arrays and this image's digest."""
    try:
        _links_inside(partial)
        with read_h5(partial) as f:
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
        with read_h5(path) as f:
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
        with read_h5(self.path) as f:
            g = f["views"].get(view)
            # another index renamed over this one since it was opened: a grown one holds the
            # same view (same digest); anything else is refused
            if not isinstance(g, h5py.Group) or str(g.attrs.get(DONE_ATTR)) != self.views[view]:
                raise GoiError(f"--res-index: {self.path} changed while it was read; ask again")
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


#: file identity -> the views whose values `check_values` has read in this process. A process
#: that opens one index for prompt after prompt (goi view, goi eval) reads each view's arrays
#: once to check them, not at every open (8 views of OWLv2 + SAM 2.1: 190 MB a prompt); a file
#: written again is another identity (inode, size, mtime), and `ResIndex.image_side` checks
#: what it reads every time. The identity is the file's, not its name's: the partial file an
#: `IndexWriter` checked before renaming it over the index is not read again under that name.
_CHECKED: dict[tuple[int, int, int, int], set[str]] = {}


def _identity(path: Path) -> tuple[int, int, int, int]:
    st = os.stat(path)
    return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)


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
    checked = _CHECKED.setdefault(_identity(index.path), set())
    for view in index.views:
        if view not in checked:
            index.image_side(view)
            checked.add(view)


def check_res_index(
    index: ResIndex,
    scene: Scene,
    bundle: Bundle,
    cams: list[Camera],
    complete: bool = True,
    option: str = "--res-index",
) -> None:
    """Refuse an index that does not answer for these views of this scene with this bundle,
    naming what differs (bundle, scene, image set, the arrays and their values; with
    `complete`, missing views: an index that may grow lacks them rightly)."""
    where = f"{option}: {index.path}"
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
    if missing and complete:
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
        raise GoiError(f"{option}: {e}") from None


class GrowingIndex:
    """The index a lifted query reads and adds to (--res-index FILE with its --bundle): the
    views the file holds, read and checked like any index (a missing file holds none), and,
    from the first view the query asks for that it lacks, an `IndexWriter` that indexes it.
    `close()` publishes the views added (the object may add more after it). Reads like a
    `ResIndex` (path, bundle_sha256, views, image_side)."""

    def __init__(
        self,
        path: Path,
        scene: Scene,
        bundle: Bundle,
        report: Report = SILENT,
        wait: float = INDEX_WAIT_S,
    ):
        self.path = Path(path)
        self.scene = scene
        self.bundle = bundle
        self.report = report
        self.wait = wait
        self.bundle_sha256 = bundle.digest()
        self.cams = scene.views("train")
        self.writer: IndexWriter | None = None
        self.planned: int | None = None
        check_output_name(self.path, "--res-index")
        parent = self.path.parent if str(self.path.parent) else Path(".")
        if not parent.is_dir():
            raise GoiError(f"--res-index: {self.path}: directory {parent} does not exist")
        self.published = self._open()
        if not self.complete:
            _not_a_link(self.path, "--res-index")  # before any work
            for c in self.cams:  # every photo it may index found before any work
                scene.image_path(c)

    def _open(self) -> ResIndex | None:
        if not (self.path.exists() or self.path.is_symlink()):
            return None
        index = load_res_index(self.path)
        check_res_index(index, self.scene, self.bundle, self.cams, complete=False)
        return index

    @property
    def views(self) -> dict[str, str]:
        if self.writer is not None:
            return self.writer.views
        return self.published.views if self.published is not None else {}

    @property
    def complete(self) -> bool:
        return all(c.name in self.views for c in self.cams)

    def image_side(self, view: str) -> dict[str, np.ndarray]:
        if self.writer is not None and view in self.writer.views:
            return self.writer.image_side(view)
        if self.published is None or view not in self.published.views:
            raise GoiError(f"--res-index: {self.path} holds no view '{view}'")
        return self.published.image_side(view)

    def plan(self, n: int) -> None:
        """The caller means to add about `n` views (each progress line says the time left)."""
        self.planned = n
        if self.writer is not None:
            self.writer.planned = n + len(self.writer.seconds)

    def add(self, cam: Camera) -> None:
        """Index `cam` (once this process holds the index: a second one waits for it)."""
        if self.writer is None:
            writer = IndexWriter(self.scene, self.bundle, self.path, self.report, self.wait,
                                 option="--res-index", wait_option="--index-wait")  # fmt: skip
            self.writer = writer.__enter__()
            writer.planned = self.planned
        self.writer.add(cam)

    def close(self) -> None:
        """Publish the views added (renamed over the index) and let the index go."""
        if self.writer is None:
            return
        writer, self.writer = self.writer, None
        writer.__exit__(None, None, None)
        self.published = load_res_index(self.path) if self.path.is_file() else None

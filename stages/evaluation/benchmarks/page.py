"""The HTML page of `goi eval --benchmark`: per scene and for the mean over scenes, one row per
variant and metric family, each labelled with the protocol it follows; the published figures
beside them with their source."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from stages.core.artifacts import write_png
from stages.core.files import make_dir
from stages.evaluation.benchmarks.common import BenchmarkScene
from stages.evaluation.benchmarks.published import (
    NOTES,
    PUBLISHED,
    published_means,
    published_rows,
    published_scenes,
)
from stages.evaluation.benchmarks.scoring import PROTOCOLS
from stages.evaluation.report import esc, fmt, page_files_dir, rel, write_page
from stages.query.prompts import safe_name

GOI_ROW = "goi (paper's per-image IoU/mPA/mP, goi's metrics.py; query -> mean)"


def _table(rows: list[tuple[str, str, dict]], keys: list[str]) -> str:
    head = "".join(f"<th>{esc(k)}</th>" for k in keys)
    out = [f"<table><tr><th class='l'>variant / method</th><th class='l'>protocol</th>{head}</tr>"]
    for label, protocol, figs in rows:
        cells = "".join(f"<td>{fmt(figs.get(k))}</td>" for k in keys)
        out.append(
            f"<tr><td class='l'>{esc(label)}</td><td class='l'>{esc(protocol)}</td>{cells}</tr>"
        )
    return "".join(out) + "</table>"


def _rows(figs_of: dict, protocol: str) -> list[tuple[str, str, dict]]:
    rows = []
    for v, figs in figs_of.items():
        rows.append((v, protocol, figs["protocol"]))
        rows.append((v, GOI_ROW, figs["goi"]))
    return rows


def _mean(values: list) -> float | None:
    return None if any(x is None for x in values) else float(np.mean(values))


def _seed_tables(b: dict) -> str:
    """The spread of the seeded variant's figures over --seeds: the mean over scenes, and per
    scene each figure and its widest queries."""
    sd = b["seeds"]
    seeds = sd["seeds"]
    head = "".join(f"<th>seed {x}</th>" for x in seeds) + "<th>range</th><th>sd</th>"
    out = [
        f"<h2>Spread of {esc(sd['variant'])} over seeds {esc(', '.join(map(str, seeds)))}</h2>",
        f"<p class='key'>{esc(sd['what'])}. A difference between two runs smaller than the "
        "range is within the fit's own noise.</p>",
    ]

    def rows(spreads: dict[str, dict]) -> str:
        cells = []
        for label, sp in spreads.items():
            vals = "".join(f"<td>{fmt(x)}</td>" for x in sp["values"])
            cells.append(
                f"<tr><td class='l'>{esc(label)}</td>{vals}<td>{fmt(sp['range'])}</td>"
                f"<td>{fmt(sp['sd'])}</td></tr>"
            )
        return "".join(cells)

    def figures(sp: dict) -> dict[str, dict]:
        return {
            **{f"protocol {k}": v for k, v in sp["protocol"].items()},
            "goi mIoU": sp["goi_miou"],
        }

    out.append(f"<table><tr><th class='l'>mean over scenes</th>{head}</tr>")
    out.append(rows(figures(sd["mean"])) + "</table>")
    for scene, entry in b["scenes"].items():
        sp = entry["seeds"]
        out.append(f"<table><tr><th class='l'>{esc(scene)}</th>{head}</tr>")
        out.append(rows(figures(sp)))
        widest = dict(list(sp["queries"].items())[:5])
        out.append(rows({f"query {q} (IoU)": v for q, v in widest.items()}) + "</table>")
    return "".join(out)


def benchmark_page(
    path: Path,
    doc: dict,
    scenes: dict[str, BenchmarkScene],
    thumbs: dict[tuple[str, str], dict[str, tuple[str, np.ndarray]]],
) -> None:
    """Write the page and its images: the tables, and per scene, query and variant the first
    frame's prediction (red) against the ground truth (green outline); every frame's figures
    are in report.json."""
    files = page_files_dir(path)
    make_dir(files, "--html")
    b = doc["benchmark"]
    name, protocol = b["name"], b["protocol"]
    keys = list(
        dict.fromkeys(
            [
                *PROTOCOLS[name][1],
                *next(iter(b["scenes"].values()))["variants"][next(iter(doc["variants"]))][
                    "protocol"
                ],
                "mpa",
                "mp",
            ]
        )
    )
    notes = doc["metric_notes"]
    given = list(b["scenes"])
    means = published_means(name, given)
    shown = {label.split(" (published")[0] for _, label, _, _ in means}
    for scene in given:
        shown |= {label.split(" (published")[0] for label, _, _ in published_rows(name, scene)}
    body = [
        f"<p class='key'>benchmark {esc(name)} · {esc(doc['room'])} · goi {esc(doc['goi_version'])}"
        f" · fixed threshold {fmt(doc['threshold'])}</p>",
        f"<p class='key'>protocol: {esc(protocol)}. How goi's binary answer enters it: "
        f"{esc(notes['how_goi_enters'])}. The goi rows: {esc(notes['goi'])}.</p>",
        "<p class='key'>Figures: each query's first frame per variant, goi's prediction in red "
        "on goi's rendering, the ground truth outlined in green.</p>",
        *([f"<p class='key'>{esc(notes['full_noise'])}.</p>"] if "full_noise" in notes else []),
    ]
    if shown:
        pub = PUBLISHED.get(name)
        where = (
            f" Source of the GOI paper's rows: {esc(pub['source'])}; {esc(pub['note'])}."
            if pub
            else ""
        )
        body.append(
            f"<p class='key'>Published figures shown: {esc(', '.join(sorted(shown)))}, each row "
            "naming the protocol it was measured under and its source, and set beside goi's "
            "only over the same scenes: a mean row is the printed mean where it covers exactly "
            "the scenes given, else the mean of the row's per-scene figures over the given "
            f"scenes it has, beside goi's mean over those scenes.{where}"
            + (f" {esc(NOTES[name])}." if name in NOTES else "")
            + " They were measured with other RES models, features and training.</p>"
        )
    else:
        have = published_scenes(name)
        body.append(
            "<p class='key'>No published figures are shown: "
            + (
                f"none was published for the scenes given ({esc(', '.join(given))}); "
                f"{esc(name)} has published figures for {esc(', '.join(have))}.</p>"
                if have
                else "goi has no citable number for this benchmark.</p>"
            )
        )
    mean = {v: {"protocol": r["protocol"], "goi": r["goi"]} for v, r in doc["variants"].items()}
    same = [(lab, pr, f) for sc, lab, pr, f in means if set(sc) == set(given)]
    body.append(f"<h2>Mean over {len(given)} scene(s)</h2>")
    body.append(_table(_rows(mean, protocol) + same, keys))
    subsets = dict.fromkeys(sc for sc, *_ in means if set(sc) != set(given) and len(sc) > 1)
    for sub in subsets:  # goi's mean over the published scenes given, beside theirs
        part = {
            v: {
                k: {m: _mean([b["scenes"][sc]["variants"][v][k].get(m) for sc in sub])
                    for m in mean[v][k]}
                for k in ("protocol", "goi")
            }
            for v in mean
        }  # fmt: skip
        body.append(
            f"<h2>Mean over the {len(sub)} published scenes given ({esc(', '.join(sub))})</h2>"
        )
        body.append(
            _table(
                _rows(part, protocol) + [(lab, pr, f) for sc, lab, pr, f in means if sc == sub],
                keys,
            )
        )
    if "seeds" in b:
        body.append(_seed_tables(b))
    for scene, entry in b["scenes"].items():
        body.append(
            f"<h2>{esc(scene)}</h2><p class='key'>{entry['n_frames']} frames, "
            f"{entry['n_queries']} queries"
            + (
                f"; skipped as the reference does: {esc('; '.join(entry['skipped'][:5]))}"
                if entry["skipped"]
                else ""
            )
            + "</p>"
        )
        body.append(_table(_rows(entry["variants"], protocol) + published_rows(name, scene), keys))
        variants = list(entry["variants"])
        body.append(
            "<table><tr><th class='l'>query</th>"
            + "".join(f"<th>{esc(v)} IoU (protocol)</th>" for v in variants)
            + "</tr>"
        )
        for q in scenes[scene].queries:
            cells = []
            for v in variants:
                ious = [d.get("iou") for d in entry["variants"][v]["queries"][q.id].values()]
                ious = [x for x in ious if x is not None]
                cells.append(f"<td>{fmt(float(np.mean(ious)) if ious else None)}</td>")
            body.append(f"<tr><td class='l'>{esc(q.text)}</td>{''.join(cells)}</tr>")
        body.append("</table>")
        for q in scenes[scene].queries:
            figs = []
            for v in variants:
                if q.id not in thumbs.get((scene, v), {}):
                    continue
                key, img = thumbs[(scene, v)][q.id]
                png = f"{safe_name(scene)}_{safe_name(q.id)}_{safe_name(v)}.png"
                write_png(files / png, img, force=True)
                figs.append(
                    f"<figure><img src='{rel(files / png, path)}' alt='{esc(v)}'>{esc(v)}: "
                    f"{esc(q.text)}, frame {esc(key)}</figure>"
                )
            body.append("<div>" + "".join(figs) + "</div>")
    body.append("<h2>Timings (s)</h2><table>")
    for k, t in doc["timings_s"].items():
        body.append(f"<tr><td class='l'>{esc(k)}</td><td>{fmt(float(t))}</td></tr>")
    body.append("</table>")
    write_page(path, f"goi eval --benchmark {name}", "".join(body))

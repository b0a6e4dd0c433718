"""Replica as GOI scores it (Quyans/GOI-Hyperplane, eval_seg.py `replica_top7`).

<root>/<scene>/test/sem/<prefix>_<N>.png (a class-id map, cv2 grey) and test/top_list.json
{"<prefix>_<N>.png": [{"class_name", "id"}, ...]}: the prompts of each image, ground truth
sem == id. The image's view is rgb_<N> (the script's rendered mask name). An image whose view
has no camera is skipped with a warning, as the script skips a missing rendering.
"""

from __future__ import annotations

from pathlib import Path

from stages.core.errors import GoiError
from stages.core.files import read_json
from stages.evaluation.benchmarks.common import (
    BenchmarkScene,
    Frame,
    Query,
    camera_or_skip,
    checked_size,
    query_id,
    read_grey_cv2,
    require_dir,
    skip,
)
from stages.scene.cameras import Camera

SCENES = ("office0", "office1", "room0", "room1")


def read_replica_goi(root: Path, scene: str, cameras: list[Camera]) -> BenchmarkScene:
    test = require_dir(root / scene / "test", "Replica as GOI scores it keeps test/sem/ there")
    sem = require_dir(test / "sem", "the class-id maps <prefix>_<N>.png")
    listing = read_json(test / "top_list.json", "missing; it lists each image's prompts")
    if not isinstance(listing, dict):
        raise GoiError(
            f"{test / 'top_list.json'}: expected an object {{image: [{{class_name, id}}]}}"
        )
    by_name = {c.name: c for c in cameras}
    out = BenchmarkScene(scene, test, [], [])
    queries: dict[str, Query] = {}
    for f in sorted(sem.glob("*.png")):
        img_name = f.name.split(".")[0]
        key = img_name + ".png"
        where = f"{test / 'top_list.json'}: {key!r}"
        if key not in listing:
            raise GoiError(f"{where}: missing; every class-id map in {sem} needs its prompt list")
        entries = listing[key]
        if not isinstance(entries, list):
            raise GoiError(f"{where}: expected a list of {{class_name, id}}")
        parts = img_name.split("_")
        if len(parts) < 2:
            raise GoiError(f"{f}: expected <prefix>_<N>.png")
        view = "rgb_" + parts[1]
        cam = camera_or_skip(out, by_name, view, f)
        if cam is None:
            continue
        frame = Frame(img_name, checked_size(cam, f, "class-id map"), f, {})
        ids = read_grey_cv2(f, "class-id map")
        for k, e in enumerate(entries):
            if not isinstance(e, dict) or not isinstance(e.get("class_name"), str):
                raise GoiError(f"{where}[{k}]: field 'class_name' is missing or not a string")
            cid = e.get("id")
            if not isinstance(cid, int) or isinstance(cid, bool) or not 0 <= cid <= 255:
                raise GoiError(f"{where}[{k}]: field 'id' must be a class id 0-255, found {cid!r}")
            text = e["class_name"]
            q = queries.setdefault(text, Query(query_id(text), text))
            if q.id in frame.gts:  # the script scores such an entry twice; goi keeps the last
                skip(
                    out,
                    f"{where}[{k}]: class {text!r} listed twice for the image; the last id kept",
                )
            frame.gts[q.id] = ids == cid
        out.frames.append(frame)
    out.queries = list(queries.values())
    return out

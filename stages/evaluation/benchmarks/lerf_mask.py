"""LERF-Mask as Gaussian Grouping releases it (render_lerf_mask.py, script/eval_lerf_mask.py).

<root>/<scene>/{images, images_train, sparse, test_mask}: ground truth
test_mask/<k>/<prompt>.png (grey > 128 is in). The folder <k> is an index: render_lerf_mask.py
writes its predictions to `test_mask/str(idx)` for `idx, view in
enumerate(scene.getTestCameras())`, and eval_lerf_mask.py pairs each ground-truth folder with
the prediction folder of the same name. The test cameras are those whose image name (the file
name before its first '.') is not in images_train/, in the loader's order: sorted by image name.
So folder 0 is the first test camera by image name. Folders named after the test cameras'
images (goi's earlier reading) are accepted too; the scene records which layout was found.
"""

from __future__ import annotations

from pathlib import Path

from stages.core.errors import GoiError
from stages.evaluation.benchmarks.common import (
    BenchmarkScene,
    Frame,
    Query,
    checked_size,
    image_name,
    query_id,
    read_grey,
    require_dir,
    sorted_by_image,
)
from stages.scene.cameras import Camera

SCENES = ("figurines", "ramen", "teatime")

#: the two layouts of test_mask/, as the scene's `layout` records them
NUMBERED = "numbered folders (as released: k = the k-th test camera by image name)"
NAMED = "folders named after the test cameras' images"


def test_cameras(d: Path, cameras: list[Camera]) -> tuple[set[str], list[Camera]]:
    """(the training image names, the test cameras in the release's order): readColmapSceneInfo
    with train_split: `train_names = [n.split('.')[0] for n in sorted(os.listdir(images_train))]`,
    test = the cameras (sorted by image_name) whose image_name is not among them."""
    train_dir = require_dir(d / "images_train", "LERF-Mask's training images tell the test views")
    trained = {p.name.split(".")[0] for p in train_dir.iterdir()}
    return trained, [c for c in sorted_by_image(cameras) if image_name(c) not in trained]


def read_lerf_mask(root: Path, scene: str, cameras: list[Camera]) -> BenchmarkScene:
    d = root / scene
    masks = require_dir(d / "test_mask", "LERF-Mask keeps the ground truth in test_mask/<k>/")
    trained, tests = test_cameras(d, cameras)
    out = BenchmarkScene(scene, masks, [], [])
    out.held_out = {c.name for c in tests}
    folders = sorted((p for p in masks.iterdir() if p.is_dir()), key=lambda p: p.name)
    if not folders:
        raise GoiError(f"{masks}: no <k>/ folders of ground-truth masks")
    if not tests:
        raise GoiError(
            f"{d / 'images_train'}: every camera's image is there, so the scene has no test "
            "camera (LERF-Mask's test views are the images not in images_train/)"
        )
    numbered = all(p.name.isdigit() and p.name == str(int(p.name)) for p in folders)
    if numbered:
        out.layout = NUMBERED
        if len(folders) != len(tests):
            raise GoiError(
                f"{masks}: {len(folders)} numbered folders, but the scene has {len(tests)} test "
                "cameras (images not in images_train/); the release has one folder per test "
                "camera, in image-name order"
            )
        pairs = []
        for p in folders:
            k = int(p.name)
            if k >= len(tests):
                raise GoiError(
                    f"{p}: folder {k}, but the {len(tests)} test cameras are numbered "
                    f"0-{len(tests) - 1}"
                )
            pairs.append((p, tests[k]))
    else:
        out.layout = NAMED
        by_name = {image_name(c): c for c in tests}
        pairs = []
        for p in sorted(folders, key=lambda p: p.name.isdigit()):  # a stray name named first
            cam = by_name.get(p.name)
            if cam is None:
                where = "in images_train/" if p.name in trained else "no test camera's image"
                raise GoiError(
                    f"{p}: neither a test-camera index (the release numbers its folders 0-"
                    f"{len(tests) - 1}) nor a test camera's image name ({p.name!r} is {where})"
                )
            pairs.append((p, cam))
    queries: dict[str, Query] = {}
    for view_dir, cam in pairs:
        pngs = sorted(p for p in view_dir.iterdir() if p.name.endswith(".png") and p.is_file())
        if not pngs:
            raise GoiError(f"{view_dir}: no <prompt>.png ground truth")
        frame: Frame | None = None
        seen: dict[str, Path] = {}
        for png in pngs:
            text = png.name.split(".")[0]  # the script's cat_id: a file's name, only data
            if frame is None:
                frame = Frame(
                    view_dir.name, checked_size(cam, png, "ground-truth mask"), view_dir, {}
                )
            else:  # every mask of a view at the view's size, checked before decoding
                checked_size(cam, png, "ground-truth mask", frame.camera)
            q = queries.setdefault(text, Query(query_id(text), text))
            if q.id in seen:
                raise GoiError(
                    f"{png}: a second mask of prompt {text!r} in the view, beside "
                    f"{seen[q.id].name} (the script takes a mask's prompt from its name before "
                    "the first '.')"
                )
            seen[q.id] = png
            frame.gts[q.id] = read_grey(png, "ground-truth mask")
        assert frame is not None
        out.frames.append(frame)
    out.queries = list(queries.values())
    return out

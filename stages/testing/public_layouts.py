"""Small synthetic scenes written in the exact layout of each public benchmark's release, for
the tests and `benchmarks/run.py --suite public-eval`: a trained 3DGS directory (INRIA
point_cloud/iteration_*/point_cloud.ply), the benchmark's annotations of a few frames, features
for the training views, RES masks and the text embeddings of the queries; and
`room_as_lerf_mask`, a goi benchmark room written as Gaussian Grouping releases LERF-Mask.

What each layout follows is what the benchmark's reference code reads or writes, quoted below
from it (../shared/notes/public-benchmarks.md names the files), not what goi's readers expect:
the tests hold the readers to these layouts. The image names are chosen so that a reader which
took a folder or file name for something other than what the reference takes it for would
pair a frame with the wrong camera.

The scene is a room with four boxes (`room_vertex`); the ground truth of a query is the pixels
its box covers most (rendered from the Gaussians' object ids), so a good answer scores high.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from stages.core.errors import GoiError
from stages.render.rasterizer import Rasterizer
from stages.scene.cameras import Camera
from stages.scene.formats.colmap import write_colmap
from stages.scene.formats.inria import write_inria
from stages.scene.gaussians import load_ply, save_ply
from stages.testing.synthetic import ring_cameras, room_vertex

#: object id -> its query text (0 is the room's shell)
NAMES = {0: "wall", 1: "red box", 2: "green box", 3: "blue box", 4: "tall box"}
#: the annotated frames, as indices into the ring of cameras
EVAL_VIEWS = (1, 4)
#: how each benchmark names its cameras' images
PREFIX = {
    "lerf-ovs": "frame_",
    "lerf-mask": "frame_",
    "3d-ovs": "IMG_",
    "goi-m360": "DSCF",
    "replica-goi": "rgb_",
}


def _image_names(benchmark: str, n: int) -> list[str]:
    """The cameras' image names, in name order. LERF's captures are frame_00001, frame_00002,
    ...; 3D-OVS's folder NN is an index, so its images are named otherwise than 00, 01, ...
    (IMG_0100, IMG_0102, ...) and a reader that took NN for a name finds no camera."""
    if benchmark in ("lerf-ovs", "lerf-mask"):
        return [f"frame_{i + 1:05d}" for i in range(n)]
    if benchmark == "3d-ovs":
        return [f"IMG_{100 + 2 * i:04d}" for i in range(n)]
    if benchmark == "goi-m360":
        return [f"DSCF{4660 + i}" for i in range(n)]
    return [f"rgb_{i}" for i in range(n)]


def _write_png(path: Path, image: np.ndarray) -> None:
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), image)


def synthetic_benchmark(
    root: Path,
    benchmark: str,
    scene: str = "toy",
    n: int = 4000,
    n_views: int = 8,
    size: tuple[int, int] = (64, 48),
    dim: int = 16,
    stride: int = 4,
    seed: int = 0,
) -> dict:
    """Write root/{trained/<scene>, bench/..., features, res, text_embeddings.json}; returns
    the paths and what the tests compare with."""
    import cv2

    trained = root / "trained" / scene
    ply = trained / "point_cloud" / "iteration_7000" / "point_cloud.ply"
    ply.parent.mkdir(parents=True)
    v, ids = room_vertex(n, seed=seed, n_objects=4)
    save_ply(ply, v, force=True)
    names = _image_names(benchmark, n_views)
    cams: list[Camera] = ring_cameras(n_views, *size, radius=1.9, height_m=1.5)
    for c, name in zip(cams, names, strict=True):
        c.name, c.image = name, name
    bench = root / "bench"
    sdir = bench / scene
    if benchmark in ("lerf-ovs", "lerf-mask", "3d-ovs"):  # the dataset ships COLMAP + images
        write_colmap(sdir / "sparse" / "0", cams, binary=True)
    else:  # GOI's masks come without cameras: the trained directory has them
        write_inria(trained / "cameras.json", cams)
    rast = Rasterizer.from_gaussians(load_ply(ply))
    onehot = np.eye(ids.max() + 1, dtype=np.float32)[ids]  # [G, K]
    rng = np.random.default_rng(seed)
    objects = rng.normal(size=(ids.max() + 1, dim))
    objects /= np.linalg.norm(objects, axis=1, keepdims=True)
    share = {c.name: rast.render_features(c, onehot).image for c in cams}  # [H, W, K]
    label = {k: (s.argmax(2)) * (s.sum(2) > 0.5) + (s.sum(2) <= 0.5) * -1 for k, s in share.items()}
    for c in cams:  # the datasets' photographs (3D-OVS indexes them; GOI's masks come alone)
        if benchmark in ("lerf-ovs", "lerf-mask", "3d-ovs"):
            rgb = (np.clip(rast.render_rgb(c).image, 0, 1) * 255).astype(np.uint8)
            _write_png(sdir / "images" / f"{c.name}.png", rgb[:, :, ::-1])
    eval_names = [cams[i].name for i in EVAL_VIEWS]
    held_out = set(eval_names) if benchmark == "lerf-mask" else set()
    queries = {1: NAMES[1], 2: NAMES[2], 3: NAMES[3]}
    if benchmark == "3d-ovs":
        queries = dict(NAMES)
    qid = {k: (t.replace(" ", "_") if benchmark == "goi-m360" else t) for k, t in queries.items()}
    # the annotations
    if benchmark == "lerf-ovs":
        # LangSplat eval/evaluate_iou_loc.py, eval_gt_lerfdata:
        #   gt_json_paths = sorted(glob.glob(os.path.join(str(json_folder), 'frame_*.json')))
        #   img_paths = sorted(glob.glob(os.path.join(str(json_folder), 'frame_*.jpg')))
        #   h, w = gt_data['info']['height'], gt_data['info']['width']
        #   idx = int(gt_data['info']['name'].split('_')[-1].split('.jpg')[0]) - 1
        #   label = prompt_data['category']; box = np.asarray(prompt_data['bbox']).reshape(-1)
        #   mask = polygon_to_mask((h, w), prompt_data['segmentation'])
        # and `compressed_sem_feats[i][j] = np.load(feat_paths_lvl[idx])`: idx indexes the
        # renders of the training cameras, which the 3DGS loader sorts by image name
        # (`sorted(cam_infos_unsorted.copy(), key = lambda x : x.image_name)`).
        d = bench / "label" / scene
        d.mkdir(parents=True)
        for i in EVAL_VIEWS:
            c = cams[i]
            objs = []
            for k, text in queries.items():
                m = (label[c.name] == k).astype(np.uint8)
                contours, _ = cv2.findContours(m, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
                if not contours:
                    continue
                poly = max(contours, key=cv2.contourArea).reshape(-1, 2)
                if len(poly) < 3:
                    continue
                x1, y1 = poly.min(0)
                x2, y2 = poly.max(0)
                objs.append({"category": text, "bbox": [[int(x2), int(y2)], [int(x1), int(y1)]],
                             "segmentation": poly.tolist()})  # fmt: skip
            info = {"height": c.height, "width": c.width, "name": f"{c.name}.jpg"}
            (d / f"{c.name}.json").write_text(json.dumps({"info": info, "objects": objs}))
            _write_png(d / f"{c.name}.jpg", np.zeros((c.height, c.width, 3), np.uint8))
    elif benchmark == "lerf-mask":
        # Gaussian Grouping, scene/dataset_readers.py (readColmapSceneInfo, train_split):
        #   train_names = sorted(os.listdir(os.path.join(path, "images_train")))
        #   train_names = [train_name.split('.')[0] for train_name in train_names]
        #   test_cam_infos = the cameras (sorted by image_name) not in train_names
        # render_lerf_mask.py writes its predictions to
        #   for idx, view in enumerate(tqdm(views, ...)):      # views = scene.getTestCameras()
        #       pred_obj_img_path = os.path.join(pred_obj_path, str(idx))
        #       Image.fromarray(pred_obj_mask).save(
        #           os.path.join(pred_obj_img_path, TEXT_PROMPT + ".png"))
        # and script/eval_lerf_mask.py pairs `os.path.join(gt_folder_path, image_name)` with
        # `os.path.join(pred_folder_path, image_name)`, `cat_id = cat_file.split('.')[0]`:
        # so the ground truth's folders are numbered 0, 1, ... over the test cameras by name.
        for c in cams:
            if c.name not in held_out:
                _write_png(sdir / "images_train" / f"{c.name}.jpg", np.zeros((4, 4), np.uint8))
        tests = sorted(eval_names)
        for name in eval_names:
            for k, text in queries.items():
                m = (label[name] == k).astype(np.uint8) * 255
                _write_png(sdir / "test_mask" / str(tests.index(name)) / f"{text}.png", m)
    elif benchmark == "3d-ovs":
        # 3D-OVS dataLoader/llff.py:
        #   self.image_paths = sorted(glob.glob(os.path.join(self.root_dir, 'images/*')))
        #   self.classes = [line.strip() for line in lines]; self.classes.sort()
        #   folders = [f for f in os.listdir(segmentation_path) if os.path.isdir(...)]
        #   self.idxes.append(int(folder))  # to get the camera id
        #   seg_path = os.path.join(self.root_dir, f'segmentations/{folder}/{class_name}.png')
        # int(NN) indexes the poses, which LLFF's poses_bounds.npy lists in sorted image order.
        seg = sdir / "segmentations"
        seg.mkdir(parents=True)
        (seg / "classes.txt").write_text("\n".join(queries.values()) + "\n")
        for i in EVAL_VIEWS:
            c = cams[i]
            for k, text in queries.items():
                _write_png(
                    seg / f"{i:02d}" / f"{text}.png", (label[c.name] == k).astype(np.uint8) * 255
                )
    elif benchmark == "goi-m360":
        # GOI eval_seg.py, m360:
        #   queries = os.listdir(gt_root)                       # gt_root = <root>/<scene>
        #   gt_masks = os.listdir(os.path.join(gt_root, prompt, 'masks'))
        #   img_name = gt_mask.split('.')[0]
        #   rendered_mask_p = os.path.join(saving_root, scene_name, prompt, img_name + '.png')
        # The prompt folder is the query with underscores; the masks' extension is not
        # confirmed from code (any works: the name before the first '.' is the image's).
        for name in eval_names:
            for k in queries:
                m = (label[name] == k).astype(np.uint8) * 255
                _write_png(sdir / qid[k] / "masks" / f"{name}.JPG.png", m)
    elif benchmark == "replica-goi":
        # GOI eval_seg.py, replica_top7:
        #   gt_root = f'{data_root}/{scene_name}/test/sem'; gt_masks = os.listdir(gt_root)
        #   data = json.load(open(f"{data_root}/{scene_name}/test/top_list.json"))
        #   img_name = gt.split('.')[0]; prompt_list = data[img_name + '.png']
        #   prompt, id = prompt_list[i]['class_name'], prompt_list[i]['id']
        #   mask = gt_all_mask == id
        #   rendered_mask_p = os.path.join(saving_root, scene_name, prompt,
        #                                  'rgb_' + img_name.split('_')[1] + '.png')
        top = {}
        for i, name in zip(EVAL_VIEWS, eval_names, strict=True):
            sem = np.where(label[name] >= 0, label[name] * 10 + 3, 0).astype(np.uint8)
            _write_png(sdir / "test" / "sem" / f"sem_{name.split('_')[1]}.png", sem)
            top[f"sem_{i}.png"] = [{"class_name": t, "id": k * 10 + 3} for k, t in queries.items()]
        (sdir / "test" / "top_list.json").write_text(json.dumps(top))
    else:
        raise ValueError(benchmark)
    # features for the training views, RES masks on them, text embeddings
    feats, res = root / "features", root / "res"
    feats.mkdir()
    for c in cams:
        if c.name in held_out:
            continue
        f = share[c.name] @ objects + rng.normal(0, 0.3 / np.sqrt(dim), (c.height, c.width, dim))
        small = cv2.resize(f.astype(np.float32), (c.width // stride, c.height // stride),
                           interpolation=cv2.INTER_AREA)  # fmt: skip
        np.save(feats / f"{c.name}.npy", small.transpose(2, 0, 1).astype(np.float16))
        for k in queries:
            m = (label[c.name] == k).astype(np.uint8) * 255
            if m.any():
                _write_png(res / qid[k] / f"{c.name}.png", m)
    emb = root / "text_embeddings.json"
    emb.write_text(json.dumps({t: objects[k].tolist() for k, t in queries.items()}))
    return {"trained": trained, "bench": bench, "features": feats, "res": res,
            "embeddings": emb, "scene": scene, "cameras": cams, "queries": qid,
            "labels": label, "query_objects": queries}  # fmt: skip


def room_as_lerf_mask(room: Path, out: Path, scene: str = "room", res: str = "res") -> dict:
    """A goi benchmark room (eval/masks/<prompt id>/<view>.png on its test views, split.json,
    prompts.json) written as Gaussian Grouping releases LERF-Mask: out/<scene>/{images/,
    images_train/ (the training views), sparse/0/ (COLMAP text, as `colmap model_converter`
    exports it), test_mask/<k>/<prompt text>.png} with k the k-th test camera by image name,
    and out/res/<prompt text>/<view>.png, the room's RES masks (`res`) under the id goi gives a
    plain text. The room is only read. Returns {"bench", "res", "tests": the test cameras in
    folder order, "pairs": {(prompt id, view): "test_mask/<k>/<text>.png"}}."""
    import shutil

    from stages.query.prompts import check_plain_name
    from stages.scene.scene import load_scene

    s = load_scene(room)
    split = json.loads((room / "split.json").read_text())
    prompts = json.loads((room / "prompts.json").read_text())
    d = out / scene
    write_colmap(d / "sparse" / "0", s.cameras, binary=False)
    rast = None
    for c in s.cameras:
        subs = ["images", *(["images_train"] if c.name in split["train"] else [])]
        for sub in subs:
            (d / sub).mkdir(parents=True, exist_ok=True)
        try:
            src = s.image_path(c)
        except GoiError:  # a room without photos: goi's rendering stands in for them
            rast = rast or Rasterizer.from_gaussians(s.gaussians)
            rgb = (np.clip(rast.render_rgb(c).image, 0, 1) * 255).astype(np.uint8)
            for sub in subs:
                _write_png(d / sub / f"{c.name}.png", rgb[:, :, ::-1])
            continue
        for sub in subs:
            shutil.copyfile(src, d / sub / f"{c.name}{src.suffix}")
    tests = sorted(split["test"])
    pairs = {}
    for p in prompts:
        text = check_plain_name(p["text"], "prompt")  # the release files a mask under its text
        for v in p["test_views"]:
            dst = d / "test_mask" / str(tests.index(v)) / f"{text}.png"
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(room / "eval" / "masks" / p["id"] / f"{v}.png", dst)
            pairs[(p["id"], v)] = str(dst.relative_to(d))
        shutil.copytree(room / res / p["id"], out / "res" / text)
    return {"bench": out, "res": out / "res", "tests": tests, "pairs": pairs}

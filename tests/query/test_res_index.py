"""goi index-res and --res-index on a synthetic scene with photos, through the tiny random
Grounded-SAM and CLIPSeg bundles: the index holds every training view's image side, a query
from it gives the bundle's own masks, a cut-off build resumes, and an index made from another
bundle, scene or image set, or lacking views, is refused by name."""

import json
import shutil

import cv2
import h5py
import numpy as np
import pytest

from goi_cli.main import main
from schemas import validate_file
from stages.core.errors import GoiError
from stages.models.bundle import load_bundle
from stages.query.prompts import safe_name
from stages.query.res import checked_index
from stages.query.res_index import index_order, load_res_index
from stages.query.selection import load_selection
from stages.render.rasterizer import Rasterizer
from stages.scene.gaussians import load_ply
from stages.scene.images import read_rgb
from stages.scene.scene import load_scene
from tests.helpers import semantic_scene

PROMPT = "the red box"

pytestmark = pytest.mark.slow  # the session's tiny RES models (~30 s to export)


@pytest.fixture(scope="module")
def photographed(tmp_path_factory):
    """A scene whose images/ hold goi's renderings of every view (the 'photos')."""
    root = tmp_path_factory.mktemp("resindex")
    s = semantic_scene(root, n=6000, n_views=8, size=(64, 48), dim=8)
    rast = Rasterizer.from_gaussians(load_ply(s["scene"] / "point_cloud.ply"))
    (s["scene"] / "images").mkdir()
    for name, cam in s["cameras"].items():
        rgb = (np.clip(rast.render_rgb(cam).image, 0, 1) * 255 + 0.5).astype(np.uint8)
        cv2.imwrite(str(s["scene"] / "images" / f"{name}.png"), rgb[:, :, ::-1])
    return s, root


def _index(s, bundle, out, *extra):
    return main(["index-res", "--scene", str(s["scene"]), "--bundle", str(bundle),
                 "--out", str(out), *extra])  # fmt: skip


def test_an_index_answers_as_the_bundle_does(photographed, res_bundles, tmp_path, capsys):
    s, _ = photographed
    # a RES exported whole (CLIPSeg today) has no image side to index: refused, named
    assert _index(s, res_bundles["clipseg"], tmp_path / "x.h5") == 2
    assert "no prompt-independent image side" in capsys.readouterr().err
    assert not (tmp_path / "x.h5").exists() and not (tmp_path / "x.h5.partial").exists()
    bundle = res_bundles["grounded"]
    idx = tmp_path / "index.h5"
    assert _index(s, bundle, idx) == 0
    assert validate_file(idx, "goi.res_index")[1] == []
    index = load_res_index(idx)
    # every training view, in the index's order (camera-pose farthest-point sampling)
    cams = [s["cameras"][v] for v in s["train"]]
    assert list(index.views) == [c.name for c in index_order(cams)]
    assert sorted(index.views) == sorted(s["train"])
    b = load_bundle(bundle)
    assert index.bundle_sha256 == b.digest()
    prompt = b.res_prompt(PROMPT)
    for view in s["train"][:2]:
        cam = s["cameras"][view]
        rgb = read_rgb(s["scene"] / "images" / f"{view}.png")
        got = b.res_from_image_side(index.image_side(view), (cam.height, cam.width), prompt, rgb)
        np.testing.assert_array_equal(got.mask, b.segment(rgb, PROMPT))
    # the field-free lifted query from the index: every indexed view, nothing else
    out = tmp_path / "q"
    argv = ["query", "--scene", str(s["scene"]), "--prompt", PROMPT, "--lift",
            "--res-index", str(idx), "--bundle", str(bundle), "--out", str(out)]  # fmt: skip
    assert main(argv) == 0
    sel = load_selection(out / safe_name(PROMPT) / "selection.h5")
    assert sel.lifted["views"] == s["train"]
    assert sel.lifted["chosen_by"].startswith("every indexed view")
    assert sorted(p.stem for p in (out / safe_name(PROMPT) / "masks").glob("*[!y].png")) == sorted(
        s["test"]
    )


def test_a_cut_off_index_resumes_and_bad_indexes_are_refused(
    photographed, res_bundles, tmp_path, capsys
):
    s, root = photographed
    bundle = res_bundles["grounded"]
    idx = tmp_path / "index.h5"
    assert _index(s, bundle, idx) == 0
    full = load_res_index(idx)
    # a build cut off after two views (the third one half written) resumes with those two
    partial = tmp_path / "again.h5.partial"
    shutil.copy(idx, partial)
    with h5py.File(partial, "r+") as f:
        for v in s["train"][2:]:
            del f["views"][v]
        g = f["views"][s["train"][1]]
        del g.attrs["image_sha256"]
    capsys.readouterr()
    assert _index(s, bundle, tmp_path / "again.h5") == 0
    assert "resuming" in capsys.readouterr().err
    assert not partial.exists()
    again = load_res_index(tmp_path / "again.h5")
    assert sorted(again.views) == sorted(full.views)
    for v in s["train"]:
        a, b = again.image_side(v), full.image_side(v)
        assert all(np.array_equal(a[k], b[k]) for k in a)
    assert _index(s, bundle, idx) == 2  # exists: --force is needed
    q = ["query", "--scene", str(s["scene"]), "--prompt", PROMPT, "--lift",
         "--out", str(tmp_path / "q")]  # fmt: skip

    def refused(*extra, match):
        capsys.readouterr()
        assert main([*q, *extra]) == 2
        err = capsys.readouterr().err
        assert match in err and len(err.strip().splitlines()) == 1, err
        assert not (tmp_path / "q").exists()

    # another bundle (the same models under another name: another digest)
    other_bundle = tmp_path / "other_bundle"
    shutil.copytree(bundle, other_bundle)
    manifest = json.loads((other_bundle / "manifest.json").read_text())
    (other_bundle / "manifest.json").write_text(json.dumps({**manifest, "name": "other"}))
    refused("--res-index", str(idx), "--bundle", str(other_bundle),
            match="was made with bundle")  # fmt: skip
    # no bundle
    refused("--res-index", str(idx), match="--res-index needs --bundle")
    # a view missing: a reader that needs every view refuses it by name (a lifted query
    # indexes it instead: tests/query/test_res_index_growing.py)
    lacking = tmp_path / "lacking.h5"
    shutil.copy(idx, lacking)
    with h5py.File(lacking, "r+") as f:
        del f["views"][s["train"][3]]
    scene = load_scene(s["scene"])
    with pytest.raises(GoiError, match=f"lacks view '{s['train'][3]}'"):
        checked_index(lacking, bundle, scene)
    # another image set: one photo changed
    other = tmp_path / "other_scene"
    shutil.copytree(s["scene"], other)
    img = other / "images" / f"{s['train'][2]}.png"
    cv2.imwrite(str(img), 255 - cv2.imread(str(img)))
    q[2] = str(other)
    refused("--res-index", str(idx), "--bundle", str(bundle),
            match=f"the image of view '{s['train'][2]}'")  # fmt: skip
    # another scene: none of its views are in the index
    renamed = tmp_path / "renamed.h5"
    shutil.copy(idx, renamed)
    with h5py.File(renamed, "r+") as f:
        for v in list(f["views"]):
            f["views"].move(v, f"x_{v}")
    q[2] = str(s["scene"])
    refused("--res-index", str(renamed), "--bundle", str(bundle), match="another scene")
    assert json.loads(h5py.File(idx)["/"].attrs["inputs"])["bundle"] == full.bundle_sha256


def test_eval_from_an_index(res_bundles, tmp_path):
    """goi eval --res-index: the lifted variants lift every indexed view; a view's masks come
    from the index (on the room's photos)."""
    from tests.evaluation.test_eval import make_room

    s, room = make_room(tmp_path)
    rast = Rasterizer.from_gaussians(load_ply(room / "point_cloud.ply"))
    (room / "images").mkdir()
    for name, cam in s["cameras"].items():
        rgb = (np.clip(rast.render_rgb(cam).image, 0, 1) * 255 + 0.5).astype(np.uint8)
        cv2.imwrite(str(room / "images" / f"{name}.png"), rgb[:, :, ::-1])
    bundle = res_bundles["grounded"]
    idx = tmp_path / "index.h5"
    assert main(["index-res", "--scene", str(room), "--bundle", str(bundle),
                 "--out", str(idx)]) == 0  # fmt: skip
    out = tmp_path / "r.json"
    argv = ["eval", str(room), "--bundle", str(bundle), "--res-index", str(idx),
            "--variants", "lifted_fieldless", "--out", str(out),
            "--html", str(tmp_path / "r.html")]  # fmt: skip
    assert main(argv) == 0
    r = json.loads(out.read_text())
    for e in r["variants"]["lifted_fieldless"]["prompts"].values():
        assert e["fit_views"] == s["train"]
        assert e["views_chosen_by"].startswith("every indexed view")
    assert main([*argv[:-4], "--res-masks", str(room / "res"), "--out", str(out), "--force"]) == 2

import json

import numpy as np
import pytest

from stages.core.errors import GoiError
from stages.scene.formats import load_cameras
from stages.scene.formats.colmap import write_colmap
from stages.scene.formats.inria import write_inria
from stages.scene.formats.nerf import write_transforms
from stages.scene.scene import load_scene
from stages.testing.synthetic import look_at
from tests.helpers import DEV_ROOM


def _cams(cx_offset: float = 0.0):
    rng = np.random.default_rng(3)
    cams = []
    for i in range(5):
        eye = rng.uniform(-3, 3, 3) + np.array([0, 0, 4])
        c = look_at(f"img{i}", eye, rng.uniform(-0.5, 0.5, 3), 320, 240, 50 + 5 * i % 20)
        c.cx += cx_offset
        cams.append(c)
    return cams


def _project_all(cams, pts):
    return np.stack([c.project(pts)[0] for c in cams])


@pytest.mark.parametrize(
    "fmt", ["inria", "transforms-angle", "transforms-focal", "colmap-txt", "colmap-bin"]
)
def test_every_format_projects_a_point_to_the_same_pixel(tmp_path, fmt):
    # Only the formats that can say so carry an off-centre principal point.
    offset = 3.5 if fmt in ("transforms-focal", "colmap-txt", "colmap-bin") else 0.0
    cams = _cams(offset)
    if fmt == "transforms-angle":
        cams = [c for c in cams if abs(c.fx - cams[0].fx) < 1e-9]  # one shared intrinsic
    if fmt == "transforms-focal":
        for c in cams:
            c.fx, c.fy = cams[0].fx, cams[0].fy
    writers = {
        "inria": lambda: write_inria(tmp_path / "cameras.json", cams),
        "transforms-angle": lambda: write_transforms(tmp_path / "transforms.json", cams, "angle"),
        "transforms-focal": lambda: write_transforms(tmp_path / "transforms.json", cams, "focal"),
        "colmap-txt": lambda: write_colmap(tmp_path / "sparse", cams, binary=False),
        "colmap-bin": lambda: write_colmap(tmp_path / "sparse", cams, binary=True),
    }
    loaded = load_cameras(writers[fmt]())
    assert [c.name for c in loaded] == [c.name for c in cams]
    pts = np.random.default_rng(0).uniform(-1, 1, (100, 3))
    np.testing.assert_allclose(_project_all(loaded, pts), _project_all(cams, pts), atol=1e-6)
    for a, b in zip(loaded, cams, strict=True):
        np.testing.assert_allclose(a.center, b.center, atol=1e-9)
        assert (a.width, a.height) == (b.width, b.height)


def test_simple_pinhole_colmap(tmp_path):
    cams = _cams()
    loaded = load_cameras(write_colmap(tmp_path / "s", cams, binary=True, model="SIMPLE_PINHOLE"))
    assert loaded[1].fx == loaded[1].fy == cams[1].fx


@pytest.mark.parametrize("binary", [True, False])
def test_distorted_colmap_model_is_refused(tmp_path, binary):
    d = write_colmap(tmp_path / "s", _cams(), binary=binary, model="OPENCV")
    with pytest.raises(GoiError, match="OPENCV model.*undistort"):
        load_cameras(d)


def test_transforms_without_intrinsics_is_refused(tmp_path):
    p = write_transforms(tmp_path / "transforms.json", _cams(), intrinsics="none")
    with pytest.raises(GoiError, match=r"transforms.json \[frame 0\]: no intrinsics"):
        load_cameras(p)


def test_non_positive_focal_is_refused(tmp_path):
    cams = _cams()
    p = write_inria(tmp_path / "cameras.json", cams)
    data = json.loads(p.read_text())
    data[2]["fx"] = 0
    p.write_text(json.dumps(data))
    with pytest.raises(GoiError, match="img2.*focal length"):
        load_cameras(p)


def test_bad_json_and_unknown_formats(tmp_path):
    (tmp_path / "a.json").write_text("{nope")
    with pytest.raises(GoiError, match="not valid JSON"):
        load_cameras(tmp_path / "a.json")
    (tmp_path / "b.txt").write_text("x")
    with pytest.raises(GoiError, match="unknown cameras format"):
        load_cameras(tmp_path / "b.txt")
    with pytest.raises(GoiError, match="no COLMAP model"):
        load_cameras(tmp_path)


@pytest.mark.skipif(not DEV_ROOM.is_dir(), reason="shared/dev-room is not beside the checkout")
def test_dev_room_formats_agree():
    inria = {c.name: c for c in load_cameras(DEV_ROOM / "cameras.json")}
    nerf = load_cameras(DEV_ROOM / "transforms_train.json") + load_cameras(
        DEV_ROOM / "transforms_test.json"
    )
    assert len(nerf) == len(inria) == 60
    worst = 0.0
    for c in nerf:
        i = inria[c.name]
        worst = max(
            worst,
            np.abs(c.R - i.R).max(),
            np.abs(c.t - i.t).max(),
            abs(c.fx - i.fx),
            abs(c.cx - i.cx),
        )
    assert worst < 1e-5
    scene = load_scene(DEV_ROOM)
    assert len(scene.train) == 48 and len(scene.test) == 12
    assert scene.image_path(scene.camera("v002")).name == "v002.png"

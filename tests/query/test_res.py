"""RES mask files: finding them, resizing, empty masks, and the choice of fitting views."""

from pathlib import Path

import cv2
import numpy as np
import pytest

from stages.core.errors import GoiError
from stages.query.osh import HyperplaneParams
from stages.query.prompts import Prompt
from stages.query.res import ResFiles, choose_views
from stages.scene.cameras import Camera


def _cam(name, w=40, h=30):
    return Camera(name, w, h, 30.0, 30.0, w / 2, h / 2, np.eye(3), np.zeros(3), None)


def test_res_masks_resized_with_a_warning_and_empty_ones_skipped(tmp_path, recwarn):
    d: Path = tmp_path / "res" / "p1"
    d.mkdir(parents=True)
    small = np.zeros((15, 20), np.uint8)
    small[5:10, 5:10] = 255
    cv2.imwrite(str(d / "a.png"), small)
    cv2.imwrite(str(d / "b.png"), np.zeros((30, 40), np.uint8))
    src = ResFiles(tmp_path / "res", Prompt("x", "p1"))
    chosen = choose_views(src, [_cam("a"), _cam("b")], HyperplaneParams())
    assert [c.name for c, _ in chosen] == ["a"] and chosen[0][1].shape == (30, 40)
    assert chosen[0][1].sum() == 100
    assert any("resized" in str(w.message) for w in recwarn)
    with pytest.raises(GoiError, match="RES mask of view 'b' is empty"):
        choose_views(src, [_cam("a"), _cam("b")], HyperplaneParams(fit_on="b"))
    cv2.imwrite(str(d / "a.png"), np.zeros((30, 40), np.uint8))
    with pytest.raises(GoiError, match="every RES mask of this prompt is empty"):
        choose_views(src, [_cam("a"), _cam("b")], HyperplaneParams())
    with pytest.raises(GoiError, match="no <view>.png masks"):
        ResFiles(tmp_path / "res", Prompt("x", "p2"))

"""The dev room with its thin and small objects added as prompts (made at test time)."""

import json

import cv2
import numpy as np
import pytest

from stages.scene.images import read_mask
from stages.testing.thin_room import (
    HELD_OUT_PROMPTS,
    THIN_PROMPTS,
    add_res,
    eroded_masks,
    extend_room,
    main,
    true_masks,
)
from tests.helpers import DEV_ROOM

pytestmark = pytest.mark.skipif(not DEV_ROOM.is_dir(), reason="the dev room is absent")


def test_extended_room_adds_prompts_with_ground_truth_and_eroded_masks(tmp_path):
    room = extend_room(DEV_ROOM, tmp_path / "room")
    prompts = json.loads((room / "prompts.json").read_text())
    own = json.loads((DEV_ROOM / "prompts.json").read_text())
    assert prompts[: len(own)] == own  # the room's prompts as they are
    added = {p["id"]: p for p in prompts[len(own) :]}
    assert list(added) == [p[0] for p in THIN_PROMPTS]
    guitar = added["t01"]
    assert guitar["test_views"]  # the guitar covers >= 0.5% of some test views
    for v in guitar["test_views"]:
        ids = cv2.imread(str(DEV_ROOM / "ids" / f"{v}.png"), cv2.IMREAD_UNCHANGED)
        gt = read_mask(room / "eval" / "masks" / "t01" / f"{v}.png")
        assert (gt == (ids == 23)).all()
    assert (room / "point_cloud.ply").is_symlink()  # the big parts are linked, not copied
    # eroded masks (one prompt, to keep the test fast) hold only target pixels
    (room / "prompts.json").write_text(json.dumps([guitar]))
    eroded_masks(room, tmp_path / "eroded")
    files = sorted((tmp_path / "eroded" / "t01").iterdir())
    assert files
    for f in files:
        ids = cv2.imread(str(DEV_ROOM / "ids" / f.name), cv2.IMREAD_UNCHANGED)
        m = read_mask(f)
        assert m.any() and not (m & (ids != 23)).any()
        assert m.sum() < np.sum(ids == 23)


def test_true_masks_are_the_training_views_ground_truth(tmp_path):
    """The ceiling's RES set: every training view where the target covers >= 0.5% of the
    pixels has the ground truth as its mask, and no other view has one."""
    room = extend_room(DEV_ROOM, tmp_path / "room")
    clock = [p for p in json.loads((room / "prompts.json").read_text()) if p["id"] == "t03"]
    (room / "prompts.json").write_text(json.dumps(clock))  # one prompt keeps it fast
    true_masks(room, tmp_path / "true")
    split = json.loads((DEV_ROOM / "split.json").read_text())
    made = {f.stem for f in (tmp_path / "true" / "t03").iterdir()}
    assert made
    for v in split["train"]:
        ids = cv2.imread(str(DEV_ROOM / "ids" / f"{v}.png"), cv2.IMREAD_UNCHANGED)
        gt = ids == 24
        assert (v in made) == (gt.mean() >= 0.005)
        if v in made:
            assert (read_mask(tmp_path / "true" / "t03" / f"{v}.png") == gt).all()


def test_held_out_prompts_are_the_rooms_other_furniture(tmp_path):
    room = extend_room(DEV_ROOM, tmp_path / "room", THIN_PROMPTS + HELD_OUT_PROMPTS)
    prompts = {p["id"]: p for p in json.loads((room / "prompts.json").read_text())}
    own = json.loads((DEV_ROOM / "prompts.json").read_text())
    prompted = {t for p in own for t in p["targets"]}
    texts = json.loads((DEV_ROOM / "text_embeddings.json").read_text())
    for pid, text, targets, _ in HELD_OUT_PROMPTS:
        assert not prompted & set(targets)  # held out: no prompt of the room names them
        assert text in texts  # the room ships its embedding
        assert prompts[pid]["test_views"]  # and it is seen in the test views
        v = prompts[pid]["test_views"][0]
        ids = cv2.imread(str(DEV_ROOM / "ids" / f"{v}.png"), cv2.IMREAD_UNCHANGED)
        gt = read_mask(room / "eval" / "masks" / pid / f"{v}.png")
        assert (gt == np.isin(ids, targets)).all()


@pytest.mark.parametrize(
    ("option", "value", "unknown"),
    [("--prompts", "thin,stools", "stools"), ("--res", "res,perfect", "perfect")],
)
def test_an_unknown_set_is_refused_before_anything_is_made(
    tmp_path, capsys, option, value, unknown
):
    with pytest.raises(SystemExit) as e:
        main([str(DEV_ROOM), str(tmp_path / "room"), option, value])
    assert e.value.code == 2
    assert f"{option}: unknown set '{unknown}'" in capsys.readouterr().err
    assert not (tmp_path / "room").exists()


def test_another_mask_seed_draws_the_rooms_own_prompts_anew(tmp_path):
    """Seed 0 links the room's own masks (its RES sets are seed 0); another seed makes every
    prompt's masks with the room's tool, a new draw of the same error model."""
    room = extend_room(DEV_ROOM, tmp_path / "room", ())
    basketball = [p for p in json.loads((room / "prompts.json").read_text()) if p["id"] == "p08"]
    (room / "prompts.json").write_text(json.dumps(basketball))  # one prompt keeps it fast
    tools = DEV_ROOM.resolve().parent / "tools"
    same = add_res(room, DEV_ROOM, "res", tools, seed=0)
    assert (same / "p08").is_symlink()
    (room / "res").rename(room / "res-0")
    drawn = add_res(room, DEV_ROOM, "res", tools, seed=1)
    assert not (drawn / "p08").is_symlink()
    views = sorted(f.name for f in (drawn / "p08").glob("*.png"))
    assert views == sorted(f.name for f in (DEV_ROOM / "res" / "p08").glob("*.png"))
    old = room / "res-0" / "p08"
    assert any((read_mask(drawn / "p08" / v) != read_mask(old / v)).any() for v in views)

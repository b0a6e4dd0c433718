"""Clean answers (stages.query.clean): the voxel-hash kernels held to their plain references,
and the rule that drops the specks far from an answer's body."""

import numpy as np
import pytest

from stages.query.clean import (
    LINK,
    NEAR,
    STRONG_CLAIM,
    clean_selection,
    components,
    near_any,
    reference_components,
    reference_near_any,
    robust_extent,
    scene_extent,
)


@pytest.mark.parametrize("n", [0, 1, 2, 50, 600])
@pytest.mark.parametrize("r", [0.01, 0.07, 0.3])
def test_components_equal_the_plain_reference(n, r):
    rng = np.random.default_rng(n)
    # clustered points, so the graph has components of every size
    centres = rng.random((max(1, n // 40), 3)) * np.array([2.0, 1.0, 0.5])
    p = centres[rng.integers(0, centres.shape[0], n)] + rng.normal(0, 0.03, (n, 3))
    assert np.array_equal(components(p, r), reference_components(p, r))


def test_components_link_exactly_at_r_and_number_by_first_member():
    p = np.array([[0.0, 0, 0], [5.0, 0, 0], [0.25, 0, 0], [5.25, 0, 0], [0.5, 0, 0], [9, 9, 9]])
    assert components(p, 0.25).tolist() == [0, 1, 0, 1, 0, 2]
    assert components(p, 0.2499).tolist() == [0, 1, 2, 3, 4, 5]
    assert reference_components(p, 0.25).tolist() == [0, 1, 0, 1, 0, 2]


@pytest.mark.parametrize("n", [0, 1, 300])
@pytest.mark.parametrize("r", [0.02, 0.2])
def test_near_any_equals_the_plain_reference(n, r):
    rng = np.random.default_rng(7 + n)
    p = rng.random((n, 3))
    q = rng.random((400, 3)) * 1.6 - 0.3  # queries outside the points' grid too
    assert np.array_equal(near_any(q, p, r), reference_near_any(q, p, r))


def test_scene_extent_is_the_bounding_box_diagonal():
    m = np.array([[0, 0, 0], [3, 0, 0], [1, 4, 0], [2, 2, 12]], np.float32)
    assert scene_extent(m) == pytest.approx(13.0)
    assert scene_extent(np.zeros((0, 3))) == 0.0


def _blob(rng, centre, n, spread=0.02):
    return np.asarray(centre, float) + rng.normal(0, spread, (n, 3))


def _room(rng, *parts):
    """Means [G, 3]: a 5 x 4 x 2 m shell of Gaussians (the scene's extent, ~6.7 m) and the
    given parts after it; returns the means and each part's index range."""
    shell = rng.uniform((-2.5, -2, 0), (2.5, 2, 2), (4000, 3))
    means, ranges, at = [shell], [], shell.shape[0]
    for p in parts:
        means.append(p)
        ranges.append(np.arange(at, at + p.shape[0]))
        at += p.shape[0]
    return np.concatenate(means), ranges


def test_a_speck_far_from_the_body_is_dropped_and_recorded():
    rng = np.random.default_rng(0)
    means, (body, speck) = _room(rng, _blob(rng, (0, 0, 0.5), 800), _blob(rng, (1.5, 1, 1), 12))
    sel = np.zeros(means.shape[0], bool)
    sel[body] = sel[speck] = True
    claim = np.zeros(means.shape[0])
    claim[body], claim[speck] = 5.0, 5.0  # as claimed per Gaussian: it is small
    kept, rec = clean_selection(means, sel, claim)
    assert kept[body].all() and not kept[speck].any() and kept.sum() == body.size
    assert rec["rule"] == "far_piece" and rec["n_dropped"] == speck.size
    assert rec["n_before"] == sel.sum() and rec["n_dropped_pieces"] == 1
    assert rec["params"]["extent"] == pytest.approx(robust_extent(means), abs=1e-6)
    assert sel.sum() == body.size + speck.size  # the input is left as it is


def test_an_object_in_two_places_stays_whole():
    """'The armchairs': a second body far from the first, claimed in its own right."""
    rng = np.random.default_rng(1)
    means, (a, b) = _room(rng, _blob(rng, (-1, 0, 0.5), 900), _blob(rng, (1.5, 1, 0.5), 300))
    sel = np.zeros(means.shape[0], bool)
    sel[a] = sel[b] = True
    claim = np.where(sel, 3.0, 0.0)  # b carries a third of a's claim
    kept, rec = clean_selection(means, sel, claim)
    assert np.array_equal(kept, sel) and rec["n_body_pieces"] == 2 and rec["n_dropped"] == 0
    weak = claim.copy()
    weak[b] = 3.0 * STRONG_CLAIM * a.size / b.size * 0.9  # just under the strong claim
    kept, _ = clean_selection(means, sel, weak)
    assert kept[a].all() and not kept[b].any()


def test_a_weak_piece_near_the_body_is_kept():
    """A part the link radius cuts off (a chair's leg a few cm away) is no stray."""
    rng = np.random.default_rng(2)
    ext = 6.7
    gap = (LINK + 0.5 * (NEAR - LINK)) * ext  # beyond the link radius, within NEAR
    body = _blob(rng, (0, 0, 0.5), 600, spread=0.01)
    leg = _blob(rng, (0, 0, 0.5 - 0.03 - gap), 10, spread=0.002)
    means, (b, leg_i) = _room(rng, body, leg)
    sel = np.zeros(means.shape[0], bool)
    sel[b] = sel[leg_i] = True
    kept, rec = clean_selection(means, sel, sel.astype(float))
    assert np.array_equal(kept, sel)
    assert rec["n_pieces"] == 2 and rec["n_near_pieces"] == 1 and rec["n_dropped"] == 0


def test_nothing_claimed_the_largest_piece_leads_and_nothing_selected_is_kept_as_is():
    rng = np.random.default_rng(3)
    means, (a, b) = _room(rng, _blob(rng, (-1, 0, 0.5), 500), _blob(rng, (1.5, 1, 1), 20))
    sel = np.zeros(means.shape[0], bool)
    sel[a] = sel[b] = True
    kept, rec = clean_selection(means, sel, np.zeros(means.shape[0]))  # a field-only answer
    assert kept[a].all() and not kept[b].any()
    none = np.zeros(means.shape[0], bool)
    kept, rec = clean_selection(means, none, np.zeros(means.shape[0]))
    assert not kept.any() and rec["n_dropped"] == 0 and rec["n_pieces"] == 0


def test_cleaning_is_deterministic_and_independent_of_the_gaussians_order():
    rng = np.random.default_rng(4)
    parts = [_blob(rng, c, n) for c, n in (((0, 0, 0.5), 700), ((1, 1, 1), 9), ((-2, 1, 1), 40))]
    means, _ = _room(rng, *parts)
    sel = rng.random(means.shape[0]) < 0.05
    sel[4000:] = True
    claim = rng.random(means.shape[0])
    kept, rec = clean_selection(means, sel, claim)
    again, rec2 = clean_selection(means, sel, claim)
    assert np.array_equal(kept, again) and rec == rec2
    perm = rng.permutation(means.shape[0])
    shuffled, rec3 = clean_selection(means[perm], sel[perm], claim[perm])
    assert np.array_equal(shuffled, kept[perm]) and rec3["n_dropped"] == rec["n_dropped"]


class _Masks:
    """RES masks in memory: {view: [H, W] bool}, every view lifted (as mask files are)."""

    every_view = True
    source = "test masks"

    def __init__(self, masks):
        self.masks = masks

    def available(self, cams):
        return [c for c in cams if c.name in self.masks]

    def mask(self, cam):
        return self.masks[cam.name]


@pytest.fixture(scope="module")
def specked(tmp_path_factory):
    """A synthetic room and RES masks of its object 2 that also take in a speck on the floor
    (the floor's Gaussians within 0.2 m of the one the first three training views see best,
    1.5 m from the object) on those three views: the vote keeps the speck, as it keeps what a
    RES model repeats. And masks of objects 2 and 3 together (1.3 m apart)."""
    import cv2

    from stages.render.rasterizer import Rasterizer
    from stages.scene.gaussians import load_ply
    from tests.helpers import semantic_scene

    root = tmp_path_factory.mktemp("specked")
    s = semantic_scene(root, n=20000, n_views=8, size=(64, 48), dim=8)
    rast = Rasterizer.from_gaussians(load_ply(s["scene"] / "point_cloud.ply"))
    means = rast.means.astype(np.float64)
    ids = s["onehot"].argmax(1)
    train = [s["cameras"][n] for n in s["train"]]
    vis = np.stack([rast.contribution(c) for c in train[:3]])  # [3, G]
    centre = means[int(np.argmax(vis.min(0) * (ids == 0)))]
    speck = (np.linalg.norm(means - centre, axis=1) < 0.2) & (ids == 0)
    labels = np.stack([ids == 2, speck, ids == 3], 1).astype(np.float32)  # [G, 3]
    masks, both = {}, {}
    for i, name in enumerate(s["train"]):
        share = rast.render_features(s["cameras"][name], labels).image  # [H, W, 3]
        masks[name] = share[:, :, 0] > 0.5
        if i < 3:
            masks[name] |= share[:, :, 1] > 0.5
        both[name] = (share[:, :, 0] > 0.5) | (share[:, :, 2] > 0.5)
    d = root / "res" / "o2"
    d.mkdir(parents=True)
    for name, m in masks.items():
        cv2.imwrite(str(d / f"{name}.png"), m.astype(np.uint8) * 255)
    return s, rast, ids, speck, masks, both, root


def _lift(rast, s, masks, clean):
    from stages.query.lift_answer import lift_prompt
    from stages.query.lift_math import LiftParams
    from stages.query.osh import HyperplaneParams

    train = [s["cameras"][n] for n in s["train"]]
    lp = LiftParams(lift=True, clean=clean)
    return lift_prompt(rast, train, _Masks(masks), "object 2", None, HyperplaneParams(), lp)


def test_the_lifted_answer_is_cleaned_and_says_so(specked):
    s, rast, ids, speck, masks, _, _ = specked
    raw = _lift(rast, s, masks, clean=False)
    assert raw.cleaned is None and raw.record(raw_params()).get("clean") is None
    assert raw.selected[speck].sum() >= 5  # the vote keeps the speck
    ans = _lift(rast, s, masks, clean=True)
    assert not ans.selected[speck].any()
    assert np.array_equal(ans.selected, raw.selected & ~speck)  # the object is untouched
    assert ans.cleaned["n_dropped"] == int(raw.selected[speck].sum())
    assert ans.record(raw_params())["clean"] == ans.cleaned
    # the evidence is the vote's: cleaning changes the selection only
    assert np.array_equal(ans.lifted.S1, raw.lifted.S1)


def test_two_objects_of_one_prompt_both_stay(specked):
    s, rast, ids, _, _, both, _ = specked
    raw = _lift(rast, s, both, clean=False)
    ans = _lift(rast, s, both, clean=True)
    assert raw.selected[ids == 2].sum() > 100 and raw.selected[ids == 3].sum() > 100
    # (the vote of four views takes a third of each box, in pieces: a lone Gaussian of one
    # may lie farther than NEAR from the pieces that carry the claim)
    for k in (2, 3):
        assert ans.selected[ids == k].sum() >= 0.98 * raw.selected[ids == k].sum()
    assert ans.cleaned["n_body_pieces"] >= 2


def test_no_clean_on_the_command_line(specked, tmp_path):
    from goi_cli.main import main
    from stages.query.selection import load_selection

    s, _, _, speck, _, _, root = specked
    common = ["select", "--scene", str(s["scene"]), "--prompt", "object 2", "--res-masks",
              str(root / "res"), "--prompt-id", "o2"]  # fmt: skip
    assert main([*common, "--lift", "--out", str(tmp_path / "a.h5")]) == 0
    assert main([*common, "--lift", "--no-clean", "--out", str(tmp_path / "b.h5")]) == 0
    a, b = load_selection(tmp_path / "a.h5"), load_selection(tmp_path / "b.h5")
    assert a.lifted["clean"]["rule"] == "far_piece" and a.lifted["clean"]["n_dropped"] > 0
    assert a.lifted["params"]["clean"] is True and b.lifted["params"]["clean"] is False
    assert b.lifted["clean"] is None and b.selected[speck].any() and not a.selected[speck].any()
    # an option of the lifted mode: refused without --lift
    assert main([*common, "--no-clean", "--out", str(tmp_path / "c.h5")]) == 2


def raw_params():
    from stages.query.lift_math import LiftParams

    return LiftParams(lift=True)

"""The report's floor under every prompt: worst prompt, prompts below `full`, and each prompt
against the exact 3D answer."""

from stages.evaluation.report import floor_table
from stages.evaluation.worst import add_against_exact, add_worst_prompts


def _variant(ious):
    return {"miou": 0.0, "prompts": {k: {"text": f"t{k}", "iou": v} for k, v in ious.items()}}


def test_worst_prompt_and_prompts_below_full():
    variants = {
        "full": _variant({"a": 0.6, "b": 0.5, "c": 0.9, "d": None}),
        "lifted": _variant({"a": 0.9, "b": 0.03, "c": 0.86, "d": None}),
    }
    add_worst_prompts(variants)
    assert variants["full"]["worst_prompt"] == {"id": "b", "text": "tb", "iou": 0.5}
    assert "below_full" not in variants["full"]
    lifted = variants["lifted"]
    assert lifted["worst_prompt"]["id"] == "b"
    # c is 0.04 below: within the margin; d has no test views
    assert lifted["below_full"] == {"margin": 0.05, "count": 1, "prompts": ["b"]}
    assert list(lifted)[-1] == "prompts"
    page = floor_table(variants)
    assert "b: tb" in page and "1 (more than 0.05 below): b" in page


def test_no_scored_prompt_and_no_full():
    variants = {"lifted": _variant({"d": None})}
    add_worst_prompts(variants)
    assert variants["lifted"]["worst_prompt"] is None
    assert "below_full" not in variants["lifted"]


def test_prompts_against_the_exact_answer():
    variants = {
        "full": _variant({"a": 0.6, "b": 0.5, "c": 0.9, "d": None}),
        "lifted": _variant({"a": 0.9, "b": 0.58, "c": 0.86, "d": None}),
    }
    # b is a thin prompt whose exact answer scores 0.6; c beats its exact answer in 2D
    exact = {"prompts": {"a": {"iou": 0.95}, "b": {"iou": 0.6}, "c": {"iou": 0.8}, "e": {"iou": 1}}}
    add_worst_prompts(variants)
    add_against_exact(variants, exact)
    lifted = variants["lifted"]["against_exact"]
    # the lowest IoU (b, 0.58: 0.97 of its ceiling) is not the worst against its ceiling: a is
    assert variants["lifted"]["worst_prompt"]["id"] == "b"
    assert lifted["worst"]["id"] == "a" and abs(lifted["worst"]["share"] - 0.9 / 0.95) < 1e-12
    assert variants["full"]["against_exact"]["worst"] == {
        "id": "a", "text": "ta", "iou": 0.6, "exact": 0.95, "share": 0.6 / 0.95
    }  # fmt: skip
    shares = [0.9 / 0.95, 0.58 / 0.6, 0.86 / 0.8]  # d has no test view, e no variant IoU
    assert abs(lifted["mean_share"] - sum(shares) / 3) < 1e-12
    assert list(variants["lifted"])[-1] == "prompts"
    page = floor_table(variants)
    assert "worst against the exact answer" in page and "a: 0.6000 / 0.9500 = 0.6316" in page


def test_against_exact_without_a_common_prompt():
    variants = {"lifted": _variant({"d": None})}
    add_against_exact(variants, {"prompts": {"d": {"iou": 0.5}}})
    assert variants["lifted"]["against_exact"] is None
    assert "worst against the exact answer" not in floor_table(variants)

"""The report's floor under every prompt: worst prompt and prompts below `full`."""

from stages.evaluation.report import floor_table
from stages.evaluation.worst import add_worst_prompts


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

"""The floor under every prompt: a mean over prompts hides one prompt's collapse (issue #26: a
thin target at lifted IoU 0.03 where `full` gets 0.58, inside a mean well above `full`'s). Per
variant, the report names its worst prompt and, against the paper's `full`, the prompts where
the variant is more than BELOW_FULL_MARGIN below it."""

from __future__ import annotations

#: IoU by which a variant may trail `full` on a prompt before the prompt counts as below it.
BELOW_FULL_MARGIN = 0.05


def add_worst_prompts(variants: dict) -> None:
    """Add `worst_prompt` ({id, text, iou}, None without scored prompts) to every variant's
    report and, when `full` ran, `below_full` ({margin, count, prompts: [ids]}) to the others.
    Prompts without test views (no 2D IoU) are left out, as from the means."""
    full = variants.get("full")
    for name, rep in variants.items():
        scored = {pid: e for pid, e in rep["prompts"].items() if e.get("iou") is not None}
        worst = min(scored, key=lambda pid: scored[pid]["iou"], default=None)
        rep["worst_prompt"] = (
            None
            if worst is None
            else {"id": worst, "text": scored[worst]["text"], "iou": scored[worst]["iou"]}
        )
        if full is None or name == "full":
            continue
        below = [
            pid
            for pid, e in scored.items()
            if full["prompts"].get(pid, {}).get("iou") is not None
            and e["iou"] < full["prompts"][pid]["iou"] - BELOW_FULL_MARGIN
        ]
        rep["below_full"] = {"margin": BELOW_FULL_MARGIN, "count": len(below), "prompts": below}
        rep["prompts"] = rep.pop("prompts")  # keep the summaries first

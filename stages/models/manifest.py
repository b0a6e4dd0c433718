"""Every value of a bundle manifest, checked by one typed table before any model loads.

`schemas/goi.bundle.json` says which fields a manifest has and their JSON kinds; this table
says what each value may be: its type (a boolean is not an integer, a string is not a
number), finite, in range, and below an upper bound that keeps a model's input a sane size
(a `size` of 200000 would ask OpenCV for 120 GB before any model ran). The rules go by a
field's own name wherever it sits in the manifest, so every model section (encoders, a RES
model, a grounded pipeline's parts, and any kind added later) gets the same checks.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from stages.core.errors import GoiError

#: The largest side goi resizes an image to for a model (the export's own limit).
MAX_SIDE = 4096
#: The longest tokenizer limit goi accepts (models use 77 to 512).
MAX_TOKENS = 8192
#: The largest feature dimension of an encoder.
MAX_DIM = 65536

#: Sections that record what was measured, not how to run a model: not checked here.
INFORMATIVE = ("export_checks",)


def _int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _number(v: Any) -> float | None:
    """`v` as a finite float, or None when it is not a finite JSON number."""
    if isinstance(v, bool) or not isinstance(v, int | float):
        return None
    try:
        f = float(v)
    except OverflowError:  # an integer beyond float's range
        return None
    return f if math.isfinite(f) else None


def integer(lo: int, hi: int) -> Callable[[Any], str | None]:
    def check(v: Any) -> str | None:
        if not _int(v):
            return f"needs an integer, not {_shown(v)}"
        return None if lo <= v <= hi else f"is {v}, not an integer in [{lo}, {hi}]"

    return check


def number(lo: float, hi: float) -> Callable[[Any], str | None]:
    def check(v: Any) -> str | None:
        f = _number(v)
        if f is None:
            return f"needs a finite number, not {_shown(v)}"
        return None if lo <= f <= hi else f"is {f:g}, not a number in [{lo:g}, {hi:g}]"

    return check


def numbers(n: int, lo: float, hi: float, what: str) -> Callable[[Any], str | None]:
    def check(v: Any) -> str | None:
        if not isinstance(v, list) or len(v) != n:
            return f"needs {n} numbers ({what})"
        for x in v:
            f = _number(x)
            if f is None or not lo <= f <= hi:
                return f"needs {n} finite numbers in [{lo:g}, {hi:g}] ({what}), not {_shown(x)}"
        return None

    return check


def sides(v: Any) -> str | None:
    if not isinstance(v, list) or len(v) != 2 or not all(_int(x) for x in v):
        return "needs [width, height] as two integers"
    if not all(1 <= x <= MAX_SIDE for x in v):
        return f"{v} is not two sides in [1, {MAX_SIDE}] pixels"
    return None


def text(v: Any) -> str | None:
    if not isinstance(v, str) or not v or len(v) > 1000 or "\x00" in v:
        return f"needs a name of 1 to 1000 characters without NUL, not {_shown(v)}"
    return None


def one_of(*choices: str, fold: bool = False) -> Callable[[Any], str | None]:
    def check(v: Any) -> str | None:
        if isinstance(v, str) and (v.upper() if fold else v) in choices:
            return None
        return f"must be one of {', '.join(choices)}, not {_shown(v)}"

    return check


def names(n: int) -> Callable[[Any], str | None]:
    def check(v: Any) -> str | None:
        if not isinstance(v, list) or len(v) != n:
            return f"needs {n} tensor names"
        bad = [x for x in v if text(x)]
        return f"has {_shown(bad[0])}, not a tensor name" if bad else None

    return check


#: A field's name -> its check (None when the value is good, else what is wrong).
RULES: dict[str, Callable[[Any], str | None]] = {
    "feature_dim": integer(1, MAX_DIM),
    "size": sides,
    "mean": numbers(3, 0.0, 1.0, "per channel, of the 0..1 image"),
    "std": numbers(3, 1e-3, 10.0, "per channel, of the 0..1 image"),
    "max_length": integer(2, MAX_TOKENS),
    "threshold": number(-50.0, 50.0),
    "box_threshold": number(0.0, 1.0),
    "mask_threshold": number(-50.0, 50.0),
    "max_boxes": integer(1, 100),
    "channel_order": one_of("RGB", "BGR", fold=True),
    "resize": one_of("area", "pil-bilinear"),
    "kind": one_of("huggingface"),
    "file": text,
    "input": text,
    "output": text,
    "input_ids": text,
    "attention_mask": text,
    "token_type_ids": text,
    "image_input": text,
    "pixel_values": text,
    "pixel_mask": text,
    "logits": text,
    "boxes": text,
    "image_embeddings": text,
    "masks": text,
    "high_res": names(2),
}


def check_values(manifest: dict, where: str) -> None:
    """Every value of the manifest against its rule (a GoiError naming the field)."""
    _walk(manifest, where, "")


def _walk(obj: dict, where: str, prefix: str) -> None:
    for name, value in obj.items():
        key = f"{prefix}{name}"
        if not prefix and name in INFORMATIVE:
            continue
        if isinstance(value, dict):
            _walk(value, where, key + ".")
            continue
        rule = RULES.get(name)
        problem = rule(value) if rule else None
        if problem:
            raise GoiError(f"{where}: field '{key}' {problem}")


def _shown(v: Any) -> str:
    s = repr(v)
    return s if len(s) <= 40 else s[:37] + "..."

"""Ranges and choices of stage options, declared once on the options dataclasses.

A field declares them with `Annotated`, e.g. `lr: Annotated[float, Range(gt=0)] = 0.01` or
`loss: Annotated[str, Choice(("logistic", "hinge"))] = "logistic"`. The CLI turns them into
click types (a bad value is refused while parsing, before any work); stages run
`check_params(params)` for library callers. Float options are always finite: NaN and infinity
are refused whatever the range.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from dataclasses import dataclass
from typing import TypeVar

from stages.core.errors import GoiError

T = TypeVar("T")


@dataclass(frozen=True)
class Range:
    """Bounds of a number: ge/le are inclusive, gt/lt exclusive; None leaves a side open."""

    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None

    def problem(self, value: float) -> str | None:
        """Why `value` is refused, or None when it is fine."""
        if isinstance(value, float) and not math.isfinite(value):
            return f"{value} is not a finite number"
        if self.ge is not None and not value >= self.ge:
            return f"{value} is below {_number(self.ge)} (it must be >= {_number(self.ge)})"
        if self.gt is not None and not value > self.gt:
            return f"{value} must be > {_number(self.gt)}"
        if self.le is not None and not value <= self.le:
            return f"{value} is above {_number(self.le)} (it must be <= {_number(self.le)})"
        if self.lt is not None and not value < self.lt:
            return f"{value} must be < {_number(self.lt)}"
        return None

    def describe(self) -> str:
        parts = []
        for op, v in ((">=", self.ge), (">", self.gt), ("<=", self.le), ("<", self.lt)):
            if v is not None:
                parts.append(f"{op} {_number(v)}")
        return " and ".join(parts)


def _number(v: float) -> str:
    return str(int(v)) if float(v).is_integer() and abs(v) < 1e15 else f"{v:g}"


@dataclass(frozen=True)
class Choice:
    """The values a text option may take."""

    values: tuple[str, ...]

    def problem(self, value: str) -> str | None:
        if value in self.values:
            return None
        return f"{value!r} is not one of {', '.join(self.values)}"


#: Often used ranges.
POSITIVE = Range(gt=0)
NON_NEGATIVE = Range(ge=0)
AT_LEAST_1 = Range(ge=1)
FRACTION = Range(ge=0, le=1)
#: Seeds: numpy and torch both take these.
SEED = Range(ge=0, le=2**32 - 1)
#: A cosine threshold.
COSINE = Range(ge=-1, le=1)


def field_range(cls: type, name: str) -> Range | None:
    """The Range a dataclass field declares, if any."""
    return _marker(cls, name, Range)


def field_choice(cls: type, name: str) -> Choice | None:
    """The Choice a dataclass field declares, if any."""
    return _marker(cls, name, Choice)


def _marker(cls: type, name: str, kind: type[T]) -> T | None:
    hint = typing.get_type_hints(cls, include_extras=True)[name]
    if typing.get_origin(hint) is typing.Annotated:
        return next((m for m in hint.__metadata__ if isinstance(m, kind)), None)
    return None


def option_name(name: str) -> str:
    return "--" + name.replace("_", "-")


def check_params(params: object) -> None:
    """Every ranged number of an options dataclass, and every float, is checked; the first
    problem raises a GoiError naming the option."""
    cls = type(params)
    for f in dataclasses.fields(params):  # type: ignore[arg-type]
        value = getattr(params, f.name)
        why = None
        if isinstance(value, str):
            choice = field_choice(cls, f.name)
            why = choice.problem(value) if choice else None
        elif isinstance(value, int | float) and not isinstance(value, bool):
            why = (field_range(cls, f.name) or Range()).problem(value)
        if why:
            raise GoiError(f"{option_name(f.name)}: {why}")


def name_list(text: str, option: str) -> list[str]:
    """A comma-separated list of names ('v001,v007'), each given once; an empty list or an
    empty item (',', 'a,,b') is refused, naming the option."""
    names = [n.strip() for n in text.split(",")]
    if not names or any(not n for n in names):
        raise GoiError(f"{option}: {text!r} is not a comma-separated list of names")
    dup = next((n for n in names if names.count(n) > 1), None)
    if dup is not None:
        raise GoiError(f"{option}: {dup!r} is named more than once")
    return names

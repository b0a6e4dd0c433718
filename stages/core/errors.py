"""The one error type the CLI turns into a clean message and exit code 2.

Everything a user can cause (a missing file, a malformed field, a bad option value) raises
`GoiError` with a message that names the file, field or option. Anything else is a bug in goi
and exits 1.
"""

from __future__ import annotations

import warnings


class GoiError(Exception):
    """A problem with the user's input; the message is shown as is, without a traceback."""


def warn(message: str) -> None:
    """A non-fatal problem the user should know about (printed once on stderr by the CLI)."""
    warnings.warn(message, GoiWarning, stacklevel=2)


class GoiWarning(UserWarning):
    pass


def check_choice(option: str, value: str, choices: tuple[str, ...]) -> str:
    """`value` when it is one of `choices`, else a GoiError naming the option."""
    if value not in choices:
        raise GoiError(f"{option}: {value!r} is not one of {', '.join(choices)}")
    return value

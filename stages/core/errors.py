"""The one error type the CLI turns into a clean message and exit code 2.

Everything a user can cause (a missing file, a malformed field, a bad option value) raises
`GoiError` with a message that names the file, field or option. Anything else is a bug in goi
and exits 1.
"""

from __future__ import annotations

import os
import warnings

#: --debug on this command's line (the CLI sets it); GOI_DEBUG=1 says the same
_debug = False


class GoiError(Exception):
    """A problem with the user's input; the message is shown as is, without a traceback."""


def warn(message: str) -> None:
    """A non-fatal problem the user should know about (printed once on stderr by the CLI)."""
    warnings.warn(message, GoiWarning, stacklevel=2)


class GoiWarning(UserWarning):
    pass


def set_debug(on: bool) -> None:
    """The CLI's --debug, for the stages that show more when it is given."""
    global _debug
    _debug = on


def debugging() -> bool:
    """Whether the user asked for the details of a failure (--debug or GOI_DEBUG=1)."""
    return _debug or os.environ.get("GOI_DEBUG", "") not in ("", "0")


def check_choice(option: str, value: str, choices: tuple[str, ...]) -> str:
    """`value` when it is one of `choices`, else a GoiError naming the option."""
    if value not in choices:
        raise GoiError(f"{option}: {value!r} is not one of {', '.join(choices)}")
    return value

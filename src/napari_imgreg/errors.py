"""Errors the package raises for bad input.

Every bad-input error is an :class:`InputError`: the command line turns it into
one line on stderr and exit code 2, the widgets into one notification.
"""

from __future__ import annotations

import os

__all__ = ["InputError", "input_error"]


class InputError(ValueError):
    """Bad input: a missing or corrupt file, a wrong field. The message names
    the file (or field) and the problem in one line."""


def input_error(path: str | os.PathLike | None, problem: str) -> InputError:
    """An :class:`InputError` whose message is ``"<file>: <problem>"``."""
    if path is None:
        return InputError(problem)
    return InputError(f"{os.fspath(path)}: {problem}")

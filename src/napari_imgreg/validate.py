"""Shared checks of inputs at the boundary, and the limits they enforce.

Every input is checked where it enters (a file read, a command-line option,
a parameter dataclass built) and before any long work: numbers finite and in
their declared range, output paths writable, images and renders of a
bounded size. A failed check raises :class:`FieldValueError` (a
``ValueError`` that knows the field, for the readers to prefix with the
file) or :class:`~napari_imgreg.errors.InputError` (one line naming the file
or option; exit code 2 on the command line). ``docs/limits.md`` lists the
limits and what each bad input gets.

This module sits beside :mod:`napari_imgreg.camera` in the layers: it
imports nothing of the package but :mod:`napari_imgreg.errors`.
"""

from __future__ import annotations

import math
import numbers
import os
import tempfile
from dataclasses import asdict, fields
from pathlib import Path
from typing import Any, ClassVar, Self

from numpy import bool_ as np_bool

from .errors import InputError, input_error

__all__ = [
    "MAX_IMAGE_SIDE_PX",
    "MAX_PHOTO_PIXELS",
    "MAX_RENDER_PIXELS",
    "FieldValueError",
    "check_number",
    "check_ranges",
    "param_range",
    "check_option",
    "check_render_size",
    "check_writable",
]

#: Largest width or height of a camera or image, pixels (JPEG's own limit is
#: 65 535; a 150 MP medium-format back is 14 204 px wide).
MAX_IMAGE_SIDE_PX = 65_535

#: Largest photo decoded, pixels (width × height): 160 MP, above every field
#: camera (150 MP medium format) and below Pillow's own decompression-bomb
#: error (179 MP). Checked from the file header, before the pixels are read:
#: a decoded RGB photo takes 3 bytes a pixel, its registration about ten
#: times more.
MAX_PHOTO_PIXELS = 160_000_000

#: Largest render, pixels: a render keeps about 60 bytes a pixel (rays,
#: coordinates, depth, normals, colour), so 64 MP (a 61 MP full-frame photo
#: at full resolution) take about 4 GB.
MAX_RENDER_PIXELS = 64_000_000


class FieldValueError(InputError):
    """A field's value is out of its range or not a number.

    The message is ``field 'NAME' PROBLEM``; :meth:`within` names the field
    inside a block (``field 'camera.fx' ...``) for a reader to prefix with
    the file.

    Parameters
    ----------
    field : str
        The field's name (``"fx"``, ``"max_trials"``).
    problem : str
        What is wrong (``"must be within [1, 100], got 0"``).
    """

    def __init__(self, field: str, problem: str) -> None:
        self.field, self.problem = field, problem
        super().__init__(f"field '{field}' {problem}")

    def within(self, block: str) -> str:
        """The message with the field named inside ``block``."""
        return f"field '{block}.{self.field}' {self.problem}"


def _bound(x: float) -> str:
    """A range bound as people write it: 1000000, not 1e+06; 0.5; inf."""
    if math.isfinite(x) and x == int(x) and abs(x) < 1e15:
        return str(int(x))
    return f"{x:g}"


def _shown(value: Any) -> str:
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if isinstance(value, tuple):
        return repr(list(value))
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def check_number(
    value: Any,
    field: str,
    low: float = -math.inf,
    high: float = math.inf,
    *,
    integer: bool = False,
    low_open: bool = False,
) -> float | int:
    """``value`` as a number after checking it is finite and in its range.

    Parameters
    ----------
    value : object
        What was given (JSON brings ints, floats, and anything else).
    field : str
        Its name, for the message.
    low, high : float
        Inclusive range (``low`` exclusive when ``low_open``).
    integer : bool
        Require a whole number (``640`` or ``640.0``); an ``int`` is returned.

    Returns
    -------
    float or int

    Raises
    ------
    FieldValueError
        Not a number (booleans neither), not finite, not whole, or out of range.
    """
    # numbers.Real: Python and NumPy ints and floats; not bool (JSON true).
    if isinstance(value, (bool, np_bool)) or not isinstance(value, numbers.Real):
        raise FieldValueError(field, f"must be a number, got {_shown(value)}")
    try:
        number = float(value)
    except OverflowError:  # an int beyond float's range (JSON allows 10**400)
        raise FieldValueError(field, f"must be within [{_bound(low)}, {_bound(high)}], got an integer of "
                              f"{len(str(abs(value)))} digits") from None
    if not math.isfinite(number):
        raise FieldValueError(field, f"must be a finite number, got {_shown(value)}")
    if integer and number != int(number):
        raise FieldValueError(field, f"must be a whole number, got {_shown(value)}")
    below = number <= low if low_open else number < low
    if below or number > high:
        bracket = "(" if low_open else "["
        raise FieldValueError(field, f"must be within {bracket}{_bound(low)}, {_bound(high)}], got "
                              f"{_shown(value)}")
    return int(number) if integer else number


def check_ranges(settings: Any) -> None:
    """Check every field named in ``settings.RANGES`` against its declared range.

    ``RANGES`` (a class attribute of each parameter dataclass) maps a field
    to its inclusive ``(low, high)`` (types are checked where the dataclass
    is read, e.g. ``RegistrationParams.from_dict``). A tuple field has every element checked; a None value
    (where the field allows it) is not checked.

    Raises
    ------
    FieldValueError
        A value out of its range, not finite, or not a number.
    """
    for name, (low, high) in settings.RANGES.items():
        value = getattr(settings, name)
        if value is None:
            continue
        for v in value if isinstance(value, (tuple, list)) else (value,):
            try:
                check_number(v, name, low, high)
            except FieldValueError:
                what = "" if isinstance(v, numbers.Real) and not isinstance(v, bool) else \
                    " (not a number)"
                raise FieldValueError(name, f"must be within [{_bound(low)}, {_bound(high)}], "
                                      f"got {_shown(value)}{what}") from None


def param_range(settings: Any, name: str) -> tuple[float, float] | None:
    """The declared ``(low, high)`` of a parameter (for a GUI's spin box), or
    None when the field has none."""
    return getattr(settings, "RANGES", {}).get(name)


def check_option(value: float, option: str, low: float, high: float,
                 *, low_open: bool = False) -> float:
    """A command-line option's number, finite and within its range.

    Raises
    ------
    InputError
        ``--scale must be within (0, 8], got nan`` (one line, exit code 2).
    """
    try:
        return check_number(value, option, low, high, low_open=low_open)
    except FieldValueError as exc:
        raise InputError(f"{option} {exc.problem}") from None


def check_render_size(width: int, height: int, what: str = "render",
                      limit: int = MAX_RENDER_PIXELS) -> None:
    """Refuse an image of more than ``limit`` pixels before it is allocated.

    Raises
    ------
    InputError
        Saying the size, the limit and by how much to reduce the scale.
    """
    pixels = int(width) * int(height)
    if pixels > limit:
        factor = math.sqrt(limit / pixels)
        raise InputError(
            f"{what} of {width}×{height} px ({pixels / 1e6:,.0f} MP) exceeds the limit of "
            f"{limit / 1e6:g} MP; reduce the scale by {factor:.3g}× or more")


def check_writable(path: str | os.PathLike, folder: bool = False) -> Path:
    """Check that an output can be written, before any long work.

    The deepest existing folder on the way to ``path`` must take a new file
    (tried with a temporary file, which is the only reliable test: read-only
    mounts, /proc, ACLs); ``path`` must not be a folder (or, with
    ``folder``, a file) and no parent may be a file. A symbolic link is
    followed: its target is checked.

    Parameters
    ----------
    path : path-like
        The output file (or folder, with ``folder=True``).
    folder : bool
        The output is a folder the command fills.

    Returns
    -------
    Path
        ``path`` as given.

    Raises
    ------
    InputError
        One line naming the path and why it cannot be written.
    """
    given = Path(path)
    target = Path(os.path.realpath(given))
    if target.exists():
        if folder and not target.is_dir():
            raise input_error(given, "cannot write here: it is a file, not a folder")
        if not folder and target.is_dir():
            raise input_error(given, "cannot write here: it is a folder, not a file")
    probe = target if folder and target.is_dir() else target.parent
    while not probe.exists():
        probe = probe.parent
    if not probe.is_dir():
        raise input_error(given, f"cannot write here: {probe} is a file, not a folder")
    try:
        fd, tmp = tempfile.mkstemp(prefix=".napari-imgreg-write-test.", dir=probe)
    except OSError as exc:
        reason = exc.strerror or type(exc).__name__
        raise input_error(given, f"cannot write here: folder {probe} does not take new "
                          f"files ({reason})") from None
    os.close(fd)
    try:
        os.unlink(tmp)
    except OSError:
        pass
    return given


def _json_ready(value: Any) -> Any:
    """Tuples as lists, at any depth (JSON has no tuples)."""
    if isinstance(value, dict):
        return {k: _json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_ready(v) for v in value]
    return value


class StageParams:
    """Base of a stage's parameter dataclass: its dict (JSON) round trip.

    A subclass is a ``@dataclass`` and names itself in ``KIND`` for the
    error on an unknown key; ``RegistrationParams.from_dict`` turns that
    error into one line naming the ``--params`` file.
    """

    KIND: ClassVar[str] = "stage"

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: nested parameter blocks as dicts, tuples as lists."""
        return _json_ready(asdict(self))  # type: ignore[call-overload]

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Self:
        """The parameters from ``d`` (every key a field; missing ones default).

        Raises
        ------
        KeyError
            A key that is not a field.
        FieldValueError
            A value outside its declared range (the subclass's check).
        """
        unknown = set(d) - {f.name for f in fields(cls)}  # type: ignore[arg-type]
        if unknown:
            raise KeyError(f"unknown {cls.KIND} parameter(s): {', '.join(sorted(unknown))}")
        return cls(**d)

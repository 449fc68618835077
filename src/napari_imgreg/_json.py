"""Strict JSON: what every file the package writes holds.

Python's :mod:`json` writes ``NaN``, ``Infinity`` and ``-Infinity`` for
non-finite floats by default. They are not JSON (RFC 8259): JavaScript, jq,
GIS tools and most other languages refuse the whole file. Every JSON writer
of the package passes its data through :func:`strict_json` first, which turns
each non-finite number into ``null`` and, in a top-level object, records why
under ``null_reasons`` (JSON Pointer → reason), so a reader can tell "no
value" from "the value was not a number". NumPy scalars and arrays become
plain numbers and lists on the way.

:func:`dumps` and :func:`dump` are :func:`json.dumps`/:func:`json.dump` with
that conversion and ``allow_nan=False`` (a value the conversion missed fails
loudly at write time rather than producing a file other tools cannot parse).
"""

from __future__ import annotations

import functools
import json
import math
from typing import IO, Any, Callable

__all__ = ["strict_json", "strict_output", "dumps", "dump", "NULL_REASONS_KEY"]

#: Key of the top-level object that says why values were written as ``null``.
NULL_REASONS_KEY = "null_reasons"


def _pointer_token(key: object) -> str:
    """One RFC 6901 reference token (``~`` and ``/`` escaped)."""
    return str(key).replace("~", "~0").replace("/", "~1")


def _describe(value: float) -> str:
    if math.isnan(value):
        return "not a number (NaN)"
    return "infinite (+Infinity)" if value > 0 else "infinite (-Infinity)"


def _convert(value: Any, pointer: str, reasons: dict[str, str]) -> Any:
    # bool before int/float: bool is an int subclass and must stay a bool.
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, int):
        return value
    if isinstance(value, float):
        if math.isfinite(value):
            return value
        reasons[pointer or "/"] = _describe(value)
        return None
    if isinstance(value, dict):
        return {str(k) if not isinstance(k, str) else k:
                _convert(v, f"{pointer}/{_pointer_token(k)}", reasons)
                for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_convert(v, f"{pointer}/{i}", reasons) for i, v in enumerate(value)]
    # NumPy (or any array-like/scalar with ``tolist``/``item``) without
    # importing numpy here: this module sits at the bottom layer.
    tolist = getattr(value, "tolist", None)
    if callable(tolist):
        return _convert(tolist(), pointer, reasons)
    item = getattr(value, "item", None)
    if callable(item):
        return _convert(item(), pointer, reasons)
    if isinstance(value, (set, frozenset)):
        return [_convert(v, f"{pointer}/{i}", reasons) for i, v in enumerate(sorted(value, key=str))]
    try:  # a numbers.Real such as fractions.Fraction or decimal.Decimal
        return _convert(float(value), pointer, reasons)
    except (TypeError, ValueError):
        raise TypeError(
            f"{pointer or '/'}: a {type(value).__name__} cannot be written as JSON"
        ) from None


def strict_json(data: Any, reasons: dict[str, str] | None = None) -> Any:
    """``data`` with every non-finite number made ``null``, as plain JSON types.

    Parameters
    ----------
    data : object
        Dicts, lists/tuples, str, bool, int, float, None, NumPy scalars and
        arrays (nested freely).
    reasons : dict of str to str, optional
        Context for particular values, JSON Pointer → reason (e.g.
        ``{"/quality/Q": "no trial solved a pose"}``); used instead of the
        generic "not a number (NaN)" for those pointers.

    Returns
    -------
    object
        A copy that :func:`json.dumps` writes with ``allow_nan=False``. When
        ``data`` is a dict and some value was not finite, the copy has a
        ``null_reasons`` object: JSON Pointer (RFC 6901) of each ``null``
        written for a non-finite number → why (merged with any
        ``null_reasons`` already present). Data without non-finite numbers
        is returned unchanged in content (no ``null_reasons`` key is added).

    Raises
    ------
    TypeError
        A value that has no JSON form (an arbitrary object), naming its place.
    """
    found: dict[str, str] = {}
    out = _convert(data, "", found)
    if found and isinstance(out, dict):
        context = reasons or {}
        merged = dict(out.get(NULL_REASONS_KEY) or {}) \
            if isinstance(out.get(NULL_REASONS_KEY), dict) else {}
        for pointer, what in found.items():
            merged[pointer] = f"{context[pointer]} (was {what})" if pointer in context else what
        out[NULL_REASONS_KEY] = merged
    return out


def strict_output(method: Callable[..., Any]) -> Callable[..., Any]:
    """Decorate a ``to_dict``-like method so that what it returns is strict JSON."""

    @functools.wraps(method)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        return strict_json(method(*args, **kwargs))

    return wrapper


def dumps(data: Any, **kwargs: Any) -> str:
    """:func:`json.dumps` of :func:`strict_json` ``(data)``, ``allow_nan=False``."""
    kwargs.setdefault("allow_nan", False)
    return json.dumps(strict_json(data), **kwargs)


def dump(data: Any, fh: IO[str], **kwargs: Any) -> None:
    """:func:`json.dump` of :func:`strict_json` ``(data)``, ``allow_nan=False``.

    The same text as :func:`json.dump` writes, made by :func:`json.dumps`
    and written at once: ``json.dump`` never uses the C encoder (several
    times faster; used without ``indent``) and writes every token apart.
    """
    kwargs.setdefault("allow_nan", False)
    fh.write(json.dumps(strict_json(data), **kwargs))

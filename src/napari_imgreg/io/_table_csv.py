"""The small CSV tables users write by hand or export from a spreadsheet
(orientation tables, control points): one way to read them and their numbers.

Commas, semicolons or tabs separate fields (the header line says which);
blank lines and lines starting with ``#`` are skipped; a byte-order mark is
ignored. In a table separated by semicolons (what a spreadsheet writes where
the decimal separator is a comma: most of Europe) a number may have a
decimal comma, ``12,5``. The text must be UTF-8 (Excel: "CSV UTF-8"). Rows are numbered by their line in the file (the header being row 1
when it is the first line), so that a message names the line a user sees.
"""

from __future__ import annotations

import csv
import math
import re
from pathlib import Path

from ..errors import input_error

__all__ = ["read_table_rows", "cell_number", "header_excerpt"]

_DELIMITERS = (",", ";", "\t")
#: A number written with a decimal comma (``-12,5``, ``1,5e3``).
_DECIMAL_COMMA = re.compile(r"[+-]?\d*,\d+(?:[eE][+-]?\d+)?")

#: Characters of a header quoted in a message, at most.
HEADER_EXCERPT_CHARS = 80


def header_excerpt(header: list[str], limit: int = HEADER_EXCERPT_CHARS) -> str:
    """The header as a message quotes it: its names joined by commas, cut to
    ``limit`` characters (with "…")."""
    text = ",".join(header)
    return text if len(text) <= limit else text[: limit - 1].rstrip(",") + "…"


def _not_a_table(text: str) -> str | None:
    """What a file clearly not a CSV table is ("a GeoJSON file", "a JSON
    file"), from its first character; None for anything else."""
    head = text.lstrip()[:1]
    if head not in ("{", "["):
        return None
    start = text.lstrip()[:2000].lower()
    if '"featurecollection"' in start.replace(" ", "") or '"feature"' in start.replace(" ", ""):
        return "a GeoJSON file"
    return "a JSON file"


def read_table_rows(path: Path, expected: str) -> tuple[list[str], list[tuple[int, list[str]]]]:
    """The header and the data rows of a hand-written CSV table.

    Parameters
    ----------
    path : Path
    expected : str
        What the header should be, for the message of an empty file
        (``"expected photo,trend_deg,..."``).

    Returns
    -------
    header : list of str
        Column names, stripped and lower-cased.
    rows : list of (int, list of str)
        Each data row's line number and its cells, stripped, padded with
        empty cells to the header's length.

    Raises
    ------
    InputError
        A missing, unreadable or empty file; a JSON or GeoJSON file
        (``"<file>: a GeoJSON file, not a CSV table"``).
    """
    if not path.exists():
        raise input_error(path, "no such file")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        # Excel's plain "CSV" is in the Windows code page (cp1252): "Störung"
        # is not UTF-8. Guessing the code page could misread names silently.
        line = exc.object[:exc.start].count(b"\n") + 1
        raise input_error(path, f"line {line}: not UTF-8 text; save the table as UTF-8 "
                                "(Excel: 'CSV UTF-8')") from None
    except OSError as exc:
        raise input_error(path, f"cannot read ({exc})") from None
    kind = _not_a_table(text)
    if kind is not None:
        raise input_error(path, f"{kind}, not a CSV table")
    lines = [(number, line) for number, line in enumerate(text.splitlines(), start=1)
             if line.strip() and not line.lstrip().startswith("#")]
    if not lines:
        raise input_error(path, f"empty file ({expected})")
    delimiter = next((d for d in _DELIMITERS if d in lines[0][1]), ",")
    parsed = list(csv.reader((line for _, line in lines), delimiter=delimiter))
    header = [h.strip().lower() for h in parsed[0]]
    rows = []
    for (number, _), row in zip(lines[1:], parsed[1:]):
        cells = [c.strip() for c in row]
        if delimiter == ";":  # a decimal-comma spreadsheet's numbers
            cells = [c.replace(",", ".") if _DECIMAL_COMMA.fullmatch(c) else c for c in cells]
        rows.append((number, cells + [""] * max(0, len(header) - len(cells))))
    return header, rows


def cell_number(path: Path, row: int, column: str, cell: str, optional: bool = False) -> float:
    """A cell's finite number (an empty optional cell: NaN).

    Raises
    ------
    InputError
        ``"<file>: row N: <column> is empty / is not a number / is not a
        finite number"``.
    """
    if cell == "":
        if optional:
            return math.nan
        raise input_error(path, f"row {row}: {column} is empty")
    try:
        value = float(cell)
    except ValueError:
        raise input_error(path, f"row {row}: {column} is not a number ({cell!r})") from None
    if not math.isfinite(value):
        raise input_error(path, f"row {row}: {column} is not a finite number ({cell!r})")
    return value

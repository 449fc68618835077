"""Shared by the benchmark scripts: each owns one marked section of a markdown
report (``<!-- bench_NAME:start -->`` … ``<!-- bench_NAME:end -->``) and
rewrites only that section, atomically, keeping the others."""

from __future__ import annotations

from pathlib import Path

from napari_imgreg._atomic import atomic_write


def markers(name: str) -> tuple[str, str]:
    """The start and end markers of benchmark ``name``'s section."""
    return f"<!-- {name}:start -->", f"<!-- {name}:end -->"


def write_section(path: Path, section: str, start: str, end: str) -> None:
    """Replace the text between ``start`` and ``end`` (markers included in
    ``section``) in the markdown file ``path``, or append it."""
    text = path.read_text(encoding="utf-8") if path.exists() else "# Benchmarks\n\n"
    if start in text and end in text:
        before, rest = text.split(start, 1)
        text = before + section + rest.split(end, 1)[1]
    else:
        text = text.rstrip() + "\n\n" + section + "\n"
    with atomic_write(path, encoding="utf-8") as fh:
        fh.write(text)

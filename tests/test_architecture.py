"""The layer rules of docs/architecture.md, checked by import-linter.

The contracts live in ``pyproject.toml`` (``[tool.importlinter]``); this test
runs them on the installed tree, and once on a copy with a deliberately wrong
import, to show that they bite.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "src" / "napari_imgreg"

pytest.importorskip("importlinter")


def _lint_imports(src_dir: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(src_dir))
    # --no-cache: the copy below has the same module names as the real tree.
    return subprocess.run(
        [sys.executable, "-c",
         "import sys; from importlinter.cli import lint_imports_command; "
         "sys.exit(lint_imports_command())",
         str(ROOT / "pyproject.toml"), "--no-cache", "--no-logo"],
        cwd=src_dir, env=env, capture_output=True, text=True, timeout=300,
    )


def test_import_contracts_are_kept():
    run = _lint_imports(ROOT / "src")
    assert run.returncode == 0, run.stdout[-4000:] + run.stderr[-2000:]
    assert "0 broken" in run.stdout


def test_a_wrong_import_breaks_the_contracts(tmp_path):
    copy = tmp_path / "src" / "napari_imgreg"
    shutil.copytree(PACKAGE, copy, ignore=shutil.ignore_patterns("__pycache__"))
    camera = copy / "camera.py"
    # The lowest layer reaching up into the pipeline and into Qt.
    camera.write_text(camera.read_text() + "\nimport napari_imgreg.registration.pipeline\nimport qtpy\n")
    run = _lint_imports(tmp_path / "src")
    assert run.returncode == 1, run.stdout[-4000:]
    out = " ".join(run.stdout.split())
    assert "napari_imgreg.camera is not allowed to import napari_imgreg.registration" in out
    assert "napari_imgreg.camera -> qtpy" in out

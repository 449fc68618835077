"""The splat renderer as it was before issue 16's speed-ups (commit d4da268),
loaded from the repository's history instead of kept as a copy: the "old
kernel" that ``bench_cloud_render.py`` times beside the current one and that
``tests/test_cloud_scene.py`` compares with, bit for bit.

:func:`load` runs ``git show d4da268:src/napari_imgreg/render_points.py`` and
executes it (from a copy in the temporary folder, where numba can cache its
kernels) as ``napari_imgreg._render_points_before`` (its relative imports
then find today's ``camera``, ``errors`` and ``validate``, whose interfaces it
uses unchanged). It returns None where the history is not there (an sdist, a
shallow clone without that commit, no git).
"""

from __future__ import annotations

import subprocess
import sys
import types
from pathlib import Path

BEFORE_COMMIT = "d4da268"
SOURCE = "src/napari_imgreg/render_points.py"
MODULE = "napari_imgreg._render_points_before"


def load() -> types.ModuleType | None:
    """The old renderer as a module, or None when git cannot give it."""
    if MODULE in sys.modules:
        return sys.modules[MODULE]
    root = Path(__file__).resolve().parents[1]
    try:
        code = subprocess.run(["git", "show", f"{BEFORE_COMMIT}:{SOURCE}"], cwd=root,
                              capture_output=True, text=True, check=True, timeout=30).stdout
    except (OSError, subprocess.SubprocessError):
        return None
    import importlib.util
    import tempfile

    import napari_imgreg  # noqa: F401  (the package its relative imports resolve in)

    # A real file: numba caches its compiled kernels beside their source.
    path = Path(tempfile.gettempdir()) / f"napari_imgreg_render_points_{BEFORE_COMMIT}.py"
    if not path.exists() or path.read_text() != code:
        tmp = path.with_suffix(".tmp")
        tmp.write_text(code)
        tmp.replace(path)
    spec = importlib.util.spec_from_file_location(MODULE, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[MODULE] = module  # its dataclasses look their module up
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[MODULE]
        raise
    return module

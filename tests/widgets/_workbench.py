"""Helpers of the workbench GUI tests (the fixture is in ``conftest.py``)."""

from __future__ import annotations

#: ms: the first run on a fresh machine generates the sample scene.
LOAD_S = 90_000


def idle(wb, qtbot, timeout: int = 30_000) -> None:
    """Wait until the workbench runs no job."""
    qtbot.waitUntil(lambda: not wb.controller.busy, timeout=timeout)


def load_sample(wb, qtbot):
    """Open the bundled sample in the workbench; returns its controller."""
    wb.scene_panel.sample_button.click()
    qtbot.waitUntil(lambda: wb.controller.current is not None, timeout=LOAD_S)
    idle(wb, qtbot)
    return wb.controller

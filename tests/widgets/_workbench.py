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


def save_and_reopen(wb, qtbot, folder):
    """Save the workbench's workspace as ``folder`` (``.imgreg`` added), let
    it go and open it again in the same window; returns the workspace opened."""
    from pathlib import Path

    ctrl = wb.controller
    ctrl.save_workspace(folder)
    saved = Path(str(folder) + ".imgreg")
    idle(wb, qtbot)
    ctrl.workspace.detach()
    ctrl.open_workspace(saved)
    qtbot.waitUntil(lambda: ctrl.workspace_folder is not None and ctrl.current is not None,
                    timeout=LOAD_S)
    idle(wb, qtbot)
    return ctrl.workspace

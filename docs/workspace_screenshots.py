"""Screenshots of docs/workspace.md, taken from a real napari window.

Drives the registration workbench through the workspace workflow on the
sample outcrop — load (with its busy bar), Register all (real registrations,
in the background), the photos table, save as a workspace folder, reopen it
by dropping it onto napari, the File menu — and saves each step's window to
``docs/images/workspace_*.png``. Needs a display (Xvfb is fine)::

    xvfb-run -a -s "-screen 0 1600x1000x24" .venv/bin/python docs/workspace_screenshots.py

Registering the three sample photos takes a few minutes on a laptop. Look at
every image before committing it.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
from pathlib import Path

OUT = Path(__file__).parent / "images"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=OUT)
    parser.add_argument("--only", nargs="*", help="names of the shots to take (default: all)")
    args = parser.parse_args()

    import napari
    from _screenshot_session import open_workbench
    from qtpy.QtCore import QPoint, QTimer

    from napari_imgreg.widgets.workbench import PHOTOS_TAB, WORKBENCH_NAME

    app, viewer, wb, pump, wait = open_workbench(wait_timeout_s=900.0)
    ctrl = wb.controller

    def idle() -> None:
        wait(lambda: not ctrl.busy)

    def shot(name: str, v=None) -> None:
        if args.only and name not in args.only:
            return
        pump(0.8)
        path = args.out / f"workspace_{name}.png"
        (v or viewer).screenshot(str(path), canvas_only=False)
        print("wrote", path)

    # 1. Loading the sample: a busy bar and a line saying what is going on.
    wb.show_tab("Scene")
    wb.scene_panel.sample_button.click()
    pump(0.4)
    shot("loading")
    wait(lambda: ctrl.current is not None)
    idle()

    # 2. Register all, under way: the table fills in as the photos register.
    wb.show_tab(PHOTOS_TAB)
    wb.photos_table.register_all_button.click()
    wait(lambda: len([p for p in ctrl.photos if p.registration is not None]) >= 1)
    shot("register_all")
    wait(lambda: not ctrl.is_running("register all"))
    idle()

    # 3. The photos table: status, grade, Q, ± px, time; sorted by Q.
    ctrl.select_photo(1)
    idle()
    ctrl.accept()  # accepted by the user: no longer needs attention
    wb.photos_table.table.sortItems(2)  # by status
    ctrl.select_photo(0)
    idle()
    shot("photos")

    # 4. Saved as a workspace folder: the bar says where, and that it autosaves.
    tmp = Path(tempfile.mkdtemp(prefix="imgreg-shots-"))
    folder = tmp / "campaign.imgreg"
    ctrl.save_workspace(folder)  # written in a worker behind a modal dialog
    wait(lambda: not ctrl.saving)
    shot("saved")

    # 5. The File menu's entries (File → IO utilities).
    if not args.only or "file_menu" in args.only:
        window = viewer.window._qt_window
        file_menu = viewer.window.file_menu
        sub = next(a.menu() for a in file_menu.actions()
                   if a.menu() is not None and "IO" in a.text().replace("&", ""))
        file_menu.popup(window.mapToGlobal(QPoint(10, 25)))
        pump(0.5)
        action = next(a for a in file_menu.actions() if a.menu() is sub)
        file_menu.setActiveAction(action)
        sub.popup(file_menu.mapToGlobal(file_menu.actionGeometry(action).topRight()))
        pump(0.8)
        screen = app.primaryScreen()
        path = args.out / "workspace_file_menu.png"
        geo = window.frameGeometry()
        screen.grabWindow(0, geo.x(), geo.y(), 900, 420).save(str(path))
        print("wrote", path)
        sub.close()
        file_menu.close()

    # 6. Dropped onto a new napari window: the workbench opens it.
    ctrl.workspace.detach()
    viewer2 = napari.Viewer(title="napari-imgreg", show=True)
    viewer2.window._qt_window.resize(1600, 1000)
    pump(0.5)
    viewer2.open(str(folder), plugin="napari-imgreg")
    wb2 = viewer2.window.dock_widgets[WORKBENCH_NAME]
    wait(lambda: wb2.controller.current is not None and wb2.controller.workspace_folder)
    wait(lambda: not wb2.controller.busy)
    wb2.show_tab(PHOTOS_TAB)
    shot("reopened", viewer2)
    wb2.controller.workspace.detach()
    QTimer.singleShot(0, app.quit)
    shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()

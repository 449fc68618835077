"""Screenshots of docs/interpretation.md, taken from a real napari window.

The Interpret dock on its own (*Plugins → Outcrop registration:
napari-imgreg → Interpret*), as section 1 of the guide sets it up: the sample
outcrop opened as napari sample data, the photo ``IMG_0002.jpg`` opened
beside it and given its registration (``napari-imgreg register``, then
*Attach RESULT.json…*), the sample's true bed boundaries and fault drawn on
it by hand (the sample's example drawing ``IMG_0002.lines.geojson``, loaded
as with *Load GeoJSON…*), then *Project onto the model* and *Show in 3D*.
Saves ``docs/images/interpretation_photo.png``, ``interpretation_3d.png``
and ``interpretation_3d_oblique.png``. Needs a display (Xvfb is fine)::

    xvfb-run -a -s "-screen 0 1600x1000x24" .venv/bin/python docs/interpretation_screenshots.py

The registration takes some seconds. Look at every image before committing it.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

OUT = Path(__file__).parent / "images"
PHOTO = "IMG_0002.jpg"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()

    import napari
    from qtpy.QtWidgets import QApplication

    from napari_imgreg.sample import sample_scene

    folder = sample_scene("small")
    tmp = Path(tempfile.mkdtemp(prefix="imgreg-interp-shots-"))

    # The registration, as the guide has it: napari-imgreg register.
    result = tmp / f"{Path(PHOTO).stem}.result.json"
    cli = Path(sys.executable).with_name("napari-imgreg")
    subprocess.run([str(cli), "register", str(folder / "outcrop.obj"), str(folder / PHOTO),
                    "--dem", str(folder / "dem.tif"), "--out", str(result)], check=True)

    # What a geologist draws on it: the visible true contacts, by hand (the
    # sample's example drawing beside the photo; made here for an older sample).
    lines = folder / f"{Path(PHOTO).stem}.lines.geojson"
    if not lines.is_file():
        from napari_imgreg import Scene
        from napari_imgreg.sample import load_truth
        from napari_imgreg.sample.drawing import drawing_geojson, visible_stretches

        truth = load_truth(folder)
        pt = truth.photos[PHOTO]
        scene = Scene.load(folder / "outcrop.obj", dem=folder / "dem.tif")
        drawing = drawing_geojson(visible_stretches(scene, pt.intrinsics, pt.pose, truth.lines),
                                  np.random.default_rng(0))
        lines = tmp / lines.name
        lines.write_text(json.dumps(drawing))

    from _screenshot_session import event_pumps

    app = QApplication.instance() or QApplication([])
    pump, wait = event_pumps(app, 300.0)

    def shot(name: str) -> None:
        pump(0.8)
        path = args.out / f"interpretation_{name}.png"
        viewer.screenshot(str(path), canvas_only=False)
        print("wrote", path)

    viewer = napari.Viewer(title="napari-imgreg", show=True)
    scene = getattr(viewer, "scene", None)  # napari >= 0.9 keeps the camera there
    camera = scene.camera if scene is not None and hasattr(scene, "camera") else viewer.camera
    viewer.window._qt_window.resize(1600, 1000)
    pump(0.5)
    # File → Open Sample → … → Outcrop model, then the photo.
    viewer.open_sample("napari-imgreg", "outcrop_model")
    viewer.open(str(folder / PHOTO), plugin="napari")
    pump(0.5)
    _dock, iw = viewer.window.add_plugin_dock_widget("napari-imgreg", "Interpret")
    pump(0.5)
    iw.photo_combo.setCurrentText(Path(PHOTO).stem)
    iw.surface_combo.setCurrentText("sample outcrop")
    iw.attach_result(result)
    shapes = iw.load_geojson(lines)
    viewer.layers.selection.active = shapes
    shapes.mode = "pan_zoom"
    shapes.selected_data = set()
    viewer.dims.ndisplay = 2
    # The model steps back over the photo (its 2D slice is a stray line); the
    # photo as large as the canvas holds it. Show in 3D shows the model again.
    viewer.layers["sample outcrop"].visible = False
    photo = viewer.layers[Path(PHOTO).stem]
    extent = np.asarray(photo.extent.world, float)[:, -2:]
    cam = camera
    cam.center = (cam.center[0],) * (len(cam.center) - 2) + tuple(extent.mean(axis=0))
    canvas_h, canvas_w = viewer.canvas.size
    cam.zoom = 0.98 * min(canvas_h / np.ptp(extent[:, 0]), canvas_w / np.ptp(extent[:, 1]))
    pump(0.5)
    shot("photo")

    # Project onto the model, Show in 3D (from the photo's viewpoint).
    iw.project_button.click()
    wait(lambda: iw.project_button.isEnabled() and bool(iw.features))
    iw.view3d_button.click()
    pump(1.5)
    shot("3d")

    # Obliquely, from the left and above: the lines wrap around the relief.
    cam = camera
    cam.set_view_direction((-0.55, 0.5, 0.75), up_direction=(1.0, 0.0, 0.0))
    cam.zoom *= 1.8
    pump(1.5)
    path = args.out / "interpretation_3d_oblique.png"
    viewer.screenshot(str(path), canvas_only=True)
    print("wrote", path)
    viewer.close()
    shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()

"""Screenshots of the user guide, taken from a real napari window.

Drives the registration workbench through the walk-through of
``docs/user-guide.md`` on the sample outcrop and saves each step's window to
``docs/images/workbench_*.png``. Needs a display (Xvfb is fine)::

    xvfb-run -a -s "-screen 0 1600x1000x24" .venv/bin/python docs/user_guide_screenshots.py

Look at every image before committing it.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

OUT = Path(__file__).parent / "images"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=OUT)
    parser.add_argument("--only", nargs="*", help="names of the shots to take (default: all)")
    args = parser.parse_args()

    from _screenshot_session import open_workbench

    from napari_imgreg.sample import load_truth, truth_pairs
    from napari_imgreg.widgets._layers import napari_from_pixels

    _app, viewer, wb, pump, wait = open_workbench(wait_timeout_s=120.0)
    ctrl = wb.controller
    # The quality panel at the height a user gets (it fits its banner, legend,
    # all eight metric rows and the trials at 1600 × 1000).
    pump(1.0)

    def idle() -> None:
        wait(lambda: not ctrl.busy)

    def shot(name: str) -> None:
        if args.only and name not in args.only:
            return
        pump(0.8)
        path = args.out / f"workbench_{name}.png"
        viewer.screenshot(str(path), canvas_only=False)
        print("wrote", path)

    # 1. Scene: the sample, photo beside the render from its prior.
    wb.show_tab("Scene")
    wb.scene_panel.sample_button.click()
    wait(lambda: ctrl.current is not None)
    idle()
    shot("scene")

    # 2. 3D: the model, the cameras and their view frusta.
    # (the button's own overview: facing the outcrop as the cameras do, 30° down)
    wb.scene_panel.view_3d_button.click()
    pump(1.5)
    shot("3d")
    wb.scene_panel.view_2d_button.click()
    idle()

    # 3. Pose: nudges and the DEM map.
    wb.show_tab("Pose")
    wb.pose_panel.nudge_buttons["turn left"].click()
    wb.pose_panel.nudge_buttons["turn left"].click()
    idle()
    x, y, _ = ctrl.current.pose.center
    ctrl.move_on_map(x + 3.0, y + 1.5)
    ctrl.finish_drag()
    idle()
    shot("pose")

    # 4. Filters: Wallis on photo and render, previewed.
    wb.show_tab("Filters")
    fp = wb.filters_panel
    fp.link_check.setChecked(True)
    fp.preview_check.setChecked(True)
    fp.photo_editor.wallis_check.setChecked(True)
    fp.photo_editor.widgets["gamma"].setValue(1.3)
    idle()
    shot("filters")
    fp.preview_check.setChecked(False)
    fp.photo_editor.reset()
    fp.render_editor.reset()
    fp.link_check.setChecked(False)
    idle()

    # 5. Register: a strict first Run (fair), the hint and the suggestion
    # (keypoints only: the stages for another light come in step 10).
    wb.show_tab("Register")
    rp = wb.register_panel
    for check in (rp.sun_relight_check, rp.area_match_check, rp.edge_align_check,
                  rp.dense_refine_check):
        check.setChecked(False)
    rp.threshold_spin.setValue(3.0)
    rp.max_features_spin.setValue(600)
    rp.outlier_check.setChecked(True)
    rp.run_button.click()
    wait(lambda: bool(ctrl.current.trials) and not ctrl.is_running("registration"))
    idle()
    shot("run")

    # 6. Apply the suggestion, Auto: the grade, arrows, history, correspondences.
    wb.quality.apply_button.click()
    rp.outlier_check.setChecked(False)
    rp.auto_button.click()
    wait(lambda: len(ctrl.current.trials) >= 2 and not ctrl.is_running("registration"))
    idle()
    shot("auto")

    # 7. The result: the render from the estimated pose blended over the photo.
    rp.corr_check.setChecked(False)
    ctrl.set_blend(opacity=0.5, visible=True)
    rp.blend_slider.setValue(0.5)
    # The photo as large as the canvas holds it (fit_to_view fails on a 2D
    # layer while the viewer has three dimensions).
    extent = np.asarray(ctrl.photo_layer().extent.world, float)[:, -2:]
    cam = ctrl.camera
    cam.center = (cam.center[0],) * (len(cam.center) - 2) + tuple(extent.mean(axis=0))
    canvas_h, canvas_w = viewer.canvas.size
    cam.zoom = 0.98 * min(canvas_h / np.ptp(extent[:, 0]), canvas_w / np.ptp(extent[:, 1]))
    shot("blend")
    rp.corr_check.setChecked(True)
    ctrl.fit_2d()

    # 8. Manual: reference render, pairs from the truth's check points, solve.
    wb.scene_panel.photo_list.setCurrentRow(1)
    idle()
    wb.show_tab("Manual")
    wb.manual_panel.ref_pose_button.click()
    wait(lambda: ctrl.current.reference is not None)
    ps = ctrl.current
    photo_px, ref_px, _ = truth_pairs(load_truth(ps.photo.path), ps.reference, ps.size)
    wb.manual_panel.pick_button.click()
    photo_layer, ref_layer = ctrl.pair_layers()
    for p, r in zip(photo_px, ref_px):
        photo_layer.add(napari_from_pixels(p))
        ref_layer.add(napari_from_pixels(r))
    viewer.layers.selection.active = ref_layer
    ref_layer.mode = "pan_zoom"
    pump(0.5)
    wb.manual_panel.solve_button.click()
    wait(lambda: ps.manual_solution is not None and not ctrl.is_running("manual"))
    idle()
    rp.corr_check.setChecked(False)  # the pairs, not the scoring's matches
    ctrl.set_blend(visible=False)
    shot("manual")

    # 8b. The same photo's eight surveyed targets, loaded from the sample's
    # CSV (named GCP1..8, one beyond the reference's view) and solved.
    wb.manual_panel.load_pairs(ps.photo.path.with_name("IMG_0002.pairs.csv"))
    wb.manual_panel.solve_button.click()
    wait(lambda: not ctrl.is_running("manual"))
    idle()
    rp.corr_check.setChecked(True)  # the photo's matches confirming the pose
    shot("manual_loaded")
    rp.corr_check.setChecked(False)

    # 9. The Interpret tab: the interpretation tools docked in the workbench.
    wb.show_tab("Interpret")
    shot("interpret")

    # 9b. Snapping: two clicks on a bed boundary, the line follows the contact.
    iw = wb.interpret_widget
    if iw is not None and (not args.only or "snap" in args.only):
        scene_truth = load_truth(Path(ps.photo.path).parent)
        truth = scene_truth.photos[ps.name]  # the photo's true camera and pose
        photo_layer = iw.photo_layer
        image = np.asarray(photo_layer.data)
        ph, pw = image.shape[:2]
        best = None
        for feat in scene_truth.lines["features"]:
            if feat["properties"]["label"] != "bed_boundary":
                continue
            px = truth.pose.project(truth.intrinsics, np.asarray(feat["geometry"]["coordinates"]))
            ok = np.isfinite(px).all(1) & (px > 30).all(1) & (px[:, 0] < pw - 30) & (px[:, 1] < ph - 30)
            if ok.all():
                bend = np.ptp(px[:, 1] - np.interp(px[:, 0], px[[0, -1], 0], px[[0, -1], 1]))
                length = np.linalg.norm(px[-1] - px[0])
                if 200 < length < 450 and (best is None or bend > best[1]):
                    best = (px, bend)
        iw.snap_check.setChecked(True)
        for _ in range(200):  # the model's view, rendered ahead, for the snap to follow
            if iw._reference_cache is not None:
                break
            pump(0.05)
        shapes = iw.new_interpretation_layer()
        clicks = best[0][[0, -1]]
        shapes.add(napari_from_pixels(clicks), shape_type="path")
        iw.snap_shape(shapes, len(shapes.data) - 1)
        # The two clicks, as white points.
        viewer.add_points(napari_from_pixels(clicks), name="the two clicks", size=9,
                          face_color="white", border_color="black",
                          scale=photo_layer.scale[-2:], translate=photo_layer.translate[-2:])
        shapes.mode = "pan_zoom"
        shapes.selected_data = set()
        viewer.layers.selection.active = shapes
        centre = best[0].mean(axis=0)
        cam = viewer.camera
        world = photo_layer.data_to_world(napari_from_pixels(centre[None])[0])
        cam.center = (cam.center[0],) * (len(cam.center) - 2) + tuple(world[-2:])
        _, canvas_w = viewer.canvas.size
        cam.zoom = 0.85 * canvas_w / (np.ptp(best[0][:, 0]) * float(photo_layer.scale[-1]))
        from napari.layers import Points

        hidden = []
        for layer in viewer.layers:  # the manual pairs' points step back
            if isinstance(layer, Points) and layer.name != "the two clicks" and layer.visible:
                layer.visible = False
                hidden.append(layer)
        pump(0.5)
        shot("snap")
        # Back as the next steps expect it.
        viewer.layers.remove("the two clicks")
        for layer in hidden:
            layer.visible = True
        iw.snap_check.setChecked(False)

    # 10. Another sun: the third photo (a low morning sun from the east; the
    # texture was lit from the south-south-east). A Run with a detector too
    # strict for keypoints to verify goes through the stages for another
    # light; Auto with the defaults registers; the sun-lit preview shows the
    # model under the photo's sun.
    from napari_imgreg.registration.params import RegistrationParams

    wb.scene_panel.photo_list.setCurrentRow(2)
    idle()
    wb.show_tab("Register")
    ctrl.set_blend(visible=False)
    ctrl.params = RegistrationParams()
    ctrl.params_changed.emit()
    rp.threshold_spin.setValue(4.0)
    rp.max_features_spin.setValue(500)
    rp.run_button.click()
    wait(lambda: bool(ctrl.current.trials) and not ctrl.is_running("registration"))
    ctrl.params = RegistrationParams()
    ctrl.params_changed.emit()
    rp.auto_button.click()
    wait(lambda: ctrl.current.runs >= 2 and not ctrl.is_running("registration"))
    idle()
    rp.corr_check.setChecked(False)
    rp.blend_check.setChecked(False)
    rp.sun_box.preview_check.setChecked(True)
    idle()
    viewer.layers.selection.active = ctrl.layers.get("render")
    ctrl.fit_2d()
    cam = ctrl.camera
    h = ctrl.layers.height
    cam.center = (cam.center[0], 0.4 * h, cam.center[-1])
    cam.zoom *= 1.2
    wb.tabs.currentWidget().ensureWidgetVisible(rp.sun_box)
    shot("sun")

    viewer.close()


def views_main(out: Path) -> None:
    """The campaign view and the Interpret tab while drawing (issue 17), on the
    small sample with two photos at their true poses (recorded as
    registrations) and true bed boundaries drawn on them; no registration
    runs, so it takes seconds::

        xvfb-run -a -s "-screen 0 1600x1000x24" .venv/bin/python \\
            docs/user_guide_screenshots.py --views
    """
    from _screenshot_session import open_workbench

    from napari_imgreg.interpret.project import Interpretation
    from napari_imgreg.registration.params import RegistrationParams
    from napari_imgreg.registration.pipeline import Registration, Trial
    from napari_imgreg.sample import load_truth, sample_scene
    from napari_imgreg.widgets._layers import napari_from_pixels
    from napari_imgreg.widgets.campaign import CampaignView
    from napari_imgreg.workspace import read_photos, read_scene

    _app, viewer, wb, pump, _wait = open_workbench()
    ctrl = wb.controller
    ws = ctrl.workspace
    folder = sample_scene("small")
    truth = load_truth(folder)
    scene, terrain = read_scene(folder / "outcrop.obj", dem=folder / "dem.tif")
    loaded, _ = read_photos(sorted(folder.glob("IMG_*.jpg")), scene)
    ws.load_scene(scene, terrain, {"mesh": folder / "outcrop.obj", "dem": folder / "dem.tif"})
    ws.add_loaded_photos(loaded)
    pump(2.0)
    for ps in ws.photos[:2]:
        pose = truth.photos[ps.name].pose
        trial = Trial(index=0, params=RegistrationParams(), metrics={}, q=0.8, grade="good",
                      hints=[], pose=pose, start_pose=ps.pose, rounds=1, converged=True,
                      verified=True, residual_flow_px=0.5)
        ws.record_registration(Registration(
            status="registered", photo=ps.name, intrinsics=ps.intrinsics, pose=pose,
            prior=ps.prior, metrics={}, q=0.8, grade="good", hints=[], trials=[trial],
            timings_s={"total": 1.0}, best_trial=0), "Auto", ps=ps, pose_if_not_current=True)
        pt = truth.photos[ps.name]
        for feat in truth.lines["features"]:
            px = pt.pose.project(pt.intrinsics, np.asarray(feat["geometry"]["coordinates"]))
            ok = np.isfinite(px).all(1) & (px > 5).all(1)
            ok &= (px[:, 0] < pt.intrinsics.width - 5) & (px[:, 1] < pt.intrinsics.height - 5)
            if feat["properties"]["label"] == "bed_boundary" and ok.all():
                ws.add_interpretation(Interpretation("LineString", px, {"label": "sandstone"}), ps)
    ws.project_interpretations()
    ws.accept(ws.photos[0])
    pump(2.0)

    # The Interpret tab while drawing: the render overlay (on, at half opacity)
    # steps back while the line is drawn over the photo.
    ctrl.set_blend(opacity=0.5, visible=True)
    wb.show_tab("Interpret")
    iw = wb.interpret_widget
    pump(1.0)
    shapes = iw.new_interpretation_layer()
    # a true bed boundary on the photo: the longest, so the drawn line shows
    px = max((it.pixels for it in ws.current.interpretations),
             key=lambda p: float(np.ptp(np.asarray(p)[:, 0])))
    shapes.add(napari_from_pixels(px[:: max(1, len(px) // 6)]), shape_type="path",
               edge_width=12)
    shapes.mode = "add_polyline"
    ctrl.fit_2d()
    cam = ctrl.camera  # the photo, large
    cam.center = (cam.center[0], 0.5 * ctrl.layers.height, 0.5 * ctrl.layers.width)
    cam.zoom *= 1.9
    pump(1.0)
    viewer.screenshot(str(out / "workbench_drawing.png"), canvas_only=False)
    print("wrote", out / "workbench_drawing.png")
    shapes.mode = "pan_zoom"

    # The campaign view: every camera, every mapped line, every measurement.
    view = CampaignView(viewer, workspace=ws)
    viewer.window.add_dock_widget(view, name="Campaign view", area="right", tabify=True)
    view.show_3d()
    pump(1.5)
    # Only the campaign's own layers over the model. The workbench's cameras
    # (cyan, the current one magenta) sit on the campaign's markers and hide
    # their status colours, and the photo's interpretation layer (pixels, 2D)
    # would show as stray strokes beside the model: stepped back here.
    from napari.layers import Shapes

    for layer in viewer.layers:
        if layer.name in ("cameras", "view frusta") or (
                isinstance(layer, Shapes) and layer.name.endswith(" interpretation")):
            layer.visible = False
    pump(1.0)
    viewer.screenshot(str(out / "workbench_campaign.png"), canvas_only=False)
    print("wrote", out / "workbench_campaign.png")
    viewer.close()


if __name__ == "__main__":
    import sys

    if "--views" in sys.argv:
        views = argparse.ArgumentParser(description=views_main.__doc__.splitlines()[0])
        views.add_argument("--views", action="store_true")
        views.add_argument("--out", type=Path, default=OUT)
        views_main(views.parse_args().out)
    else:
        main()

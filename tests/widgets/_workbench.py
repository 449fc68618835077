"""Helpers of the workbench GUI tests (the fixture is in ``conftest.py``)."""

from __future__ import annotations

#: ms: the first run on a fresh machine generates the sample scene.
LOAD_S = 90_000


def idle(wb, qtbot, timeout: int = 30_000) -> None:
    """Wait until the workbench runs no job."""
    qtbot.waitUntil(lambda: not wb.controller.busy, timeout=timeout)


def wait_saved(wb, qtbot, timeout: int = 60_000) -> None:
    """Wait until the workbench's *Save workspace as…* (written in a worker) is over."""
    qtbot.waitUntil(lambda: not wb.controller.saving, timeout=timeout)


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
    wait_saved(wb, qtbot)
    idle(wb, qtbot)
    ctrl.workspace.detach()
    ctrl.open_workspace(saved)
    qtbot.waitUntil(lambda: ctrl.workspace_folder is not None and ctrl.current is not None,
                    timeout=LOAD_S)
    idle(wb, qtbot)
    return ctrl.workspace


def registered_on_truth(ps, pose=None):
    """A registration of a sample photo that found its true pose (or ``pose``),
    without running the pipeline (a verified, excellent trial and a 1.2 px
    estimate)."""
    from napari_imgreg.registration.params import RegistrationParams
    from napari_imgreg.registration.pipeline import Registration, Trial
    from napari_imgreg.registration.uncertainty import Uncertainty
    from napari_imgreg.sample import load_truth

    if pose is None:
        pose = load_truth(ps.photo.path).pose
    trial = Trial(index=0, params=RegistrationParams(), metrics={"inliers_3d": 200}, q=1.4,
                  grade="excellent", hints=[], pose=pose, start_pose=ps.pose, rounds=1,
                  converged=True, verified=True, residual_flow_px=0.4)
    return Registration(status="registered", photo=ps.name, intrinsics=ps.intrinsics,
                        pose=pose, prior=ps.prior, metrics=trial.metrics, q=1.4,
                        grade="excellent", hints=[], trials=[trial], timings_s={"total": 1.0},
                        best_trial=0, uncertainty=Uncertainty(1.2, 0.12, 0.06, 4))


def reference_and_truth_pairs(wb, qtbot, photo_row: int = 1):
    """The sample's photo ``photo_row`` chosen (the sample opened first), a
    reference render made from its pose on the Manual tab, and where its check
    points lie in the photo and in the reference: (controller, photo state,
    photo pixels (8, 2), reference pixels (8, 2))."""
    from napari_imgreg.sample import load_truth, truth_pairs

    ctrl = load_sample(wb, qtbot)
    wb.scene_panel.photo_list.setCurrentRow(photo_row)
    idle(wb, qtbot)
    wb.show_tab("Manual")
    with qtbot.waitSignal(ctrl.reference_ready, timeout=20_000):
        wb.manual_panel.ref_pose_button.click()
    idle(wb, qtbot)
    ps = ctrl.current
    photo_px, ref_px, _ = truth_pairs(load_truth(ps.photo.path), ps.reference, ps.size)
    return ctrl, ps, photo_px, ref_px

"""The gradient-magnitude filter and the registration presets for lidar scans (issue 16)."""

from __future__ import annotations

import numpy as np
import pytest

from napari_imgreg.registration.filters import FilterParams, apply_filters, gradient_magnitude
from napari_imgreg.registration.params import RegistrationParams


def test_gradient_magnitude_of_a_ramp_and_a_step():
    """A linear ramp has a constant gradient (its grey levels per pixel); a step
    has its peak on the step and nothing away from it."""
    x = np.arange(64, dtype=np.float32)
    ramp = np.tile(2.0 * x, (48, 1)).astype(np.uint8)  # 2 grey levels per pixel
    g = gradient_magnitude(ramp, sigma_px=0.0)
    inner = g[4:-4, 4:-4]
    assert np.ptp(inner) == 0 and inner[0, 0] == 255  # uniform: its own 99th percentile
    step = np.zeros((48, 64), np.uint8)
    step[:, 32:] = 200
    g = gradient_magnitude(step, sigma_px=1.0)
    assert set(np.argmax(g, axis=1)) <= {31, 32}
    assert g[:, :24].max() == 0 and g[:, 40:].max() == 0
    # Gain and offset of the image do not change it (scaled by its percentile).
    np.testing.assert_array_equal(gradient_magnitude((step // 2 + 20).astype(np.uint8), 1.0), g)


def test_gradient_magnitude_inside_a_mask_ignores_what_is_outside():
    img = np.full((60, 60), 90, np.uint8)
    img[:, 45:] = 250  # outside the mask: must not show
    img[20:40, 15:35] = 150  # a square inside: its outline is the only edge
    mask = np.zeros((60, 60), bool)
    mask[:, :45] = True
    g = gradient_magnitude(img, 1.0, mask)
    assert g[~mask].max() == 0
    assert g[30, 5] == 0 and g[30, 25] == 0  # flat outside the square and inside it
    assert g[30, 13:17].max() > 100 and g[18:22, 25].max() > 100  # its left and top edges
    # The mask's own border (x = 44) shows the step from the surface to nothing
    # (a skyline); the bright outside does not add to it.
    assert g[30, 42:45].max() > 100
    img2 = img.copy()
    img2[:, 45:] = 0
    np.testing.assert_array_equal(gradient_magnitude(img2, 1.0, mask), g)


def test_gradient_filter_runs_first_and_counts_as_a_filter():
    p = FilterParams(gradient=True)
    assert not p.is_identity and FilterParams().is_identity
    rgb = np.zeros((32, 32, 3), np.uint8)
    rgb[:, 16:] = 180
    out = apply_filters(rgb, p)
    np.testing.assert_array_equal(out, gradient_magnitude(rgb[..., 0], 1.0))
    with pytest.raises(ValueError, match="gradient_sigma_px"):
        FilterParams(gradient_sigma_px=20.0)
    assert FilterParams.from_dict(p.to_dict()) == p


def test_cloud_presets():
    base, cloud = RegistrationParams.baseline_cloud(), RegistrationParams.for_cloud()
    plain = RegistrationParams.baseline()
    assert base.photo_filters.gradient and base.render_filters.gradient
    # Otherwise the plain baseline: one round of SIFT + EPnP, nothing verified.
    assert (base.max_iterations, base.max_trials, base.verify, base.features) == (
        plain.max_iterations, plain.max_trials, plain.verify, plain.features)
    assert cloud.photo_filters.gradient and cloud.render_filters.gradient
    assert not cloud.features.invariant_channel
    # The presets survive a --params round trip.
    assert RegistrationParams.from_dict(cloud.to_dict()) == cloud


def _plane_cloud():
    from napari_imgreg.cloud import CloudScene

    rng = np.random.default_rng(3)
    xy = rng.uniform(-5.0, 5.0, (4000, 2))
    return CloudScene(np.c_[xy, np.zeros(len(xy))], intensity=np.full(len(xy), 0.5),
                      viewpoints=np.array([[0.0, 0.0, 10.0]]))


def test_a_point_cloud_gets_the_cloud_preset_by_default(tmp_path):
    """The command line, batches and workspaces register a point cloud with
    for_cloud() (what the cloud benchmark measures), a mesh with the defaults;
    a --params file's fields go over the scene's defaults."""
    from napari_imgreg.cli._common import read_params

    cloud = _plane_cloud()
    assert RegistrationParams.for_scene(cloud) == RegistrationParams.for_cloud()
    assert RegistrationParams.for_scene(None) == RegistrationParams()
    assert RegistrationParams.for_cloud().area.width == 1632
    assert RegistrationParams().area.width == 1024
    assert read_params(None, cloud) == RegistrationParams.for_cloud()
    f = tmp_path / "p.json"
    f.write_text('{"area": {"template_px": 41}, "max_iterations": 6}')
    on_cloud, on_mesh = read_params(f, cloud), read_params(f)
    assert (on_cloud.area.template_px, on_cloud.area.width, on_cloud.max_iterations) == (41, 1632, 6)
    assert on_cloud.photo_filters.gradient and on_cloud.max_trials == 1
    assert (on_mesh.area.template_px, on_mesh.area.width, on_mesh.max_trials) == (41, 1024, 4)
    assert not on_mesh.photo_filters.gradient
    # The base is not shared with the result.
    base = RegistrationParams.for_cloud()
    got = RegistrationParams.from_dict({"seed": 3}, base=base)
    assert got.area is not base.area and got.area == base.area and got.seed == 3


def test_workspace_defaults_follow_the_scene_custom_settings_stay():
    from dataclasses import replace

    from napari_imgreg.workspace import Workspace

    cloud = _plane_cloud()
    cloud.build_engine()
    ws = Workspace()
    seen = []
    ws.params_changed.connect(lambda *a: seen.append(1))
    ws.load_scene(cloud)
    assert ws.params == RegistrationParams.for_cloud() and seen == [1]
    ws.load_scene(cloud)  # already its defaults: no signal
    assert seen == [1] and ws.params.is_scene_default()
    custom = replace(RegistrationParams(), max_iterations=7)
    ws.set_params(custom)
    assert not custom.is_scene_default()
    ws.load_scene(cloud)
    assert ws.params == custom  # a user's settings are never replaced

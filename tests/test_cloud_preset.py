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

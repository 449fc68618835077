"""Known answers for :mod:`napari_imgreg.registration.stages.pyramid`, what the edge
and MI stages share: bilinear sampling, pyramid levels, the render callback."""

from __future__ import annotations

import functools
import warnings
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import pytest

from napari_imgreg.camera import Intrinsics
from napari_imgreg.registration.stages.pyramid import (
    PyramidLevel,
    as_render_fn,
    bilinear_taps,
    check_ranges,
    level_widths,
    sample_bilinear,
    with_keywords,
)
from napari_imgreg.render import render


def _ramp(h: int, w: int, a: float, b: float, c: float) -> np.ndarray:
    """``a + b x + c y`` at the pixel centres (x, y integers), float64 (H, W)."""
    y, x = np.mgrid[0:h, 0:w]
    return a + b * x + c * y


def test_bilinear_sampling_of_a_linear_ramp_is_exact():
    rng = np.random.default_rng(0)
    h, w = 31, 47
    stack = np.stack([_ramp(h, w, 1.0, 0.5, -2.0), _ramp(h, w, -3.0, 0.25, 4.0)])
    n = 5000
    x, y = rng.uniform(0, w - 1, n), rng.uniform(0, h - 1, n)
    x[:3], y[:3] = [0.0, w - 1.0, w - 1.0], [0.0, h - 1.0, 0.0]  # the outermost centres
    layer = rng.integers(0, 2, n)
    expected = np.where(layer == 0, 1.0 + 0.5 * x - 2.0 * y, -3.0 + 0.25 * x + 4.0 * y)
    got = sample_bilinear(stack, x, y, layer=layer)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12)
    # One image, no layers; integer positions give the pixel values themselves.
    img = stack[0]
    np.testing.assert_array_equal(sample_bilinear(img, np.array([3.0]), np.array([5.0])),
                                  img[5, 3])


def test_bilinear_sampling_beyond_the_outermost_centres_is_outside():
    img = _ramp(10, 20, 0.0, 1.0, 1.0)
    x = np.array([-0.01, 19.01, 5.0, 5.0, np.nan, np.inf, 5.0])
    y = np.array([4.0, 4.0, -0.5, 9.5, 4.0, 4.0, 4.0])
    got = sample_bilinear(img, x, y, outside=-7.0)
    np.testing.assert_array_equal(got, [-7.0] * 6 + [9.0])


def test_bilinear_taps_share_one_set_of_weights_over_planes():
    h, w = 8, 9
    planes = [_ramp(h, w, 0.0, 1.0, 0.0).ravel().astype(np.float32),
              _ramp(h, w, 0.0, 0.0, 1.0).ravel().astype(np.float32)]
    x, y = np.array([0.25, 7.5, 8.0]), np.array([0.5, 6.75, 7.0])
    taps = bilinear_taps(x, y, (h, w), dtype=np.float32)
    assert taps.fx.dtype == np.float32
    gx, gy = (taps.sample(p) for p in planes)
    assert gx.dtype == np.float32
    np.testing.assert_allclose(gx, x, atol=1e-6)
    np.testing.assert_allclose(gy, y, atol=1e-6)


def test_level_widths_are_distinct_coarse_to_fine_and_capped():
    assert level_widths((768, 320, 320), 1632) == [320, 768]
    assert level_widths((128, 256, 512, 1024), 600) == [128, 256, 512, 600]
    assert level_widths((2000,), 800) == [800]


def test_a_pyramid_level_scales_the_camera_and_resizes_the_photo():
    intr = Intrinsics.from_fov(800, 600, 60.0)
    photo = np.zeros((600, 800, 3), np.uint8)
    half = PyramidLevel(intr, 0.5)
    assert (half.width, half.height) == (400, 300) and half.intr == intr.scaled(0.5)
    assert half.resize(photo).shape == (300, 400, 3)
    assert half.scaled(intr) == half.intr
    full = PyramidLevel(intr, 1.0)
    assert full.intr is intr and full.resize(photo) is photo  # nothing to do at full size


def test_render_callbacks_of_version_0_1_are_adapted_with_a_warning():
    calls = []

    def new(intrinsics, pose, scale):
        calls.append(("new", intrinsics, pose, scale))

    def old_dense(pose, scale):
        calls.append(("dense", pose, scale))

    def old_edges(scene, intrinsics, pose, scale):
        calls.append(("edges", scene, intrinsics, pose, scale))

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert as_render_fn(new, "scene", "f") is new
        # A partial of render (scale and more with defaults) is of the new form.
        partial = functools.partial(render, "scene")
        assert as_render_fn(partial, "scene", "f") is partial
    with pytest.warns(DeprecationWarning, match=r"f: a render_fn\(pose, scale\)"):
        as_render_fn(old_dense, "scene", "f")("intr", "pose", 0.5)
    with pytest.warns(DeprecationWarning, match=r"render_fn\(scene, intrinsics, pose, scale\)"):
        as_render_fn(old_edges, "scene", "f")("intr", "pose", 0.5)
    assert calls == [("dense", "pose", 0.5), ("edges", "scene", "intr", "pose", 0.5)]


@dataclass
class _Settings:
    width: int = 100
    sizes: tuple[int, ...] = (1, 2)
    name: str = "x"
    RANGES: ClassVar[dict] = {"width": (10, 1000), "sizes": (1, 5)}


def test_check_ranges_and_deprecated_keywords():
    check_ranges(_Settings())
    for bad in (_Settings(width=5), _Settings(width=True), _Settings(sizes=(1, 9)),
                _Settings(width="100")):
        with pytest.raises(ValueError, match="must be within"):
            check_ranges(bad)
    s = _Settings()
    assert with_keywords(s, {}, "f") is s
    with pytest.warns(DeprecationWarning, match=r"f\(\.\.\., width=\.\.\.\).*_Settings"):
        assert with_keywords(s, {"width": 20}, "f") == _Settings(width=20)
    with pytest.raises(TypeError, match="wdth"):
        with_keywords(s, {"wdth": 20}, "f")


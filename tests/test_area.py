"""Area-based matching (blocks found by correlation) against known shifts."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from napari_imgreg.registration.stages.area import (
    AreaParams,
    band_pass,
    match_blocks,
    prepare_photo,
    prepare_render,
    search_schedule,
)


def _rock(shape=(240, 320), seed=0) -> np.ndarray:
    """Smooth random relief-like texture, 8-bit grey levels."""
    rng = np.random.default_rng(seed)
    img = np.zeros(shape, np.float32)
    for sigma, amp in ((1.5, 0.5), (4.0, 1.0), (10.0, 1.0)):
        layer = cv2.GaussianBlur(rng.standard_normal(shape).astype(np.float32), (0, 0), sigma)
        img += amp * layer / layer.std()
    return np.clip(128 + 30 * img, 0, 255).astype(np.uint8)


def _shifted(img: np.ndarray, dx: float, dy: float) -> np.ndarray:
    m = np.float32([[1, 0, dx], [0, 1, dy]])
    return cv2.warpAffine(img, m, (img.shape[1], img.shape[0]), flags=cv2.INTER_CUBIC,
                          borderMode=cv2.BORDER_REFLECT)


def test_band_pass_removes_constant_and_slow_variation():
    ramp = np.tile(np.linspace(0, 200, 200, dtype=np.float32), (100, 1))
    out = band_pass(ramp, 6.0)
    assert out.dtype == np.float32
    # A linear ramp is unchanged by a symmetric blur away from the borders.
    assert np.abs(out[20:-20, 20:-20]).max() < 1e-2
    assert np.abs(band_pass(np.full((50, 50), 77.0), 6.0)).max() < 1e-3


@pytest.mark.parametrize("dx, dy", [(3.3, -2.6), (-7.8, 5.1), (0.0, 0.0)])
def test_match_blocks_recovers_a_known_subpixel_shift(dx, dy):
    render = _rock()
    photo = _shifted(render, dx, dy)
    mask = np.ones(render.shape, bool)
    m = match_blocks(prepare_photo(photo, 6.0), prepare_render(render, mask, 6.0), mask,
                     template_px=33, search_px=12, stride_px=24)
    assert m.n_blocks > 40
    assert m.accepted.mean() > 0.9
    err = m.shift[m.accepted] - np.array([dx, dy])
    assert np.median(np.linalg.norm(err, axis=1)) < 0.1


def test_correlation_ignores_gain_offset_and_slow_shading():
    render = _rock(seed=1)
    photo = _shifted(render, 2.4, 1.7).astype(np.float32)
    yy, xx = np.mgrid[0:photo.shape[0], 0:photo.shape[1]]
    photo = 0.5 * photo + 40 + 0.2 * xx  # darker, lower contrast, a shading ramp
    photo = np.clip(photo, 0, 255).astype(np.uint8)
    mask = np.ones(render.shape, bool)
    m = match_blocks(prepare_photo(photo, 6.0), prepare_render(render, mask, 6.0), mask)
    err = m.shift[m.accepted] - np.array([2.4, 1.7])
    assert m.accepted.mean() > 0.9
    assert np.median(np.linalg.norm(err, axis=1)) < 0.15


def test_repeated_pattern_is_ambiguous_not_matched():
    # Vertical stripes every 9 px: a block fits at every period along x.
    xx = np.arange(320)
    stripes = np.tile(128 + 60 * np.sin(2 * np.pi * xx / 9.0), (240, 1)).astype(np.uint8)
    mask = np.ones(stripes.shape, bool)
    m = match_blocks(prepare_photo(stripes, 6.0), prepare_render(stripes, mask, 6.0), mask,
                     search_px=12)
    assert m.n_blocks > 0
    assert not m.accepted.any()


def test_blocks_are_searched_only_where_the_model_is():
    render = _rock(seed=2)
    mask = np.zeros(render.shape, bool)
    mask[:, :160] = True  # the right half is sky
    m = match_blocks(prepare_photo(render, 6.0), prepare_render(render, mask, 6.0), mask,
                     min_coverage=0.6)
    assert m.n_blocks > 0
    assert (m.render_points[:, 0] < 160 + 33 * 0.4).all()
    assert np.all(mask[m.render_points[:, 1].astype(int), m.render_points[:, 0].astype(int)])


def test_render_background_is_filled_brighter_than_the_model():
    rgb = np.full((60, 80, 3), 90, np.uint8)
    rgb[:, :40] = 120
    mask = np.ones((60, 80), bool)
    mask[:20] = False  # sky at the top
    rgb[~mask] = 0  # what a render leaves there
    bp = prepare_render(rgb, mask, 6.0)
    # Across the skyline the band-passed level rises toward the sky, as in a photo.
    assert bp[18, 60] > 0 > bp[22, 60]


def test_match_blocks_checks_sizes():
    a = np.zeros((50, 60), np.float32)
    with pytest.raises(ValueError, match="same size"):
        match_blocks(a, np.zeros((50, 61), np.float32), np.ones((50, 61), bool))


def test_search_schedule_narrows_as_the_pose_converges():
    p = AreaParams()
    assert search_schedule(p, True, True, math.inf, 1632) == (256, 40)
    assert search_schedule(p, True, False, math.inf, 1632) == (512, 24)
    # Still many pixels off: stay at half width with the wide radius.
    assert search_schedule(p, False, True, 120.0, 1632) == (512, 24)
    width, radius = search_schedule(p, False, True, 6.0, 1632)
    assert width == 1024 and 6 <= radius <= 16
    assert search_schedule(p, False, True, 0.3, 1632) == (1024, 6)
    # A photo narrower than the matching width is matched at its own.
    assert search_schedule(p, False, True, 0.3, 800)[0] == 800


def test_area_params_round_trip_and_validation():
    p = AreaParams(template_px=41, stride_px=20)
    assert AreaParams.from_dict(p.to_dict()) == p
    with pytest.raises(ValueError, match="odd"):
        AreaParams(template_px=32)
    with pytest.raises(KeyError, match="unknown area parameter"):
        AreaParams.from_dict({"templat_px": 33})

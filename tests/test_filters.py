"""Radiometric filters (filters.py): known answers for each filter and their order."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from napari_imgreg.registration.filters import (
    FilterParams,
    apply_filters,
    brightness_contrast,
    clahe,
    filtered_for_matching,
    gamma_correct,
    reduce_for_matching,
    to_gray,
    wallis,
)

RAMP = np.arange(256, dtype=np.uint8).reshape(16, 16)  # every grey level once


def _rgb(seed: int = 0, shape=(60, 80)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.integers(0, 256, (*shape, 3), dtype=np.uint8)


def _textured(h: int, w: int, offset, amp) -> np.ndarray:
    """Smooth-statistics test image: a fine sine texture (std 1 per window)
    scaled by a slowly varying amplitude and shifted by a slowly varying
    offset, so each window's mean ≈ offset and std ≈ amp."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    pattern = 2.0 * np.sin(2 * np.pi * xx / 7.3) * np.sin(2 * np.pi * yy / 6.1)  # std 1
    return np.clip(offset(xx, yy) + amp(xx, yy) * pattern, 0, 255).astype(np.uint8)


def _window_stats(img: np.ndarray, win: int, weight: np.ndarray | None = None):
    """Box-window mean and std of ``img`` (optionally weighted), float64."""
    x = img.astype(np.float64)
    w = np.ones_like(x) if weight is None else weight.astype(np.float64)
    norm = np.maximum(cv2.blur(w, (win, win)), 1e-12)
    m = cv2.blur(x * w, (win, win)) / norm
    s = np.sqrt(np.maximum(cv2.blur(x * x * w, (win, win)) / norm - m * m, 0.0))
    return m, s


# ------------------------------------------------------------------- gamma
@pytest.mark.parametrize("gamma", [0.25, 0.5, 1.0, 1.8, 2.2, 4.0])
def test_gamma_lut_equals_the_formula(gamma):
    # out = round(255 * (in / 255) ** (1 / gamma)), half up, for every grey level.
    expected = np.floor(255.0 * (RAMP / 255.0) ** (1.0 / gamma) + 0.5).astype(np.uint8)
    out = gamma_correct(RAMP, gamma)
    assert out.dtype == np.uint8 and out.shape == RAMP.shape
    np.testing.assert_array_equal(out, expected)


def test_gamma_above_one_brightens_and_keeps_the_ends():
    out = gamma_correct(RAMP, 2.2)
    assert out.flat[0] == 0 and out.flat[255] == 255
    assert np.all(out.astype(int) >= RAMP.astype(int))
    assert np.all(np.diff(out.ravel().astype(int)) >= 0)  # monotone


@pytest.mark.parametrize("gamma", [0.0, -1.0])
def test_gamma_must_be_positive(gamma):
    with pytest.raises(ValueError):
        gamma_correct(RAMP, gamma)


# ------------------------------------------------------------ identity
def test_neutral_settings_are_the_identity():
    img = _rgb(1)
    gray = to_gray(img)
    np.testing.assert_array_equal(gamma_correct(gray, 1.0), gray)
    np.testing.assert_array_equal(brightness_contrast(gray, 0.0, 1.0), gray)
    params = FilterParams(gamma=1.0, contrast=1.0, brightness=0.0, wallis=False, clahe=False)
    assert params.is_identity
    np.testing.assert_array_equal(apply_filters(img, params), gray)
    np.testing.assert_array_equal(apply_filters(gray, params), gray)


def test_is_identity_notices_every_filter():
    for change in ({"gamma": 1.5}, {"wallis": True}, {"brightness": 5.0},
                   {"contrast": 1.2}, {"clahe": True}):
        assert not FilterParams(**change).is_identity, change


def test_to_gray_is_bt601_luma():
    img = _rgb(2)
    expected = 0.299 * img[..., 0] + 0.587 * img[..., 1] + 0.114 * img[..., 2]
    assert np.abs(to_gray(img).astype(float) - expected).max() <= 1.0
    # a grey image passes through
    g = img[..., 0]
    assert to_gray(g) is g


# ------------------------------------------------------ brightness/contrast
@pytest.mark.parametrize("brightness, contrast", [(20.0, 1.0), (-35.0, 1.0), (0.0, 1.7),
                                                  (0.0, 0.4), (12.5, 2.3), (-80.0, 0.5)])
def test_brightness_contrast_formula(brightness, contrast):
    # out = clip(round((in - 127.5) * contrast + 127.5 + brightness)), gain about mid-grey.
    v = RAMP.astype(np.float64)
    expected = np.clip(np.floor((v - 127.5) * contrast + 127.5 + brightness + 0.5), 0, 255)
    np.testing.assert_array_equal(brightness_contrast(RAMP, brightness, contrast), expected)


# ----------------------------------------------------------------- Wallis
def test_wallis_full_forcing_gives_every_window_the_targets():
    h, w, win = 300, 400, 41
    g = _textured(h, w, offset=lambda x, y: 70 + 100 * x / w, amp=lambda x, y: 15 + 25 * y / h)
    # Sanity: the input's local statistics really vary across the image.
    m_in, s_in = _window_stats(g, win)
    inner = (slice(win, h - win), slice(win, w - win))
    assert np.ptp(m_in[inner]) > 60 and np.ptp(s_in[inner]) > 15

    out = wallis(g, win, target_mean=127.0, target_std=50.0, brightness=1.0, contrast=1.0)
    m, s = _window_stats(out, win)
    assert np.abs(m[inner] - 127.0).max() < 1.0
    assert np.abs(s[inner] - 50.0).max() < 3.0


@pytest.mark.parametrize("b, c", [(0.6, 0.9), (0.0, 0.0), (1.0, 0.5), (0.3, 1.0)])
def test_wallis_pixelwise_formula(b, c):
    # out = (g - m) * c*s_t / (c*s + (1-c)*s_t) + b*m_t + (1-b)*m   (docstring)
    g = _rgb(3, (50, 70))[..., 1]
    win, mt, st = 15, 120.0, 45.0
    m, s = _window_stats(g, win)  # same box window and reflected border as cv2.blur
    gf = g.astype(np.float64)
    ref = (gf - m) * c * st / (c * s + (1 - c) * st) + b * mt + (1 - b) * m
    ref = np.clip(np.floor(ref + 0.5), 0, 255)
    out = wallis(g, win, mt, st, b, c).astype(np.float64)
    assert np.abs(out - ref).max() <= 1.0  # float32 arithmetic in the filter


def test_wallis_contrast_zero_flattens_to_the_local_mean():
    # The standard Wallis gain c·s_t / (c·s + (1 − c)·s_t) is 0 at c = 0: with
    # b = 0 the output is the local mean (why the docs ask for c well above 0).
    import cv2

    g = _rgb(4)[..., 2]
    out = wallis(g, 21, 127.0, 50.0, brightness=0.0, contrast=0.0)
    local_mean = cv2.blur(g.astype(np.float32), (21, 21))
    assert np.abs(out.astype(float) - local_mean).max() <= 1.0


def _sky_over_rock(sky_value: int):
    h, w = 240, 320
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    rock = np.clip(90 + 60 * np.sin(2 * np.pi * xx / 7.3) * np.sin(2 * np.pi * yy / 6.1), 0, 255)
    mask = yy >= 80  # rock below the horizon at row 80, sky above
    return np.where(mask, rock, sky_value).astype(np.uint8), mask


def test_wallis_mask_leaves_sky_unchanged_and_out_of_the_statistics():
    win = 31
    black, mask = _sky_over_rock(0)
    white, _ = _sky_over_rock(255)
    out_black = wallis(black, win, 127.0, 50.0, 1.0, 1.0, mask=mask)
    out_white = wallis(white, win, 127.0, 50.0, 1.0, 1.0, mask=mask)
    # Masked-out pixels come back unchanged.
    np.testing.assert_array_equal(out_black[~mask], black[~mask])
    np.testing.assert_array_equal(out_white[~mask], white[~mask])
    # The sky does not pull the statistics: the rock is filtered identically
    # whatever the sky holds ...
    np.testing.assert_array_equal(out_black[mask], out_white[mask])
    # ... and right under the horizon (windows half in the sky) the rock still
    # gets the target mean and deviation.
    m, s = _window_stats(out_black, win, weight=mask)
    band = (slice(80, 80 + win // 2), slice(win, 320 - win))
    assert np.abs(m[band] - 127.0).max() < 2.0
    assert np.abs(s[band] - 50.0).max() < 4.0


def test_without_mask_a_black_sky_does_pull_the_rock():
    # The control for the test above: unmasked, the horizon band is biased.
    win = 31
    black, mask = _sky_over_rock(0)
    white, _ = _sky_over_rock(255)
    a = wallis(black, win, 127.0, 50.0, 1.0, 1.0)
    b = wallis(white, win, 127.0, 50.0, 1.0, 1.0)
    assert not np.array_equal(a[mask], b[mask])
    m, _ = _window_stats(a, win, weight=mask)
    band = (slice(80, 80 + win // 2), slice(win, 320 - win))
    assert np.abs(m[band] - 127.0).max() > 5.0


def test_apply_filters_passes_the_mask_to_wallis():
    black, mask = _sky_over_rock(0)
    params = FilterParams(wallis=True, wallis_window=31, wallis_brightness=1.0, wallis_contrast=1.0)
    out = apply_filters(black, params, mask=mask)
    np.testing.assert_array_equal(out, wallis(black, 31, 127.0, 50.0, 1.0, 1.0, mask=mask))
    np.testing.assert_array_equal(out[~mask], black[~mask])


# ------------------------------------------------------------------ CLAHE
@pytest.mark.parametrize("clip, tiles", [(2.0, 8), (4.0, 4), (1.0, 16)])
def test_clahe_equals_opencv(clip, tiles):
    g = to_gray(_rgb(5, (120, 160)))
    expected = cv2.createCLAHE(clipLimit=clip, tileGridSize=(tiles, tiles)).apply(g)
    np.testing.assert_array_equal(clahe(g, clip, tiles), expected)


# ----------------------------------------------------------- apply_filters
def test_apply_filters_order_is_gamma_wallis_brightness_contrast_clahe():
    img = _rgb(6, (96, 128))
    p = FilterParams(gamma=1.7, wallis=True, wallis_window=15, wallis_target_mean=110.0,
                     wallis_target_std=40.0, wallis_brightness=0.7, wallis_contrast=0.8,
                     brightness=-12.0, contrast=1.3, clahe=True, clahe_clip=3.0, clahe_tiles=4)
    g = to_gray(img)
    expected = clahe(
        brightness_contrast(wallis(gamma_correct(g, 1.7), 15, 110.0, 40.0, 0.7, 0.8), -12.0, 1.3),
        3.0, 4,
    )
    out = apply_filters(img, p)
    np.testing.assert_array_equal(out, expected)
    # The order matters (so the test above can tell orders apart).
    other = gamma_correct(brightness_contrast(wallis(g, 15, 110.0, 40.0, 0.7, 0.8), -12.0, 1.3), 1.7)
    assert not np.array_equal(clahe(other, 3.0, 4), out)


def test_apply_filters_single_steps():
    img = _rgb(7)
    g = to_gray(img)
    np.testing.assert_array_equal(apply_filters(img, FilterParams(gamma=0.5)), gamma_correct(g, 0.5))
    np.testing.assert_array_equal(apply_filters(img, FilterParams(brightness=10.0)),
                                  brightness_contrast(g, 10.0, 1.0))
    np.testing.assert_array_equal(apply_filters(img, FilterParams(clahe=True)), clahe(g, 2.0, 8))
    out = apply_filters(img, FilterParams(contrast=2.0))
    assert out.dtype == np.uint8 and out.shape == g.shape


# ----------------------------------------------------------- FilterParams
def test_filter_params_dict_round_trip():
    p = FilterParams(gamma=2.0, wallis=True, wallis_window=51, clahe=True, clahe_tiles=6)
    assert FilterParams.from_dict(p.to_dict()) == p
    assert FilterParams.from_dict({}) == FilterParams()


def test_filter_params_from_dict_rejects_unknown_keys():
    with pytest.raises(KeyError, match="gama"):
        FilterParams.from_dict({"gama": 2.0})


def test_illumination_invariant_cancels_shading_and_gamma_free_exposure():
    from napari_imgreg.registration.filters import illumination_invariant

    rng = np.random.default_rng(0)
    # Surface colours (chromaticity) and a shading field common to all channels.
    albedo = rng.uniform(60, 200, (64, 64, 3)).astype(np.float32)
    shading = np.linspace(0.3, 1.0, 64, dtype=np.float32)[None, :, None]
    lit = np.clip(albedo * shading, 0, 255).astype(np.uint8)
    flat = np.clip(albedo * 0.8, 0, 255).astype(np.uint8)
    a, b = illumination_invariant(lit), illumination_invariant(flat)
    # log G − α log B − (1−α) log R: a common factor cancels (up to the +1
    # guard against log 0 and 8-bit rounding) and the result is standardised.
    assert np.corrcoef(a.ravel().astype(float), b.ravel().astype(float))[0, 1] > 0.97
    assert abs(float(a.mean()) - 127) < 3 and abs(float(b.mean()) - 127) < 3


def test_illumination_invariant_statistics_come_from_the_mask_only():
    from napari_imgreg.registration.filters import illumination_invariant

    img = np.zeros((20, 20, 3), np.uint8)
    img[:, :10] = (90, 140, 60)
    img[:, 10:] = (60, 140, 90)
    mask = np.zeros((20, 20), bool)
    mask[:, :15] = True
    with_mask = illumination_invariant(img, mask)
    black_sky = img.copy()
    black_sky[:, 15:] = 0
    # Changing what lies outside the mask does not change the rock's grey values.
    np.testing.assert_array_equal(illumination_invariant(black_sky, mask)[:, :15], with_mask[:, :15])
    with pytest.raises(ValueError):
        illumination_invariant(img[..., 0])


@pytest.mark.parametrize("reduce_wide", [False, True])
def test_masked_gaussian_ignores_what_lies_outside_the_mask(reduce_wide):
    from napari_imgreg.registration.filters import masked_gaussian

    mask = np.zeros((120, 160), bool)
    mask[:, :100] = True
    values = np.where(mask, 50.0, 1000.0).astype(np.float32)  # huge values outside
    for sigma in (2.0, 12.0):
        out = masked_gaussian(values, mask, sigma, reduce_wide=reduce_wide)
        # A constant inside the mask stays that constant, right up to the mask's edge.
        np.testing.assert_allclose(out[mask], 50.0, rtol=1e-4)
    rgb = np.dstack([values, 2 * values, 3 * values])
    out = masked_gaussian(rgb, mask, 3.0)
    np.testing.assert_allclose(out[mask], np.broadcast_to([50.0, 100.0, 150.0], (mask.sum(), 3)),
                               rtol=1e-4)
    assert masked_gaussian(values, mask, 0.0) is values


# ----------------------------------------------------------- filter preview
def test_filter_preview_is_what_the_detector_reads():
    rng = np.random.default_rng(2)
    big = (rng.random((1224, 1632, 3)) * 255).astype(np.uint8)
    params = FilterParams(gamma=1.4, wallis=True)
    out = filtered_for_matching(big, params, 1024)
    assert out.shape == (768, 1024) and out.dtype == np.uint8
    small = cv2.resize(big, (1024, 768), interpolation=cv2.INTER_AREA)
    np.testing.assert_array_equal(out, apply_filters(small, params))
    # A photo narrower than the match width is filtered as it is.
    np.testing.assert_array_equal(filtered_for_matching(small, params, 2048),
                                  apply_filters(small, params))
    mask = np.zeros((1224, 1632), bool)
    mask[:, :800] = True
    masked = filtered_for_matching(big, params, 1024, mask=mask)
    assert masked.shape == (768, 1024)


def test_reduce_for_matching_gives_the_render_size_and_keeps_a_narrow_image():
    from napari_imgreg.camera import Intrinsics

    rng = np.random.default_rng(3)
    photo = rng.integers(0, 256, (1000, 1500, 3), dtype=np.uint8)
    small, mask = reduce_for_matching(photo, 640, np.ones((1000, 1500), bool))
    # The render at the same scale has the same size: pixels coincide.
    scaled = Intrinsics(1500, 1000, 1200.0, 1200.0, 749.5, 499.5).scaled(640 / 1500)
    assert small.shape[:2] == mask.shape == (scaled.height, scaled.width) == (427, 640)
    assert mask.all()
    same, none = reduce_for_matching(photo, 2000)
    assert same is photo and none is None

"""Radiometric filters applied to the photo and the render before matching.

Illumination differences (another sun, wet rock, exposure) mostly change the
luminance channel, which is what keypoint detectors read. Each filter here
pulls both images toward a common radiometry (Kehl et al. 2018, "Image
Processing and Adaptations to Radiometric Influences"): gamma, Wallis,
brightness/contrast and CLAHE. The photo and the render each get their own
:class:`FilterParams`.

For a lidar scan's intensity render, whose grey levels are the rock's
reflectance at the laser's wavelength and not the photo's luminance, the
*gradient magnitude* of both images is what they share (Morago et al., seed
003: the reflectivity view's gradient matched against the photo's):
:func:`gradient_magnitude`, ``FilterParams(gradient=True)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import cv2
import numpy as np

from ..camera import match_scale, scaled_size
from ..validate import StageParams, check_ranges

__all__ = [
    "FilterParams",
    "apply_filters",
    "to_gray",
    "gamma_correct",
    "wallis",
    "brightness_contrast",
    "clahe",
    "reduce_for_matching",
    "filtered_for_matching",
    "illumination_invariant",
    "masked_gaussian",
    "gradient_magnitude",
    "INVARIANT_ALPHA",
]


@dataclass
class FilterParams(StageParams):
    """Filter settings for one image, applied in the order listed.

    Attributes
    ----------
    gamma : float
        Output = input^(1/gamma) on [0, 1]; > 1 brightens shadows. Range 0.2–5;
        1 is off.
    gradient : bool
        Replace the (gamma-corrected) grey image by its gradient magnitude
        (:func:`gradient_magnitude`) before the filters below: what an
        intensity render and a photo have in common. Default False.
    gradient_sigma_px : float
        Gaussian σ of the smoothing before the Sobel derivatives, pixels at
        the matching width (0–10; 0: none). Default 1.
    wallis : bool
        Apply the Wallis filter.
    wallis_window : int
        Side of the square window for the local mean and deviation, pixels
        (odd; 3–501, the GUI offers 15–151).
    wallis_target_mean, wallis_target_std : float
        Grey level (0–255) and deviation (1–255) the filter pulls each window
        toward.
    wallis_brightness : float
        Brightness forcing constant b in [0, 1]: 1 replaces the local mean by
        the target, 0 keeps it.
    wallis_contrast : float
        Contrast forcing constant c in (0, 1]: 1 gives every window the
        target deviation; smaller values mix in the window's own deviation
        (as c → 0 the gain c·s_t / (c·s + (1 − c)·s_t) goes to 0 and the
        image flattens to its local mean, so keep c well above 0).
    brightness : float
        Offset added to grey levels (−100–100); 0 is off.
    contrast : float
        Gain about mid-grey (0.2–3); 1 is off.
    clahe : bool
        Contrast-limited adaptive histogram equalisation.
    clahe_clip : float
        CLAHE clip limit (1–10).
    clahe_tiles : int
        CLAHE tiles per image side (2–32).
    """

    KIND: ClassVar[str] = "filter"

    gamma: float = 1.0
    gradient: bool = False
    gradient_sigma_px: float = 1.0
    wallis: bool = False
    wallis_window: int = 41
    wallis_target_mean: float = 127.0
    wallis_target_std: float = 50.0
    wallis_brightness: float = 0.6
    wallis_contrast: float = 0.9
    brightness: float = 0.0
    contrast: float = 1.0
    clahe: bool = False
    clahe_clip: float = 2.0
    clahe_tiles: int = 8

    #: Inclusive valid range of each numeric field (checked when built, e.g.
    #: from a ``--params`` file; the GUI's sliders stay within it).
    RANGES: ClassVar[dict[str, tuple[float, float]]] = {
        "gamma": (0.2, 5.0),
        "gradient_sigma_px": (0.0, 10.0),
        "wallis_window": (3, 501),
        "wallis_target_mean": (0.0, 255.0),
        "wallis_target_std": (1.0, 255.0),
        "wallis_brightness": (0.0, 1.0),
        "wallis_contrast": (0.0, 1.0),
        "brightness": (-100.0, 100.0),
        "contrast": (0.2, 3.0),
        "clahe_clip": (1.0, 10.0),
        "clahe_tiles": (2, 32),
    }

    def __post_init__(self) -> None:
        check_ranges(self)

    @property
    def is_identity(self) -> bool:
        """True when no filter changes the image."""
        return (
            self.gamma == 1.0
            and not self.gradient
            and not self.wallis
            and self.brightness == 0.0
            and self.contrast == 1.0
            and not self.clahe
        )


def to_gray(image: np.ndarray) -> np.ndarray:
    """RGB (H, W, 3) or grey (H, W) uint8 → grey (H, W) uint8 (BT.601 luma)."""
    if image.ndim == 2:
        return image
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)


def gamma_correct(gray: np.ndarray, gamma: float) -> np.ndarray:
    """Gamma on a uint8 image through a look-up table; ``gamma > 1`` brightens."""
    if gamma <= 0:
        raise ValueError("gamma must be positive")
    lut = np.clip(255.0 * (np.arange(256) / 255.0) ** (1.0 / gamma) + 0.5, 0, 255)
    return cv2.LUT(gray, lut.astype(np.uint8))


def wallis(
    gray: np.ndarray,
    window: int = 41,
    target_mean: float = 127.0,
    target_std: float = 50.0,
    brightness: float = 0.6,
    contrast: float = 0.9,
    mask: np.ndarray | None = None,
) -> np.ndarray:
    """Wallis filter: local mean and deviation pulled toward targets.

    ``out = (g - m) * c s_t / (c s + (1 - c) s_t) + b m_t + (1 - b) m``,
    with ``m``, ``s`` the mean and deviation in a ``window`` × ``window``
    neighbourhood (Wallis 1974, as used for matching by Jazayeri & Fraser 2010).

    Parameters
    ----------
    gray : (H, W) uint8 array
    window : int
        Neighbourhood side in pixels.
    target_mean, target_std : float
        Targets (grey levels).
    brightness, contrast : float
        Forcing constants b in [0, 1] and c in (0, 1].
    mask : (H, W) bool array, optional
        Pixels that count (e.g. the render's surface, not its empty sky); the
        local statistics ignore the rest, which is returned unchanged.

    Returns
    -------
    (H, W) uint8 array
    """
    g = gray.astype(np.float32)
    k = (int(window) | 1, int(window) | 1)
    if mask is None:
        mean = cv2.blur(g, k)
        mean_sq = cv2.blur(g * g, k)
    else:
        w = mask.astype(np.float32)
        norm = np.maximum(cv2.blur(w, k), 1e-6)
        mean = cv2.blur(g * w, k) / norm
        mean_sq = cv2.blur(g * g * w, k) / norm
    std = np.sqrt(np.maximum(mean_sq - mean * mean, 0.0))
    gain = contrast * target_std / (contrast * std + (1.0 - contrast) * target_std + 1e-6)
    out = (g - mean) * gain + brightness * target_mean + (1.0 - brightness) * mean
    out = np.clip(out + 0.5, 0, 255).astype(np.uint8)
    if mask is not None:
        out[~mask] = gray[~mask]
    return out


def gradient_magnitude(gray: np.ndarray, sigma_px: float = 1.0,
                       mask: np.ndarray | None = None) -> np.ndarray:
    """Gradient magnitude of a grey image, scaled to grey levels.

    ``|∇(G_σ * g)|`` by 3 × 3 Sobel derivatives (divided by 8: grey levels per
    pixel), then scaled so that its 99th percentile (over ``mask``) is 255 and
    clipped: edges and texture of any contrast fill the range, whatever the
    image's brightness or gain.

    Parameters
    ----------
    gray : (H, W) uint8 array
    sigma_px : float
        Gaussian σ before differentiating, pixels (≤ 0: none).
    mask : (H, W) bool array, optional
        Valid pixels (a render's surface): the smoothing ignores the rest
        (normalised convolution), which is 0 in the result, and the scaling's
        percentile is theirs. The mask's own border (the skyline, an
        occluding contour) keeps the step it makes, as the photo shows it.

    Returns
    -------
    (H, W) uint8 array
    """
    g = gray.astype(np.float32)
    if sigma_px > 0:
        g = (masked_gaussian(g, mask, sigma_px, reduce_wide=False) if mask is not None
             else cv2.GaussianBlur(g, (0, 0), sigma_px))
    if mask is not None:
        g = np.where(mask, g, 0.0).astype(np.float32)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    mag = np.sqrt(gx * gx + gy * gy)
    sel = mag[mask] if mask is not None else mag
    top = float(np.percentile(sel, 99.0)) if sel.size else 0.0
    out = np.clip(mag * (255.0 / max(top, 1e-6)) + 0.5, 0, 255).astype(np.uint8)
    if mask is not None:
        out[~mask] = 0
    return out


def brightness_contrast(gray: np.ndarray, brightness: float, contrast: float) -> np.ndarray:
    """Linear grey-level change: gain ``contrast`` about mid-grey plus ``brightness``."""
    lut = np.clip((np.arange(256) - 127.5) * contrast + 127.5 + brightness + 0.5, 0, 255)
    return cv2.LUT(gray, lut.astype(np.uint8))


def clahe(gray: np.ndarray, clip: float = 2.0, tiles: int = 8) -> np.ndarray:
    """OpenCV's contrast-limited adaptive histogram equalisation."""
    return cv2.createCLAHE(clipLimit=float(clip), tileGridSize=(int(tiles), int(tiles))).apply(gray)


def apply_filters(
    image: np.ndarray, params: FilterParams, mask: np.ndarray | None = None
) -> np.ndarray:
    """Grey image for feature detection, with ``params`` applied.

    Parameters
    ----------
    image : (H, W, 3) or (H, W) uint8 array
    params : FilterParams
    mask : (H, W) bool array, optional
        Valid pixels (the render's surface); Wallis statistics ignore the rest.

    Returns
    -------
    (H, W) uint8 array
    """
    gray = to_gray(image)
    if params.gamma != 1.0:
        gray = gamma_correct(gray, params.gamma)
    if params.gradient:
        gray = gradient_magnitude(gray, params.gradient_sigma_px, mask)
    if params.wallis:
        gray = wallis(
            gray,
            params.wallis_window,
            params.wallis_target_mean,
            params.wallis_target_std,
            params.wallis_brightness,
            params.wallis_contrast,
            mask,
        )
    if params.brightness != 0.0 or params.contrast != 1.0:
        gray = brightness_contrast(gray, params.brightness, params.contrast)
    if params.clahe:
        gray = clahe(gray, params.clahe_clip, params.clahe_tiles)
    return gray


def reduce_for_matching(
    image: np.ndarray, match_width: int, mask: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray | None]:
    """An image (and its mask) at the registration's matching width.

    A wider image is reduced by area averaging to
    :func:`~napari_imgreg.camera.scaled_size` at
    :func:`~napari_imgreg.camera.match_scale` — the size of the render at that
    scale, so photo and render pixels coincide; a narrower one is returned as
    it is (never enlarged).

    Parameters
    ----------
    image : (H, W, 3) or (H, W) uint8 array
    match_width : int
        ``RegistrationParams.match_width``, pixels.
    mask : (H, W) bool array, optional
        Reduced by nearest neighbour.

    Returns
    -------
    image : (h, w[, 3]) uint8 array
        ``w = min(W, match_width)``.
    mask : (h, w) bool array or None
    """
    h, w = image.shape[:2]
    scale = match_scale(w, match_width)
    if scale < 1.0:
        size = scaled_size(w, h, scale)
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        if mask is not None:
            mask = cv2.resize(mask.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0
    return image, mask


def filtered_for_matching(
    image: np.ndarray, params: FilterParams, match_width: int, mask: np.ndarray | None = None
) -> np.ndarray:
    """The grey image the feature detector reads, for previewing filters.

    The registration matches at ``match_width`` pixels: the image is first
    reduced (:func:`reduce_for_matching`), then filtered — so a Wallis window
    of 41 pixels means 41 pixels at the matching resolution, as in the
    registration.

    Parameters
    ----------
    image : (H, W, 3) or (H, W) uint8 array
        The photo or a render.
    params : FilterParams
    match_width : int
        Matching width, pixels (``RegistrationParams.match_width``).
    mask : (H, W) bool array, optional
        Valid pixels (a render's surface), reduced with the image.

    Returns
    -------
    (h, w) uint8 array
        At ``min(W, match_width)`` pixels wide.
    """
    small, small_mask = reduce_for_matching(image, match_width, mask)
    return apply_filters(small, params, mask=small_mask)


#: Weight of the blue channel in :func:`illumination_invariant`, from a
#: camera's peak spectral sensitivities λ_B < λ_G < λ_R through
#: ``1/λ_G = α/λ_B + (1 − α)/λ_R`` — 0.46 for typical phone sensors
#: (470, 540, 620 nm).
INVARIANT_ALPHA = 0.464


def illumination_invariant(
    image: np.ndarray,
    mask: np.ndarray | None = None,
    alpha: float = INVARIANT_ALPHA,
    spread: float = 40.0,
) -> np.ndarray:
    """The illumination-invariant grey image of a colour image (Maddern et al. 2014).

    ``I = log G − α log B − (1 − α) log R``: the log-responses' weights sum to
    zero, so shading (a common factor of the three channels: relief, cast
    shadow, exposure) cancels, and for a Planckian illuminant (sun, sky) the
    colour temperature cancels too. What is left is the surface's
    chromaticity: bed colours, staining, lichen — the same under any sun.
    The result is standardised (mean 127, ``spread`` grey levels per standard
    deviation, statistics over ``mask``), which also removes the photo's white
    balance and gamma (an offset and a gain of ``I``).

    Parameters
    ----------
    image : (H, W, 3) uint8 array
        RGB.
    mask : (H, W) bool array, optional
        Pixels that count for the statistics (the render's surface); the rest
        is set to mid-grey.
    alpha : float
        Blue weight (:data:`INVARIANT_ALPHA`).
    spread : float
        Grey levels per standard deviation of ``I``.

    Returns
    -------
    (H, W) uint8 array

    References
    ----------
    W. Maddern, A. Stewart, C. McManus, B. Upcroft, W. Churchill, P. Newman,
    "Illumination invariant imaging: applications in robust vision-based
    localisation, mapping and classification for autonomous vehicles", ICRA
    2014 Workshop on Visual Place Recognition in Changing Environments.
    """
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError("illumination_invariant needs an RGB image")
    lut = np.log(np.arange(256, dtype=np.float32) + 1.0)  # +1: no log(0) in black pixels
    r, g, b = (cv2.LUT(image[..., k], lut) for k in range(3))
    inv = g - alpha * b - (1.0 - alpha) * r
    sel = inv[mask] if mask is not None else inv
    if sel.size == 0:
        return np.full(image.shape[:2], 127, np.uint8)
    mu, sd = float(sel.mean()), float(sel.std())
    out = 127.0 + spread * (inv - mu) / max(sd, 1e-6)
    out = np.clip(out + 0.5, 0, 255).astype(np.uint8)
    if mask is not None:
        out[~mask] = 127
    return out


def masked_gaussian(values: np.ndarray, mask: np.ndarray, sigma_px: float,
                    reduce_wide: bool = True) -> np.ndarray:
    """Gaussian blur of ``values`` over ``mask`` only (normalised convolution).

    Pixels outside the mask (sky, no model) neither contribute nor get a
    meaningful value. With ``reduce_wide``, wide blurs (σ ≥ 8 px) run on a
    reduced image — the result is smooth anyway — which keeps a 30 px σ at a
    few milliseconds.

    Parameters
    ----------
    values : (H, W) or (H, W, C) array
    mask : (H, W) bool array
    sigma_px : float
        Gaussian σ, pixels; ≤ 0 returns ``values`` unchanged.
    reduce_wide : bool
        Allow the reduced-image shortcut (off where exact values matter).

    Returns
    -------
    (H, W) or (H, W, C) float32 array
    """
    if sigma_px <= 0:
        return values
    h, w = mask.shape
    channels = values.ndim == 3
    num = np.where(mask[..., None] if channels else mask, values, 0).astype(np.float32)
    den = mask.astype(np.float32)
    factor = int(sigma_px // 4) if (reduce_wide and sigma_px >= 8.0) else 1
    if factor > 1:
        small = (max(1, w // factor), max(1, h // factor))
        num = cv2.resize(num, small, interpolation=cv2.INTER_AREA)
        den = cv2.resize(den, small, interpolation=cv2.INTER_AREA)
        sigma_px = sigma_px * small[0] / w
    num = cv2.GaussianBlur(num, (0, 0), sigma_px)
    den = cv2.GaussianBlur(den, (0, 0), sigma_px)
    if factor > 1:
        num = cv2.resize(num, (w, h), interpolation=cv2.INTER_LINEAR)
        den = cv2.resize(den, (w, h), interpolation=cv2.INTER_LINEAR)
    den = np.maximum(den, 1e-6)
    return num / (den[..., None] if channels else den)

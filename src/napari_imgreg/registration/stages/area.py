"""Area-based matching: blocks of the render found in the photo by correlation.

Keypoint descriptors compare the *pattern* of gradients around a corner; a
photo under another sun, or a bare mesh rendered with shading alone, changes
those patterns until no descriptor matches. What survives is the layout of
light and dark at the scale of the relief — ledges lit on top and shaded
below, gullies, the skyline. Area-based matching (the classic method of
photogrammetric image matching) compares exactly that: the render is cut into
blocks on a grid, each block is searched in the photo near where the current
pose puts it, and the peak of the normalised cross-correlation gives the
photo position of the block's centre, whose 3D point the render knows. The
2D–3D pairs then go to the same RANSAC EPnP, the same seven metrics and the
same verification as keypoint matches.

Both images are band-passed first (a difference of Gaussians), which removes
what differs most between a photo and a render — exposure, haze, the broad
shading of the face and the slow variation of the rock's colour — and keeps
the relief. A block counts as matched only when its correlation peak is high
enough and clearly above the best peak elsewhere in the search window (a
ledge repeats along the face; a repeated peak is ambiguous, not matched).

The search window shrinks as the pose converges: a start several degrees off
is searched at a quarter of the matching width, the following rounds at half
and then full width with a radius that follows the last image shift.

Correlation is OpenCV's ``matchTemplate`` (``TM_CCOEFF_NORMED``), refined to
sub-pixel by a parabola through the peak and its neighbours.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import cv2
import numpy as np

from ...validate import StageParams, check_ranges

__all__ = ["AreaParams", "BlockMatches", "band_pass", "match_blocks", "search_schedule",
           "prepare_render", "prepare_photo"]


@dataclass
class AreaParams(StageParams):
    """Settings of area-based matching (pixels at ``width`` unless said otherwise).

    Each numeric field has its inclusive valid range in :attr:`RANGES`.

    Attributes
    ----------
    width : int
        Matching width of the finest rounds, px (the photo's own when smaller).
    template_px : int
        Side of a render block (odd), px at the round's width.
    stride_px : int
        Grid step between block centres, px at the round's width.
    search_px : int
        Search radius of the first round from a start close to the photo
        (an edge or MI pose), px at half ``width``.
    far_search_px : int
        Search radius of the first round from a distant start (the sensor
        prior), px at a quarter of ``width``.
    band_sigma_px : float
        Outer Gaussian of the band-pass (the inner one is 0.8 px), px at the
        round's width: larger keeps broader shading.
    min_score : float
        Lowest accepted correlation peak.
    max_second_ratio : float
        The best peak farther than 3 px from the first must be below this
        fraction of it (uniqueness).
    min_texture : float
        Blocks whose band-passed grey levels vary less than this (standard
        deviation, 8-bit levels) are not searched: nothing to correlate.
    min_coverage : float
        Fraction of a block that must show the model (the rest is sky or
        background, filled with a bright level so the skyline correlates).
    """

    KIND: ClassVar[str] = "area"

    width: int = 1024
    template_px: int = 33
    stride_px: int = 24
    search_px: int = 24
    far_search_px: int = 40
    band_sigma_px: float = 6.0
    min_score: float = 0.25
    max_second_ratio: float = 0.9
    min_texture: float = 1.0
    min_coverage: float = 0.6

    #: Inclusive valid range of each numeric field.
    RANGES: ClassVar[dict[str, tuple[float, float]]] = {
        "width": (64, 16384),
        "template_px": (5, 255),
        "stride_px": (1, 512),
        "search_px": (1, 512),
        "far_search_px": (1, 512),
        "band_sigma_px": (0.5, 100.0),
        "min_score": (-1.0, 1.0),
        "max_second_ratio": (0.0, 1.0),
        "min_texture": (0.0, 255.0),
        "min_coverage": (0.0, 1.0),
    }

    def __post_init__(self) -> None:
        check_ranges(self)
        if self.template_px < 5 or self.template_px % 2 == 0:
            raise ValueError(f"template_px must be odd and ≥ 5, not {self.template_px}")
        if self.stride_px < 1 or self.search_px < 1 or self.far_search_px < 1:
            raise ValueError("stride_px, search_px and far_search_px must be positive")
        if self.width < 64:
            raise ValueError(f"width must be at least 64 px, not {self.width}")


@dataclass
class BlockMatches:
    """Blocks of a render found in a photo (pixels of the matched images).

    Attributes
    ----------
    render_points : (N, 2) float array
        Block centres (x, y) in the render.
    photo_points : (N, 2) float array
        Where they were found in the photo (sub-pixel).
    score : (N,) float array
        Correlation peak, in [−1, 1].
    second : (N,) float array
        Best correlation farther than 3 px from the peak.
    accepted : (N,) bool array
        Peak high enough and unique.
    n_blocks : int
        Blocks with texture that were searched (= N).
    """

    render_points: np.ndarray
    photo_points: np.ndarray
    score: np.ndarray
    second: np.ndarray
    accepted: np.ndarray

    @property
    def n_blocks(self) -> int:
        return len(self.score)

    @property
    def shift(self) -> np.ndarray:
        """Photo minus render position, (N, 2)."""
        return self.photo_points - self.render_points


def band_pass(gray: np.ndarray, sigma_px: float, inner_px: float = 0.8) -> np.ndarray:
    """Difference of Gaussians of a grey image, float32 with zero local mean.

    Parameters
    ----------
    gray : (H, W) array
        Grey levels (any numeric type).
    sigma_px : float
        Outer Gaussian, pixels: structures broader than this are removed.
    inner_px : float
        Inner Gaussian, pixels: sensor noise finer than this is removed.

    Returns
    -------
    (H, W) float32 array
    """
    g = np.asarray(gray, np.float32)
    fine = cv2.GaussianBlur(g, (0, 0), inner_px) if inner_px > 0 else g
    return fine - cv2.GaussianBlur(g, (0, 0), sigma_px)


def _gray(rgb: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY) if rgb.ndim == 3 else np.asarray(rgb)


def prepare_render(rgb: np.ndarray, mask: np.ndarray, sigma_px: float) -> np.ndarray:
    """The render's band-passed grey image, its background filled as sky.

    A render's background is black where a photo's sky is bright: filled with
    a level above the model's brightest, the skyline has the contrast of the
    photo's.
    """
    gray = _gray(rgb).astype(np.float32)
    if mask.any() and not mask.all():
        sky = min(255.0, float(np.percentile(gray[mask], 98)) * 1.15 + 10.0)
        gray = np.where(mask, gray, np.float32(sky))
    return band_pass(gray, sigma_px)


def prepare_photo(rgb: np.ndarray, sigma_px: float) -> np.ndarray:
    """The photo's band-passed grey image."""
    return band_pass(_gray(rgb), sigma_px)


def _subpixel(res: np.ndarray, x: int, y: int) -> tuple[float, float]:
    """Parabola vertex through the peak and its neighbours, per axis."""
    dx = dy = 0.0
    if 0 < x < res.shape[1] - 1:
        a, b, c = res[y, x - 1], res[y, x], res[y, x + 1]
        den = a - 2.0 * b + c
        if den < 0:
            dx = float(np.clip(0.5 * (a - c) / den, -0.5, 0.5))
    if 0 < y < res.shape[0] - 1:
        a, b, c = res[y - 1, x], res[y, x], res[y + 1, x]
        den = a - 2.0 * b + c
        if den < 0:
            dy = float(np.clip(0.5 * (a - c) / den, -0.5, 0.5))
    return dx, dy


def match_blocks(
    photo_bp: np.ndarray,
    render_bp: np.ndarray,
    render_mask: np.ndarray,
    *,
    template_px: int = 33,
    search_px: int = 12,
    stride_px: int = 24,
    min_score: float = 0.25,
    max_second_ratio: float = 0.9,
    min_texture: float = 1.0,
    min_coverage: float = 0.6,
) -> BlockMatches:
    """Find blocks of a (band-passed) render in a (band-passed) photo of the same size.

    Parameters
    ----------
    photo_bp, render_bp : (H, W) float32 arrays
        :func:`prepare_photo` / :func:`prepare_render` images, same size.
    render_mask : (H, W) bool array
        Render pixels that show the model; a block is searched only when its
        centre does and at least ``min_coverage`` of it does.
    template_px : int
        Block side, pixels (odd).
    search_px : int
        Search radius about the block's own position, pixels.
    stride_px : int
        Grid step, pixels.
    min_score, max_second_ratio, min_texture, min_coverage
        See :class:`AreaParams`.

    Returns
    -------
    BlockMatches
    """
    if photo_bp.shape != render_bp.shape or render_mask.shape != render_bp.shape:
        raise ValueError(f"photo {photo_bp.shape}, render {render_bp.shape} and mask "
                         f"{render_mask.shape} must have the same size")
    half, r = template_px // 2, int(search_px)
    h, w = render_bp.shape
    # Zero padding: the band-passed images have zero mean, so a window that
    # leaves the photo correlates with nothing there.
    padded = cv2.copyMakeBorder(np.ascontiguousarray(photo_bp, np.float32), r, r, r, r,
                                cv2.BORDER_CONSTANT, value=0.0)
    render_bp = np.ascontiguousarray(render_bp, np.float32)
    # Coverage of each block from an integral image (one pass, not per block).
    cover = cv2.integral(render_mask.astype(np.uint8))
    centres_y = np.arange(half, h - half, stride_px)
    centres_x = np.arange(half, w - half, stride_px)
    n_px = float(template_px * template_px)
    out_r, out_p, out_s, out_2 = [], [], [], []
    for cy in centres_y:
        y0, y1 = cy - half, cy + half + 1
        for cx in centres_x:
            if not render_mask[cy, cx]:
                continue
            x0, x1 = cx - half, cx + half + 1
            covered = cover[y1, x1] - cover[y0, x1] - cover[y1, x0] + cover[y0, x0]
            if covered < min_coverage * n_px:
                continue
            tpl = render_bp[y0:y1, x0:x1]
            if float(tpl.std()) < min_texture:
                continue
            # The window in padded coordinates: the block's own place ± r.
            win = padded[y0:y1 + 2 * r, x0:x1 + 2 * r]
            res = cv2.matchTemplate(win, tpl, cv2.TM_CCOEFF_NORMED)
            _, peak, _, (px, py) = cv2.minMaxLoc(res)
            masked = res.copy()
            masked[max(0, py - 3):py + 4, max(0, px - 3):px + 4] = -1.0
            second = float(masked.max()) if masked.size > 49 else -1.0
            dx, dy = _subpixel(res, px, py)
            out_r.append((cx, cy))
            out_p.append((cx + px - r + dx, cy + py - r + dy))
            out_s.append(peak)
            out_2.append(second)
    if not out_r:
        empty = np.zeros((0, 2))
        return BlockMatches(empty, empty.copy(), np.zeros(0), np.zeros(0), np.zeros(0, bool))
    score = np.asarray(out_s, float)
    second = np.asarray(out_2, float)
    accepted = (score >= min_score) & (second < max_second_ratio * score)
    return BlockMatches(np.asarray(out_r, float), np.asarray(out_p, float), score, second,
                        accepted)


def search_schedule(params: AreaParams, first: bool, far_start: bool,
                    last_shift_px: float, full_width: int) -> tuple[int, int]:
    """Width and search radius of a round of area matching.

    Parameters
    ----------
    params : AreaParams
    first : bool
        The trial's first round.
    far_start : bool
        The trial starts from the sensor prior (degrees off), not from a pose
        estimated by another stage.
    last_shift_px : float
        How far the last round's pose moved the model in the image, pixels at
        ``full_width`` (inf when unknown).
    full_width : int
        The photo's width, pixels.

    Returns
    -------
    width, radius : int, int
        The round's matching width (px) and search radius (px at that width).
    """
    width = min(params.width, full_width)
    if first:
        return ((max(64, width // 4), params.far_search_px) if far_start
                else (max(64, width // 2), params.search_px))
    at_half = last_shift_px * (width / 2) / full_width
    if not math.isfinite(last_shift_px) or at_half > params.search_px / 2:
        return max(64, width // 2), params.search_px
    at_full = last_shift_px * width / full_width
    radius = int(np.clip(math.ceil(1.5 * at_full + 4), 6, 2 * params.search_px // 3))
    return width, radius

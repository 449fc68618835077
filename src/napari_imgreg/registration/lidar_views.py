"""Seed 003's views of a lidar scan and of a photo, made to look alike.

Morago et al. (seed 003) register a photo to a terrestrial laser scan by
rendering the scan from a synthetic camera in two ways, each matched with a
processed version of the photo:

* the **reflectivity view** (the laser intensity rendered from the camera)
  against the photo, both as *gradient magnitude* images
  (:func:`gradient_magnitude`);
* the **wireframe view** — the outlines and intersections of the scan's
  RANSAC-segmented planes (:func:`segment_planes`, :func:`wireframe_view`) —
  against the photo's *Canny edges* (:func:`canny_edges`).

Keypoints are SIFT, described by HOG on oriented multi-scale patches
(:mod:`napari_imgreg.registration.hog`). In the photo only keypoints close to
*LSD line segments* are kept (:func:`lsd_mask`), in the render only those on
segmented planes (:func:`plane_mask`): both focus on the planar rock faces.
:func:`match_view_pair` does detection, description and matching of one
pair (line images through :func:`line_view` first); the camera then follows
from the matches lifted to 3D through the render's ``xyz``
(:func:`lift_to_3d`) by the six-point DLT with RANSAC
(``registration.resection.dlt_ransac``).

Where this departs from the seed, and why:

* The seed draws its wireframe by rotating each plane to face a synthetic
  camera and running Canny on that view; here the planes' outlines are read
  off the render's per-pixel plane labels (and depth), which puts them in
  the render's own camera directly, and the intersection of two adjacent
  planes is drawn exactly where it projects.
* Plane candidates are one point and its normal, not three points
  (see :class:`LidarViewParams`, ``plane_hypotheses``).
* The seed gives no sizes for the HOG patches, cells or scales; the
  defaults and their measurement are in :mod:`~napari_imgreg.registration.hog`.

Everything here is a pure function of images and arrays: a render is any
:class:`~napari_imgreg.render.RenderResult` (for a point-cloud render
``face_id`` is the index of the point seen at each pixel).
"""

from __future__ import annotations

import threading
import weakref
from dataclasses import dataclass, field, replace
from typing import ClassVar

import cv2
import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from ..validate import StageParams, check_ranges
from . import hog
from .features import FeatureParams, verify_geometry
from .stages.edges import canny_edges as _canny_with_orientation

__all__ = [
    "LidarViewParams",
    "PlaneSegmentation",
    "WireframeView",
    "ViewMatches",
    "gradient_magnitude",
    "reflectivity_gradient",
    "canny_edges",
    "line_segment_backend",
    "lsd_segments",
    "lsd_mask",
    "line_view",
    "estimate_normals",
    "point_spacing",
    "segment_planes",
    "plane_label_image",
    "plane_mask",
    "wireframe_view",
    "match_view_pair",
    "describe_view",
    "match_described",
    "photo_views",
    "render_views",
    "PhotoViewFeatures",
    "describe_photo_views",
    "RenderViewMatches",
    "match_render_views",
    "scene_planes",
    "LidarStageMatches",
    "check_matches",
    "lidar_view_matches",
    "lift_to_3d",
    "Seed003Correspondences",
    "seed003_correspondences",
]


@dataclass
class LidarViewParams(StageParams):
    """Settings of seed 003's views, planes, keypoints and matching.

    The seed gives no numbers for most of these; the defaults are the usual
    ones of each method (Canny, LSD, Dalal–Triggs HOG, Lowe's ratio) or
    chosen on the synthetic tests, and each is stated with its unit.

    Attributes
    ----------
    gradient_sigma_px : float
        Gaussian blur before the gradient of the photo and of the
        reflectivity view, pixels (0–10; 0 is none). 1 px removes pixel
        noise and splat edges but keeps the texture.
    gradient_percentile : float
        The gradient magnitude is divided by this percentile of itself (over
        the image or its mask) and clipped at 1 (50–100): a dull photo and a
        contrasty intensity render end up on the same scale.
    gradient_gamma : float
        Then raised to this power (0.1–2): 0.5 (square root) lifts the weak
        texture gradients the heavy-tailed distribution would leave black.
    canny_sigma_px : float
        Blur before Canny on the photo, pixels (0–10).
    canny_high_percentile : float
        Canny's upper threshold as a percentile of the photo's gradient
        magnitude (50–99.9), so a dim photo gets as many edges as a bright one.
    canny_low_ratio : float
        Canny's lower threshold as a fraction of the upper (0.05–1).
    lsd_min_length_px : float
        LSD segments shorter than this are ignored, pixels (1–1000).
    lsd_radius_px : float
        Photo keypoints are kept within this distance of an LSD segment,
        pixels (0–200).
    use_lsd_mask : bool
        Keep photo keypoints near LSD segments only (the seed's focus on
        planar rock; default True). On the generated natural cliffs the
        masks keep the keypoints that match off the rock: on the small
        sample's textured mesh :func:`~napari_imgreg.registration.seed003.register_seed003`
        registered 0 of 3 photos with both masks, 2 of 3 without them
        (upright patches, 8 rounds).
    line_blur_px : float
        Line images (the photo's Canny edges, the wireframe view) are blurred
        by this Gaussian σ before SIFT, pixels (0–10): on a one-pixel binary
        line OpenCV's SIFT finds no extrema at all (measured: 0 keypoints on
        a wireframe view, 125 after 1 px of blur).
    plane_distance_m : float
        RANSAC inlier distance to a plane, metres (0.0001–10). About ten
        times the scanner's range noise: 5 cm for a TLS at 5 mm.
    plane_normal_deg : float
        A point joins a plane only when its own normal is within this angle
        of the plane's, degrees (1–90).
    plane_min_points : int
        Smallest plane kept, points (3–10⁹); sequential RANSAC stops when the
        best remaining plane has fewer.
    plane_max_planes : int
        Planes at most (1–1000).
    plane_hypotheses : int
        Candidate planes scored per extracted plane (1–100 000). Each is one
        point and its own normal (Schnabel et al. 2007 draw three points
        whose normals must agree; with local-PCA normals one suffices), then
        the best is refined by least squares on its inliers.
    plane_sample_points : int
        Points on which the candidates are scored (1 000–10⁸): a random
        subset keeps a 50 M-point cloud as fast as a 50 k one.
    plane_cell_m : float
        Cell of the connectivity bitmap in the plane, metres (0–100; 0 is
        three times the cloud's median point spacing): a plane's points are
        split into connected patches (cells 8-connected after one cell of
        dilation, so gaps of up to two cells are bridged) and only the
        largest is kept, so two coplanar ledges far apart are two planes.
    normal_neighbours : int
        Neighbours of the local-PCA normals when none are given (5–200).
    wireframe_gap_px : float
        Unlabelled pixels up to this far from a plane's pixels join it when
        their point lies on that plane (0–50): closes the strip along a
        crease where the points' normals are mixed, so two planes meet in
        one line, not two.
    wireframe_depth_jump : float
        A depth discontinuity (occluding contour) is drawn between
        neighbouring pixels whose depths differ by more than this fraction
        of the nearer (0.001–1).
    wireframe_min_hole_px : int
        No-data regions smaller than this (pixels) are holes in the scan,
        not sky: their outlines are not drawn (0–10⁷).
    wireframe_intersections : bool
        Draw the exact projected intersection line of two adjacent planes
        in place of the ragged pixel boundary between them.
    wireframe_min_dihedral_deg : float
        Only planes meeting at this angle or more get an intersection line
        (1–90); nearly parallel planes intersect far from where they meet.
    wireframe_max_offset_px : float
        The intersection line replaces the pixel boundary only when the
        boundary lies within this median distance of it, pixels (0.1–50):
        a rough face meeting another away from the fitted planes keeps its
        own outline.
    plane_mask_radius_px : float
        Render keypoints are kept within this distance of segmented-plane
        pixels, pixels (0–200).
    use_plane_mask : bool
        Keep render keypoints near segmented planes only (the seed's;
        default True; see ``use_lsd_mask``: on the benchmark's rough cliffs
        the planes are mostly the ground).
    max_keypoints : int
        SIFT keypoints per image (10–1 000 000).
    sift_contrast_threshold : float
        OpenCV SIFT's contrast threshold (0.001–0.5; Lowe's 0.04).
    hog_scales : tuple of float
        Patch sides as multiples of the SIFT keypoint diameter, one HOG per
        scale (each 0.5–64): the seed's "patches at multiple scales".
    hog_min_patch_px : float
        Smallest patch side, image pixels (4–1024).
    hog_patch_px : int
        Side of the resampled patch, pixels (8–256; a multiple of
        ``hog_cell_px``).
    hog_cell_px : int
        HOG cell side, patch pixels (2–64).
    hog_block_cells : int
        HOG block side, cells (1–8).
    hog_orientations : int
        Unsigned orientation bins (2–36).
    upright : bool
        Describe patches at orientation 0 instead of the keypoint's dominant
        gradient direction (the seed orients them; upright is better when
        photo and render share their up to within ~15°).
    match_ratio : float
        Lowe's ratio test on the HOG distances (0.3–1).
    """

    KIND: ClassVar[str] = "lidar-view"

    gradient_sigma_px: float = 1.0
    gradient_percentile: float = 99.0
    gradient_gamma: float = 0.5
    canny_sigma_px: float = 2.0
    canny_high_percentile: float = 85.0
    canny_low_ratio: float = 0.4
    lsd_min_length_px: float = 15.0
    lsd_radius_px: float = 8.0
    use_lsd_mask: bool = True
    line_blur_px: float = 1.0
    plane_distance_m: float = 0.05
    plane_normal_deg: float = 20.0
    plane_min_points: int = 500
    plane_max_planes: int = 30
    plane_hypotheses: int = 200
    plane_sample_points: int = 20_000
    plane_cell_m: float = 0.0
    normal_neighbours: int = 16
    wireframe_gap_px: float = 4.0
    wireframe_depth_jump: float = 0.05
    wireframe_min_hole_px: int = 50
    wireframe_intersections: bool = True
    wireframe_min_dihedral_deg: float = 20.0
    wireframe_max_offset_px: float = 3.0
    plane_mask_radius_px: float = 4.0
    use_plane_mask: bool = True
    max_keypoints: int = 2000
    sift_contrast_threshold: float = 0.04
    hog_scales: tuple[float, ...] = field(default=(4.0, 8.0, 16.0))
    hog_min_patch_px: float = 16.0
    hog_patch_px: int = 32
    hog_cell_px: int = 8
    hog_block_cells: int = 2
    hog_orientations: int = 9
    upright: bool = False
    match_ratio: float = 0.8

    #: Inclusive valid range of each numeric field (every element of ``hog_scales``).
    RANGES: ClassVar[dict[str, tuple[float, float]]] = {
        "gradient_sigma_px": (0.0, 10.0),
        "gradient_percentile": (50.0, 100.0),
        "gradient_gamma": (0.1, 2.0),
        "canny_sigma_px": (0.0, 10.0),
        "canny_high_percentile": (50.0, 99.9),
        "canny_low_ratio": (0.05, 1.0),
        "lsd_min_length_px": (1.0, 1000.0),
        "lsd_radius_px": (0.0, 200.0),
        "line_blur_px": (0.0, 10.0),
        "plane_distance_m": (1e-4, 10.0),
        "plane_normal_deg": (1.0, 90.0),
        "plane_min_points": (3, 1_000_000_000),
        "plane_max_planes": (1, 1000),
        "plane_hypotheses": (1, 100_000),
        "plane_sample_points": (1000, 100_000_000),
        "plane_cell_m": (0.0, 100.0),
        "normal_neighbours": (5, 200),
        "wireframe_gap_px": (0.0, 50.0),
        "wireframe_depth_jump": (0.001, 1.0),
        "wireframe_min_hole_px": (0, 10_000_000),
        "wireframe_min_dihedral_deg": (1.0, 90.0),
        "wireframe_max_offset_px": (0.1, 50.0),
        "plane_mask_radius_px": (0.0, 200.0),
        "max_keypoints": (10, 1_000_000),
        "sift_contrast_threshold": (0.001, 0.5),
        "hog_scales": (0.5, 64.0),
        "hog_min_patch_px": (4.0, 1024.0),
        "hog_patch_px": (8, 256),
        "hog_cell_px": (2, 64),
        "hog_block_cells": (1, 8),
        "hog_orientations": (2, 36),
        "match_ratio": (0.3, 1.0),
    }

    def __post_init__(self) -> None:
        self.hog_scales = tuple(float(s) for s in self.hog_scales)  # type: ignore[assignment]
        if not self.hog_scales:
            raise ValueError("hog_scales needs at least one scale")
        check_ranges(self)
        if self.hog_patch_px % self.hog_cell_px:
            raise ValueError(f"hog_patch_px ({self.hog_patch_px}) must be a multiple of "
                             f"hog_cell_px ({self.hog_cell_px})")
        if self.hog_patch_px // self.hog_cell_px < self.hog_block_cells:
            raise ValueError("a HOG block (hog_block_cells) must fit in the patch's cells")


# ======================================================== photo-side images
def _gray_float(image: np.ndarray) -> np.ndarray:
    """(H, W) or (H, W, 3) image → (H, W) float32 grey on 0–255."""
    src = np.asarray(image)
    img = src.astype(np.float32)
    if img.ndim == 3:
        img = cv2.cvtColor(np.ascontiguousarray(img[..., :3]), cv2.COLOR_RGB2GRAY)
    if img.ndim != 2:
        raise ValueError(f"expected an (H, W) or (H, W, 3) image, got shape {src.shape}")
    img = np.nan_to_num(img)
    if src.dtype != np.uint8 and img.size and float(img.max()) <= 1.0:
        img = img * 255.0                    # a float image in [0, 1]
    return img


def gradient_magnitude(
    image: np.ndarray,
    sigma_px: float = 1.0,
    mask: np.ndarray | None = None,
    percentile: float = 99.0,
    gamma: float = 0.5,
) -> np.ndarray:
    """The gradient-magnitude image the seed matches (photo and reflectivity view).

    Grey levels are blurred (over ``mask`` only, so the edge of the render
    against the sky adds no gradient), differentiated (Sobel, per pixel),
    divided by their ``percentile`` (over the valid pixels) and clipped at
    1, then raised to ``gamma``: two images of the same rock with different
    contrast, exposure or sensor give comparable values.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) array
        uint8, or float in [0, 1].
    sigma_px : float
        Gaussian σ before differentiation, pixels; 0 for none.
    mask : (H, W) bool array, optional
        Valid pixels (a render's ``mask``); gradients within one pixel of
        its border are 0.
    percentile : float
        Normalising percentile of the magnitude, in (0, 100].
    gamma : float
        Exponent after normalisation (> 0).

    Returns
    -------
    (H, W) uint8 array
        0 where invalid, and everywhere for a flat image (normalising
        percentile under 0.001 grey levels per pixel).
    """
    if gamma <= 0 or not 0 < percentile <= 100:
        raise ValueError("gamma must be > 0 and percentile within (0, 100]")
    gray = _gray_float(image)
    valid = None if mask is None else np.asarray(mask, bool)
    if sigma_px > 0:
        if valid is None:
            gray = cv2.GaussianBlur(gray, (0, 0), float(sigma_px))
        else:  # normalised convolution: the background neither bleeds in nor shows
            num = cv2.GaussianBlur(np.where(valid, gray, 0).astype(np.float32), (0, 0),
                                   float(sigma_px))
            den = cv2.GaussianBlur(valid.astype(np.float32), (0, 0), float(sigma_px))
            gray = np.where(den > 1e-3, num / np.maximum(den, 1e-3), 0).astype(np.float32)
    dx = cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
    dy = cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    mag = cv2.magnitude(dx, dy)
    if valid is not None:
        inner = cv2.erode(valid.astype(np.uint8), np.ones((3, 3), np.uint8),
                          borderType=cv2.BORDER_REPLICATE).astype(bool)
        mag[~inner] = 0.0
        sel = mag[inner]
    else:
        sel = mag.ravel()
    scale = float(np.percentile(sel, percentile)) if sel.size else 0.0
    if scale <= 1e-3:  # grey levels per pixel: a flat image, only rounding noise
        return np.zeros(mag.shape, np.uint8)
    out = np.clip(mag / scale, 0.0, 1.0) ** float(gamma)
    return np.round(out * 255.0).astype(np.uint8)


def reflectivity_gradient(render, params: LidarViewParams | None = None) -> np.ndarray:
    """Gradient magnitude of a render's intensity (its ``rgb``) over its mask.

    Parameters
    ----------
    render : RenderResult
        For a point cloud, ``rgb`` holds the laser intensity.
    params : LidarViewParams, optional

    Returns
    -------
    (H, W) uint8 array
    """
    p = params or LidarViewParams()
    return gradient_magnitude(render.rgb, p.gradient_sigma_px, render.mask,
                              p.gradient_percentile, p.gradient_gamma)


def canny_edges(
    image: np.ndarray,
    sigma_px: float = 2.0,
    high_percentile: float = 85.0,
    low_ratio: float = 0.4,
    mask: np.ndarray | None = None,
) -> np.ndarray:
    """The photo's Canny edges, thresholds from its own gradient distribution.

    The same detector as the edge-alignment stage
    (:func:`napari_imgreg.registration.stages.edges.canny_edges`).

    Parameters
    ----------
    image : (H, W) or (H, W, 3) array
        uint8, or float in [0, 1].
    sigma_px : float
        Gaussian σ before differentiation, pixels.
    high_percentile : float
        Upper hysteresis threshold, percentile of the gradient magnitude.
    low_ratio : float
        Lower threshold as a fraction of the upper.
    mask : (H, W) bool array, optional
        Pixels whose gradients set the thresholds; edges outside it dropped.

    Returns
    -------
    (H, W) bool array
    """
    gray = np.clip(_gray_float(image), 0, 255).astype(np.uint8)
    m = None if mask is None else np.asarray(mask, bool)
    edges, _ = _canny_with_orientation(gray, sigma_px, high_percentile, low_ratio, m)
    return edges & m if m is not None else edges


def line_segment_backend() -> str:
    """``"opencv-lsd"`` when this OpenCV has the LSD detector (opencv-python-headless
    4.14 does), else ``"skimage-hough"`` (probabilistic Hough on Canny edges)."""
    try:
        cv2.createLineSegmentDetector()
        return "opencv-lsd"
    except (cv2.error, AttributeError):
        return "skimage-hough"


def lsd_segments(image: np.ndarray, min_length_px: float = 15.0) -> np.ndarray:
    """Straight line segments of an image (von Gioi et al.'s LSD through OpenCV).

    Falls back to scikit-image's probabilistic Hough transform on Canny
    edges where the installed OpenCV lacks LSD (see
    :func:`line_segment_backend`).

    Parameters
    ----------
    image : (H, W) or (H, W, 3) array
    min_length_px : float
        Shorter segments are dropped.

    Returns
    -------
    (M, 4) float32 array
        ``x1, y1, x2, y2``, pixels.
    """
    gray = np.clip(_gray_float(image), 0, 255).astype(np.uint8)
    if line_segment_backend() == "opencv-lsd":
        lines = cv2.createLineSegmentDetector().detect(gray)[0]
        lines = np.zeros((0, 4), np.float32) if lines is None else lines.reshape(-1, 4)
    else:  # only where OpenCV was built without LSD (tested by monkeypatching)
        from skimage.transform import probabilistic_hough_line

        edges = canny_edges(gray, 1.0)
        found = probabilistic_hough_line(edges, threshold=10, line_length=int(min_length_px),
                                         line_gap=2, rng=0)
        lines = np.array([(a[0], a[1], b[0], b[1]) for a, b in found], np.float32).reshape(-1, 4)
    length = np.hypot(lines[:, 2] - lines[:, 0], lines[:, 3] - lines[:, 1])
    return lines[length >= min_length_px].astype(np.float32)


def lsd_mask(
    image: np.ndarray,
    radius_px: float = 8.0,
    min_length_px: float = 15.0,
    segments: np.ndarray | None = None,
) -> np.ndarray:
    """Pixels within ``radius_px`` of a line segment of the image.

    The seed keeps only photo keypoints close to LSD segments (they are on
    the rock's planar faces and their edges, not on foliage).

    Parameters
    ----------
    image : (H, W) or (H, W, 3) array
    radius_px : float
        Distance to the nearest segment, pixels.
    min_length_px : float
        Shorter segments are ignored.
    segments : (M, 4) array, optional
        Segments already found (``x1, y1, x2, y2``); else :func:`lsd_segments`.

    Returns
    -------
    (H, W) bool array
    """
    h, w = np.asarray(image).shape[:2]
    segs = lsd_segments(image, min_length_px) if segments is None else np.asarray(segments)
    lines = np.zeros((h, w), np.uint8)
    shift = 4  # sub-pixel endpoints for cv2.line
    for x1, y1, x2, y2 in np.round(np.asarray(segs, np.float64).reshape(-1, 4) * 16).astype(int):
        cv2.line(lines, (int(x1), int(y1)), (int(x2), int(y2)), 1, 1, cv2.LINE_8, shift)
    if not lines.any():
        return np.zeros((h, w), bool)
    dist = cv2.distanceTransform((lines == 0).astype(np.uint8), cv2.DIST_L2, 5)
    return dist <= float(radius_px)


def line_view(lines: np.ndarray, blur_px: float = 1.0) -> np.ndarray:
    """A line image as SIFT can read it: 255 on the lines, blurred by ``blur_px``.

    Parameters
    ----------
    lines : (H, W) bool array
        Canny edges of the photo or :attr:`WireframeView.lines`.
    blur_px : float
        Gaussian σ, pixels; 0 for none (SIFT then finds almost nothing on
        one-pixel lines).

    Returns
    -------
    (H, W) uint8 array
        Rescaled so that the blurred lines' peak is 255 again.
    """
    img = np.asarray(lines, bool).astype(np.float32)
    if blur_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), float(blur_px))
        peak = float(img.max())
        if peak > 0:
            img /= peak
    return np.round(np.clip(img, 0, 1) * 255.0).astype(np.uint8)


# ============================================================ plane segments
def estimate_normals(xyz: np.ndarray, k: int = 16, chunk: int = 200_000) -> np.ndarray:
    """Unit normals of a point cloud by local PCA (smallest eigenvector of the
    covariance of each point's ``k`` nearest neighbours).

    Parameters
    ----------
    xyz : (N, 3) array
        Points, metres.
    k : int
        Neighbours including the point itself (≥ 3).
    chunk : int
        Points per batch (bounds the memory to ~chunk × k × 72 bytes).

    Returns
    -------
    (N, 3) float32 array
        Unit normals, sign arbitrary (PCA has none).
    """
    pts = np.asarray(xyz, np.float64).reshape(-1, 3)
    n = pts.shape[0]
    k = int(min(max(3, k), n))
    out = np.zeros((n, 3), np.float32)
    if n < 3:
        return out
    tree = cKDTree(pts)
    for start in range(0, n, chunk):
        q = pts[start:start + chunk]
        _, idx = tree.query(q, k)
        nb = pts[idx]
        nb -= nb.mean(axis=1, keepdims=True)
        cov = np.matmul(nb.transpose(0, 2, 1), nb)          # (c, 3, 3)
        _, vec = np.linalg.eigh(cov)
        out[start:start + len(q)] = vec[:, :, 0]
    return out


def point_spacing(xyz: np.ndarray, sample: int = 5000, seed: int = 0) -> float:
    """Median nearest-neighbour distance of a cloud (on a random sample), metres."""
    pts = np.asarray(xyz, np.float64).reshape(-1, 3)
    if pts.shape[0] < 2:
        return 0.0
    rng = np.random.default_rng(seed)
    pick = rng.choice(pts.shape[0], min(sample, pts.shape[0]), replace=False)
    d, _ = cKDTree(pts).query(pts[pick], 2)
    return float(np.median(d[:, 1]))


@dataclass
class PlaneSegmentation:
    """Planes found in a point cloud and the plane of each point.

    Attributes
    ----------
    labels : (N,) int32 array
        Plane index of each point, -1 for points on no plane (vegetation,
        scree, the crease strips between faces).
    normals : (K, 3) float64 array
        Unit plane normals, on the side the points' own normals face on
        average (toward the scanner when the cloud's normals are).
    offsets : (K,) float64 array
        ``d`` of the plane ``normal · x + d = 0``, metres.
    centroids : (K, 3) float64 array
        Mean of each plane's points, metres.
    counts : (K,) int64 array
        Points per plane.
    rms_m : (K,) float64 array
        RMS distance of each plane's points to it, metres.
    """

    labels: np.ndarray
    normals: np.ndarray
    offsets: np.ndarray
    centroids: np.ndarray
    counts: np.ndarray
    rms_m: np.ndarray

    def __len__(self) -> int:
        return int(self.normals.shape[0])


def _fit_plane(pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares plane of points: (centroid (3,), unit normal (3,)), float64."""
    pts = np.asarray(pts, np.float64)
    c = pts.mean(axis=0)
    _, vec = np.linalg.eigh((pts - c).T @ (pts - c))
    return c, vec[:, 0]


def _largest_patch(uv: np.ndarray, cell: float, max_side: int = 4096) -> np.ndarray:
    """Points of the largest 8-connected patch of a plane's points on a bitmap of
    ``cell``-sized squares in the plane (Schnabel et al.'s connectivity test).

    Parameters
    ----------
    uv : (M, 2) array
        In-plane coordinates, metres.
    cell : float
        Bitmap cell, metres (grown if the bitmap would exceed ``max_side``).

    Returns
    -------
    (M,) bool array
    """
    lo = uv.min(axis=0)
    extent = uv.max(axis=0) - lo
    cell = max(cell, float(extent.max()) / max_side, 1e-9)
    ij = np.floor((uv - lo) / cell).astype(np.int64)
    shape = tuple(ij.max(axis=0) + 1)
    occ = np.zeros(shape, bool)
    occ[ij[:, 0], ij[:, 1]] = True
    # One cell of dilation bridges the odd empty cell of an uneven sampling.
    occ = ndimage.binary_dilation(occ, structure=np.ones((3, 3), bool))
    lab, n = ndimage.label(occ, structure=np.ones((3, 3), bool))
    if n <= 1:
        return np.ones(uv.shape[0], bool)
    per_point = lab[ij[:, 0], ij[:, 1]]
    counts = np.bincount(per_point, minlength=n + 1)
    counts[0] = 0
    return per_point == int(np.argmax(counts))


def segment_planes(
    xyz: np.ndarray,
    normals: np.ndarray | None = None,
    params: LidarViewParams | None = None,
    seed: int = 0,
) -> PlaneSegmentation:
    """Planes of a point cloud by sequential RANSAC with normal agreement and connectivity.

    Repeatedly, on the points not yet assigned: score
    ``plane_hypotheses`` candidate planes (each a random point and its
    normal) on a random subset of ``plane_sample_points``; a point supports
    a plane when it lies within ``plane_distance_m`` of it *and* its normal
    is within ``plane_normal_deg``; refine the best candidate twice by least
    squares on its support; take its support among all the unassigned
    points, keep the largest connected patch (bitmap of ``plane_cell_m``
    cells in the plane), fit the plane to it once more and assign it. Stop
    after ``plane_max_planes`` planes or when the best has fewer than
    ``plane_min_points`` points.

    Parameters
    ----------
    xyz : (N, 3) array
        Points, metres.
    normals : (N, 3) array, optional
        Unit normals (e.g. the cloud scene's cached ones); local PCA with
        ``normal_neighbours`` neighbours when omitted.
    params : LidarViewParams, optional
    seed : int
        Seed of the random draws: the same cloud gives the same planes.

    Returns
    -------
    PlaneSegmentation
        Planes in order of extraction (largest first, roughly).
    """
    p = params or LidarViewParams()
    pts = np.asarray(xyz, np.float64).reshape(-1, 3)
    n = pts.shape[0]
    if not np.all(np.isfinite(pts)):
        raise ValueError("segment_planes: the cloud has non-finite coordinates")
    if normals is None:
        nrm = estimate_normals(pts, p.normal_neighbours).astype(np.float64)
    else:
        nrm = np.asarray(normals, np.float64).reshape(-1, 3)
        if nrm.shape[0] != n:
            raise ValueError(f"segment_planes: {nrm.shape[0]} normals for {n} points")
        nrm = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    origin = pts.mean(axis=0) if n else np.zeros(3)
    # float32 about the centroid (8 µm at 100 m) halves the memory traffic.
    local = (pts - origin).astype(np.float32)
    nrm = nrm.astype(np.float32)
    rng = np.random.default_rng(seed)
    thr = float(p.plane_distance_m)
    cos_n = float(np.cos(np.deg2rad(p.plane_normal_deg)))
    cell = float(p.plane_cell_m) or 3.0 * max(point_spacing(local, seed=seed), 1e-6)
    labels = np.full(n, -1, np.int32)
    found: list[tuple[np.ndarray, np.ndarray, int, float]] = []

    def support(c: np.ndarray, nv: np.ndarray, idx: np.ndarray) -> np.ndarray:
        nv32 = nv.astype(np.float32)
        dist = np.abs(local[idx] @ nv32 - np.float32(c @ nv))
        return (dist < thr) & (np.abs(nrm[idx] @ nv32) > cos_n)

    for _ in range(int(p.plane_max_planes)):
        free = np.flatnonzero(labels < 0)
        if free.size < p.plane_min_points:
            break
        # Drawn with replacement: a few repeats do not matter, and a 50 M-point
        # cloud then needs no permutation per plane.
        sample = free[rng.integers(0, free.size, min(free.size, int(p.plane_sample_points)))]
        hyp = sample[rng.integers(0, sample.size, int(p.plane_hypotheses))]
        sp, sn = local[sample], nrm[sample]
        best, best_count = -1, -1
        for start in range(0, hyp.size, 64):     # sample × 64 candidates at a time
            h = hyp[start:start + 64]
            nh = nrm[h]
            dist = np.abs(sp @ nh.T - np.einsum("ij,ij->i", local[h], nh)[None, :])  # (S, 64)
            agree = np.abs(sn @ nh.T) > cos_n
            counts = np.count_nonzero((dist < thr) & agree, axis=0)
            j = int(np.argmax(counts))
            if counts[j] > best_count:
                best, best_count = int(h[j]), int(counts[j])
        if best_count * free.size / sample.size < 0.5 * p.plane_min_points:
            break                                # not even half a plane left
        # Least squares on the support until it stops growing: a point's own
        # normal is a few degrees off, which on a 10 m face is a band, not the face.
        c, nv, count = local[best], nrm[best], best_count
        for _refine in range(10):
            on = support(c, nv, sample)
            if np.count_nonzero(on) < 3:
                break
            c_new, nv_new = _fit_plane(sp[on])
            n_new = int(np.count_nonzero(support(c_new, nv_new, sample)))
            if n_new <= count:
                break
            c, nv, count = c_new, nv_new, n_new
        members = free[support(c, nv, free)]
        if members.size < p.plane_min_points:
            break
        c, nv = _fit_plane(local[members])       # once more on all the free points
        members = free[support(c, nv, free)]
        if members.size < p.plane_min_points:
            break
        basis = np.linalg.svd(np.eye(3) - np.outer(nv, nv))[0][:, :2]
        members = members[_largest_patch((local[members] - c) @ basis, cell)]
        if members.size < p.plane_min_points:
            break
        c, nv = _fit_plane(local[members])
        if float(np.sum(nrm[members] @ nv)) < 0:
            nv = -nv
        rms = float(np.sqrt(np.mean(((local[members] - c) @ nv) ** 2)))
        labels[members] = len(found)
        found.append((c + origin, nv, int(members.size), rms))

    k = len(found)
    normals_out = np.array([f[1] for f in found], np.float64).reshape(k, 3)
    centroids = np.array([f[0] for f in found], np.float64).reshape(k, 3)
    return PlaneSegmentation(
        labels=labels,
        normals=normals_out,
        offsets=-np.einsum("ij,ij->i", normals_out, centroids),
        centroids=centroids,
        counts=np.array([f[2] for f in found], np.int64),
        rms_m=np.array([f[3] for f in found], np.float64),
    )


# ============================================================ wireframe view
#: Per-pixel labels of :func:`plane_label_image` besides the plane indices.
UNLABELLED, NO_HIT = -1, -2


def plane_label_image(render, point_plane_labels) -> np.ndarray:
    """The plane index seen at each pixel of a point-cloud render.

    Parameters
    ----------
    render : RenderResult
        ``face_id`` the index of the point seen at each pixel (-1 none). (A
        mesh render works too, with labels per triangle.)
    point_plane_labels : (N,) int array or PlaneSegmentation
        Plane of each point (-1 none).

    Returns
    -------
    (H, W) int32 array
        Plane index; :data:`UNLABELLED` (-1) where a point on no plane is
        seen, :data:`NO_HIT` (-2) where nothing is.
    """
    labels = np.asarray(getattr(point_plane_labels, "labels", point_plane_labels))
    face = np.asarray(render.face_id)
    hit = np.asarray(render.mask, bool) & (face >= 0)
    if hit.any() and int(face[hit].max()) >= labels.shape[0]:
        raise ValueError(f"the render shows point {int(face[hit].max())} but only "
                         f"{labels.shape[0]} point labels were given")
    out = np.full(face.shape, NO_HIT, np.int32)
    out[hit] = labels[face[hit]]
    return out


def plane_mask(plane_labels: np.ndarray, radius_px: float = 4.0) -> np.ndarray:
    """Pixels within ``radius_px`` of a segmented plane's pixels (render keypoints
    are kept there: the seed's focus on the planar rock)."""
    on = np.asarray(plane_labels) >= 0
    if not on.any():
        return on
    if radius_px <= 0:
        return on
    return cv2.distanceTransform((~on).astype(np.uint8), cv2.DIST_L2, 5) <= float(radius_px)


@dataclass
class WireframeView:
    """The wireframe view of a render: a line image of its planes' outlines.

    Attributes
    ----------
    lines : (H, W) bool array
        One-pixel lines: plane boundaries (against other planes, unlabelled
        points and the sky), occluding contours (depth discontinuities) and
        the silhouette against large no-data regions; where two planes meet
        at ``wireframe_min_dihedral_deg`` or more, their projected
        intersection line in place of the pixel boundary.
    plane_labels : (H, W) int32 array
        Plane seen at each pixel after closing the crease gaps (see
        :func:`plane_label_image` for -1 and -2).
    intersections : list of (int, int, (2, 3) array)
        The planes ``a < b`` whose intersection was drawn and the segment's
        3D end points, metres.
    """

    lines: np.ndarray
    plane_labels: np.ndarray
    intersections: list = field(default_factory=list)

    @property
    def image(self) -> np.ndarray:
        """(H, W) uint8: 255 on the lines, 0 elsewhere (for display; SIFT reads
        :func:`line_view` of :attr:`lines`)."""
        return self.lines.astype(np.uint8) * 255


def _pixel_planes(lab: np.ndarray, xyz: np.ndarray) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Least-squares plane (centroid, unit normal) of each label's pixels' points."""
    fits = {}
    for k in np.unique(lab[lab >= 0]):
        on = lab == k
        pts = xyz[on].astype(np.float64)
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        if pts.shape[0] >= 3:
            fits[int(k)] = _fit_plane(pts)
    return fits


def _fill_crease_gaps(lab: np.ndarray, xyz: np.ndarray, fits: dict, gap_px: float,
                      tol_m: float) -> np.ndarray:
    """Unlabelled hit pixels within ``gap_px`` of a plane's pixels take, of the planes
    that near, the one their point lies closest to, when within ``tol_m``."""
    unl = lab == UNLABELLED
    if gap_px <= 0 or not unl.any() or not fits:
        return lab
    best_res = np.full(lab.shape, np.inf)
    best_lab = np.full(lab.shape, UNLABELLED, np.int32)
    for k, (c, nv) in fits.items():
        dist = cv2.distanceTransform((lab != k).astype(np.uint8), cv2.DIST_L2, 5)
        ys, xs = np.nonzero(unl & (dist <= gap_px))
        if ys.size == 0:
            continue
        res = np.abs((xyz[ys, xs].astype(np.float64) - c) @ nv)
        better = (res <= tol_m) & (res < best_res[ys, xs])
        best_res[ys[better], xs[better]] = res[better]
        best_lab[ys[better], xs[better]] = k
    return np.where(unl & (best_lab >= 0), best_lab, lab).astype(np.int32)


def wireframe_view(render, point_plane_labels, params: LidarViewParams | None = None
                   ) -> WireframeView:
    """Seed 003's wireframe view: a line image of the segmented planes as the render's
    camera sees them, to match against the photo's Canny edges.

    Planes are fitted again to the pixels' ``xyz`` (so only the labels are
    needed); unlabelled pixels along a crease join the nearer plane
    (``wireframe_gap_px``); a line pixel is marked, on the nearer side,
    wherever two 4-neighbours differ in plane (at least one on a plane),
    differ in depth by more than ``wireframe_depth_jump``, or one sees
    nothing inside a no-data region of ``wireframe_min_hole_px`` or more.
    With ``wireframe_intersections``, the pixel boundary between two planes
    meeting at a real angle is replaced by their intersection line
    projected through the render's camera, over the extent of that
    boundary.

    Parameters
    ----------
    render : RenderResult
        ``xyz``, ``depth``, ``mask``, ``face_id`` (point index for a
        point-cloud render), ``intrinsics`` and ``cam_from_world``.
    point_plane_labels : (N,) int array or PlaneSegmentation
    params : LidarViewParams, optional

    Returns
    -------
    WireframeView
    """
    p = params or LidarViewParams()
    lab = plane_label_image(render, point_plane_labels)
    xyz = np.asarray(render.xyz, np.float32)
    lab = _fill_crease_gaps(lab, xyz, _pixel_planes(lab, xyz), p.wireframe_gap_px,
                            2.0 * p.plane_distance_m)
    hit = lab != NO_HIT
    h, w = lab.shape
    depth = np.where(hit, np.nan_to_num(np.asarray(render.depth, np.float64), nan=np.inf), np.inf)
    # No-data regions: large ones are sky or the scan's edge, small ones holes.
    void_lab, n_void = ndimage.label(~hit)
    sizes = np.bincount(void_lab.ravel(), minlength=n_void + 1)
    big_void = (sizes >= p.wireframe_min_hole_px)[void_lab] & ~hit
    cmp = np.where(~hit & ~big_void, -3, lab)       # -3: a small hole, never a boundary

    other = np.zeros((h, w), bool)                  # every line but plane-to-plane
    crease_pairs: dict[tuple[int, int], list[np.ndarray]] = {}
    crease = np.zeros((h, w), np.int64)             # pair code + 1 of crease pixels
    n_lab = int(max(lab.max(), 0)) + 1
    for axis in (0, 1):
        a_sl = (slice(None, -1), slice(None)) if axis == 0 else (slice(None), slice(None, -1))
        b_sl = (slice(1, None), slice(None)) if axis == 0 else (slice(None), slice(1, None))
        la, lb = cmp[a_sl], cmp[b_sl]
        da, db = depth[a_sl], depth[b_sl]
        valid = (la != -3) & (lb != -3)
        both_hit = (la >= UNLABELLED) & (lb >= UNLABELLED)
        near = np.minimum(da, db)
        with np.errstate(invalid="ignore"):
            jump = both_hit & (np.abs(da - db) > p.wireframe_depth_jump * near)
        plane_edge = valid & (la != lb) & ((la >= 0) | (lb >= 0))
        silhouette = valid & ((la == NO_HIT) != (lb == NO_HIT))   # hit beside a large void
        pair = plane_edge & (la >= 0) & (lb >= 0) & ~jump
        edge = (plane_edge | jump | silhouette) & ~pair
        mark_a = edge & (da <= db)
        mark_b = edge & ~(da <= db)
        other[a_sl] |= mark_a
        other[b_sl] |= mark_b
        # Plane-to-plane boundaries: kept apart, per pair, for the intersection lines.
        ya, xa = np.nonzero(pair)
        yb, xb = (ya + 1, xa) if axis == 0 else (ya, xa + 1)
        lo = np.minimum(la[pair], lb[pair]).astype(np.int64)
        hi = np.maximum(la[pair], lb[pair]).astype(np.int64)
        nearer_a = da[pair] <= db[pair]
        ym, xm = np.where(nearer_a, ya, yb), np.where(nearer_a, xa, xb)
        crease[ym, xm] = lo * n_lab + hi + 1
        for code in np.unique(lo * n_lab + hi):
            sel = (lo * n_lab + hi) == code
            crease_pairs.setdefault((int(code // n_lab), int(code % n_lab)), []).append(
                np.stack([ya[sel], xa[sel], yb[sel], xb[sel]], axis=1))

    lines = other | (crease > 0)
    intersections = []
    if p.wireframe_intersections and crease_pairs:
        min_sin = np.sin(np.deg2rad(p.wireframe_min_dihedral_deg))
        intr, pose = render.intrinsics, render.cam_from_world
        fits = _pixel_planes(lab, xyz)        # again: the filled pixels belong to them
        for (a, b), chunks in crease_pairs.items():
            if a not in fits or b not in fits:
                continue
            px = np.concatenate(chunks)
            if px.shape[0] < 8:
                continue
            (ca, na), (cb, nb) = fits[a], fits[b]
            u = np.cross(na, nb)
            if np.linalg.norm(u) < min_sin:
                continue
            u /= np.linalg.norm(u)
            mid = 0.5 * (xyz[px[:, 0], px[:, 1]].astype(np.float64)
                         + xyz[px[:, 2], px[:, 3]].astype(np.float64))
            centre = mid.mean(axis=0)
            x0 = np.linalg.solve(np.stack([na, nb, u]), np.array([na @ ca, nb @ cb, u @ centre]))
            t = (mid - x0) @ u
            t0, t1 = float(t.min()), float(t.max())
            ends = np.stack([x0 + t0 * u, x0 + t1 * u])
            ends_px = pose.project(intr, ends)
            if not np.all(np.isfinite(ends_px)):
                continue
            steps = int(np.ceil(np.linalg.norm(ends_px[1] - ends_px[0]) / 0.5)) + 2
            samples = pose.project(intr, x0 + np.linspace(t0, t1, steps)[:, None] * u)
            samples = samples[np.all(np.isfinite(samples), axis=1)]
            bnd_px = 0.5 * (px[:, [1, 0]] + px[:, [3, 2]]).astype(np.float64)  # (x, y)
            offset, _ = cKDTree(samples).query(bnd_px)
            if float(np.median(offset)) > p.wireframe_max_offset_px:
                continue
            code = a * n_lab + b + 1
            lines[crease == code] = False
            ij = np.round(samples[:, ::-1]).astype(np.int64)
            inside = (ij[:, 0] >= 0) & (ij[:, 0] < h) & (ij[:, 1] >= 0) & (ij[:, 1] < w)
            lines[ij[inside, 0], ij[inside, 1]] = True
            intersections.append((a, b, ends))
    return WireframeView(lines=lines, plane_labels=lab, intersections=intersections)


# ================================================================= matching
@dataclass
class ViewMatches:
    """HOG matches between two views (e.g. photo gradient ↔ reflectivity gradient).

    Attributes
    ----------
    points_a, points_b : (K, 2) float64 arrays
        Matched keypoint positions ``(x, y)`` in each image, pixels.
    n_keypoints_a, n_keypoints_b : int
        Keypoints described in each image (after the masks).
    """

    points_a: np.ndarray
    points_b: np.ndarray
    n_keypoints_a: int
    n_keypoints_b: int

    def __len__(self) -> int:
        return int(self.points_a.shape[0])


def describe_view(image: np.ndarray, mask: np.ndarray | None = None,
                  params: LidarViewParams | None = None) -> hog.HogFeatures:
    """SIFT keypoints of one view described by oriented multi-scale HOG, with the
    keypoint and HOG settings of ``params`` (so a photo's view can be described
    once and matched against every round's render, :func:`match_described`).

    Parameters
    ----------
    image : (H, W) uint8 array
        A gradient-magnitude or :func:`line_view` image.
    mask : (H, W) bool array, optional
        Where keypoints may be.
    params : LidarViewParams, optional

    Returns
    -------
    HogFeatures
    """
    return _describe(image, mask, params or LidarViewParams())


def match_described(fa: hog.HogFeatures, fb: hog.HogFeatures,
                    params: LidarViewParams | None = None) -> ViewMatches:
    """Ratio-test and mutual-best matching of two described views (see
    :func:`match_view_pair`, which describes and matches in one call)."""
    p = params or LidarViewParams()
    pairs = hog.match_hog(fa.descriptors, fb.descriptors, p.match_ratio, mutual=True)
    return ViewMatches(fa.points[pairs[:, 0]], fb.points[pairs[:, 1]], len(fa), len(fb))


def _describe(image: np.ndarray, mask: np.ndarray | None, p: LidarViewParams) -> hog.HogFeatures:
    return hog.detect_and_describe_hog(
        image, mask, max_keypoints=p.max_keypoints, contrast_threshold=p.sift_contrast_threshold,
        scales=p.hog_scales, patch_px=p.hog_patch_px, min_side_px=p.hog_min_patch_px,
        orientations=p.hog_orientations, cell_px=p.hog_cell_px, block_cells=p.hog_block_cells,
        upright=p.upright)


def match_view_pair(
    image_a: np.ndarray,
    image_b: np.ndarray,
    mask_a: np.ndarray | None = None,
    mask_b: np.ndarray | None = None,
    params: LidarViewParams | None = None,
) -> ViewMatches:
    """SIFT keypoints + oriented multi-scale HOG + ratio/mutual matching of two views.

    Parameters
    ----------
    image_a, image_b : (H, W) uint8 arrays
        E.g. the photo's gradient magnitude and the reflectivity view's, or
        :func:`line_view` of the photo's Canny edges and of the wireframe
        view's ``lines``.
    mask_a, mask_b : (H, W) bool arrays, optional
        Where keypoints may be (:func:`lsd_mask` for the photo,
        :func:`plane_mask` for a render).
    params : LidarViewParams, optional

    Returns
    -------
    ViewMatches
        Not yet verified geometrically: the DLT's RANSAC does that.
    """
    p = params or LidarViewParams()
    fa = _describe(image_a, mask_a, p)
    fb = _describe(image_b, mask_b, p)
    pairs = hog.match_hog(fa.descriptors, fb.descriptors, p.match_ratio, mutual=True)
    return ViewMatches(fa.points[pairs[:, 0]], fb.points[pairs[:, 1]], len(fa), len(fb))


def lift_to_3d(render, points: np.ndarray, depth_jump: float = 0.05
               ) -> tuple[np.ndarray, np.ndarray]:
    """The 3D points a render shows at pixels (its matched keypoints), for the DLT.

    Parameters
    ----------
    render : RenderResult
    points : (K, 2) array
        Pixels ``(x, y)`` in the render (pixel centres at integers).
    depth_jump : float
        A pixel whose 3 × 3 neighbourhood spans more than this fraction of
        its depth straddles an occluding contour: its 3D point could belong
        to either side, so it is not lifted.

    Returns
    -------
    xyz : (K, 3) float64 array
        World points, metres (NaN where not valid).
    valid : (K,) bool array
        Inside the image, on the surface and not on a depth discontinuity.
    """
    pts = np.asarray(points, np.float64).reshape(-1, 2)
    h, w = render.mask.shape
    col = np.round(pts[:, 0]).astype(np.int64)
    row = np.round(pts[:, 1]).astype(np.int64)
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    col, row = np.clip(col, 0, w - 1), np.clip(row, 0, h - 1)
    depth = np.where(render.mask, np.nan_to_num(np.asarray(render.depth, np.float32),
                                                nan=np.inf), np.inf).astype(np.float32)
    kernel = np.ones((3, 3), np.uint8)
    lo = cv2.erode(depth, kernel, borderType=cv2.BORDER_REPLICATE)
    hi = cv2.dilate(depth, kernel, borderType=cv2.BORDER_REPLICATE)
    with np.errstate(invalid="ignore"):
        steady = (hi - lo) <= depth_jump * lo
    xyz = np.asarray(render.xyz, np.float64)[row, col]
    valid = inside & np.asarray(render.mask, bool)[row, col] & steady[row, col] \
        & np.all(np.isfinite(xyz), axis=1)
    xyz[~valid] = np.nan
    return xyz, valid


@dataclass
class Seed003Correspondences:
    """Photo ↔ scan correspondences of seed 003's two view pairs, ready for the DLT.

    Attributes
    ----------
    points_2d : (K, 2) float64 array
        Photo pixels ``(x, y)`` (at the resolution of the photo given).
    points_3d : (K, 3) float64 array
        World points, metres, lifted through the render.
    source : (K,) array of str
        ``"reflectivity"`` or ``"wireframe"``: the pair each match came from.
    counts : dict
        Keypoints and matches of each pair (``reflectivity_keypoints_photo``,
        ``..._render``, ``reflectivity_matches``, ``reflectivity_lifted``,
        the same for ``wireframe``), for the report.
    wireframe : WireframeView
        The render's wireframe view (for display and the edge stages).
    points_render : (K, 2) float64 array
        The matched render pixels ``(x, y)`` the 3D points were lifted from.
    """

    points_2d: np.ndarray
    points_3d: np.ndarray
    source: np.ndarray
    counts: dict
    wireframe: WireframeView
    points_render: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))

    def __len__(self) -> int:
        return int(self.points_2d.shape[0])


def seed003_correspondences(
    photo: np.ndarray,
    render,
    planes,
    params: LidarViewParams | None = None,
    photo_mask: np.ndarray | None = None,
    pairs: tuple[str, ...] = ("reflectivity", "wireframe"),
) -> Seed003Correspondences:
    """One round of seed 003's matching: both view pairs, masks, HOG, lifting.

    The photo's gradient magnitude is matched with the render's reflectivity
    gradient, the photo's Canny edges with the wireframe view; photo
    keypoints only near LSD segments (and in ``photo_mask``), render
    keypoints only near segmented planes; render keypoints are lifted to 3D
    through its ``xyz``. The camera is then ``resection.dlt_ransac(points_3d,
    points_2d)`` (no assumption on the intrinsics).

    Parameters
    ----------
    photo : (H, W, 3) or (H, W) uint8 array
        At the render's resolution (photo and render are matched as images;
        their scales may differ, SIFT's scale invariance absorbs it).
    render : RenderResult
        The scan rendered from the prior (or the last estimate), intensity in ``rgb``.
    planes : PlaneSegmentation or (N,) int array
        :func:`segment_planes` of the scan (computed once per scan).
    params : LidarViewParams, optional
    photo_mask : (H, W) bool array, optional
        Photo pixels that may hold keypoints (e.g. not sky).
    pairs : tuple of str
        The view pairs to use: ``"reflectivity"``, ``"wireframe"`` or both
        (the seed's "All").

    Returns
    -------
    Seed003Correspondences
    """
    p = params or LidarViewParams()
    photo_imgs, mask_photo = photo_views(photo, p, photo_mask, pairs)
    render_imgs, mask_render, wire = render_views(render, planes, p, pairs)
    pts2, pts3, ptsr, src, counts = [], [], [], [], {}
    for name in photo_imgs:
        m = match_view_pair(photo_imgs[name], render_imgs[name], mask_photo, mask_render, p)
        xyz, ok = lift_to_3d(render, m.points_b, p.wireframe_depth_jump)
        pts2.append(m.points_a[ok])
        pts3.append(xyz[ok])
        ptsr.append(m.points_b[ok])
        src.append(np.full(int(ok.sum()), name))
        counts.update({f"{name}_keypoints_photo": m.n_keypoints_a,
                       f"{name}_keypoints_render": m.n_keypoints_b,
                       f"{name}_matches": len(m), f"{name}_lifted": int(ok.sum())})
    return Seed003Correspondences(
        points_2d=np.vstack(pts2) if pts2 else np.zeros((0, 2)),
        points_3d=np.vstack(pts3) if pts3 else np.zeros((0, 3)),
        source=np.concatenate(src) if src else np.zeros(0, str),
        counts=counts, wireframe=wire,
        points_render=np.vstack(ptsr) if ptsr else np.zeros((0, 2)))


def _check_pairs(pairs: tuple[str, ...]) -> None:
    unknown = set(pairs) - {"reflectivity", "wireframe"}
    if unknown or not pairs:
        raise ValueError(f"unknown view pair(s) {sorted(unknown)}; use 'reflectivity' and/or "
                         "'wireframe'")


def photo_views(
    photo: np.ndarray,
    params: LidarViewParams | None = None,
    photo_mask: np.ndarray | None = None,
    pairs: tuple[str, ...] = ("reflectivity", "wireframe"),
) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """The photo's side of seed 003's view pairs: its gradient magnitude
    (``"reflectivity"``) and its blurred Canny edges (``"wireframe"``), and
    where its keypoints may be (near LSD segments, inside ``photo_mask``).

    Parameters
    ----------
    photo : (H, W, 3) or (H, W) uint8 array
    params : LidarViewParams, optional
    photo_mask : (H, W) bool array, optional
    pairs : tuple of str

    Returns
    -------
    images : dict of str to (H, W) uint8 array
        One image per pair, in the order of ``pairs``.
    keypoint_mask : (H, W) bool array
    """
    p = params or LidarViewParams()
    _check_pairs(pairs)
    if p.use_lsd_mask:
        mask = lsd_mask(photo, p.lsd_radius_px, p.lsd_min_length_px)
    else:
        mask = np.ones(np.asarray(photo).shape[:2], bool)
    if photo_mask is not None:
        mask &= np.asarray(photo_mask, bool)
    images = {}
    for name in pairs:
        if name == "reflectivity":
            images[name] = gradient_magnitude(photo, p.gradient_sigma_px, photo_mask,
                                              p.gradient_percentile, p.gradient_gamma)
        else:
            edges = canny_edges(photo, p.canny_sigma_px, p.canny_high_percentile,
                                p.canny_low_ratio, photo_mask)
            images[name] = line_view(edges, p.line_blur_px)
    return images, mask


def render_views(
    render,
    planes,
    params: LidarViewParams | None = None,
    pairs: tuple[str, ...] = ("reflectivity", "wireframe"),
) -> tuple[dict[str, np.ndarray], np.ndarray, WireframeView]:
    """The scan's side of seed 003's view pairs: the reflectivity view's
    gradient magnitude and the wireframe view as a line image, and where the
    render's keypoints may be (near segmented planes).

    Parameters
    ----------
    render : RenderResult
    planes : PlaneSegmentation or (N,) int array
    params : LidarViewParams, optional
    pairs : tuple of str

    Returns
    -------
    images : dict of str to (H, W) uint8 array
    keypoint_mask : (H, W) bool array
    wireframe : WireframeView
    """
    p = params or LidarViewParams()
    _check_pairs(pairs)
    wire = wireframe_view(render, planes, p)
    images = {}
    for name in pairs:
        if name == "reflectivity":
            images[name] = reflectivity_gradient(render, p)
        else:
            images[name] = line_view(wire.lines, p.line_blur_px)
    if p.use_plane_mask:
        mask = plane_mask(wire.plane_labels, p.plane_mask_radius_px)
    else:  # anywhere on the surface
        mask = np.asarray(render.mask, bool)
    return images, mask, wire


@dataclass
class PhotoViewFeatures:
    """The photo's described views (:func:`describe_photo_views`): computed once
    per photo and matching width, matched against every round's render.

    Attributes
    ----------
    features : dict of str to HogFeatures
        One per view pair, in the order of ``pairs``.
    n_keypoints : int
        Keypoints over all pairs.
    shape : tuple of int
        ``(H, W)`` of the photo as described.
    """

    features: dict
    n_keypoints: int
    shape: tuple


def describe_photo_views(
    photo: np.ndarray,
    params: LidarViewParams | None = None,
    photo_mask: np.ndarray | None = None,
    pairs: tuple[str, ...] = ("reflectivity", "wireframe"),
) -> PhotoViewFeatures:
    """:func:`photo_views` of the photo, each described by :func:`describe_view`.

    Parameters
    ----------
    photo : (H, W, 3) or (H, W) uint8 array
        At the render's resolution.
    params : LidarViewParams, optional
    photo_mask : (H, W) bool array, optional
    pairs : tuple of str

    Returns
    -------
    PhotoViewFeatures
    """
    p = params or LidarViewParams()
    images, mask = photo_views(photo, p, photo_mask, pairs)
    feats = {name: describe_view(img, mask, p) for name, img in images.items()}
    return PhotoViewFeatures(feats, sum(len(f) for f in feats.values()),
                             tuple(np.asarray(photo).shape[:2]))


@dataclass
class RenderViewMatches:
    """HOG matches of the photo's views with one render's (:func:`match_render_views`).

    Attributes
    ----------
    photo_points, render_points : (M, 2) float64 arrays
        Matched pixels ``(x, y)`` at the render's resolution (the photo as
        described, at the same size).
    source : (M,) array of str
        The view pair of each match.
    n_keypoints_render : int
        The render's keypoints over all pairs.
    counts : dict
        ``<pair>_keypoints_photo``, ``<pair>_keypoints_render`` and
        ``<pair>_matches``.
    wireframe : WireframeView
    """

    photo_points: np.ndarray
    render_points: np.ndarray
    source: np.ndarray
    n_keypoints_render: int
    counts: dict
    wireframe: WireframeView

    def __len__(self) -> int:
        return int(self.photo_points.shape[0])


def match_render_views(
    photo_features: PhotoViewFeatures,
    render,
    planes,
    params: LidarViewParams | None = None,
) -> RenderViewMatches:
    """Match the photo's described views with a render's reflectivity and
    wireframe views (the pairs ``photo_features`` was described for).

    Parameters
    ----------
    photo_features : PhotoViewFeatures
        At the render's size.
    render : RenderResult
    planes : PlaneSegmentation or (N,) int array
    params : LidarViewParams, optional

    Returns
    -------
    RenderViewMatches
        Not yet checked geometrically nor lifted to 3D.
    """
    p = params or LidarViewParams()
    if tuple(photo_features.shape) != tuple(render.mask.shape):
        raise ValueError(f"the photo was described at {photo_features.shape} but the render is "
                         f"{render.mask.shape}")
    pairs = tuple(photo_features.features)
    images, mask, wire = render_views(render, planes, p, pairs)
    pa, pb, src, counts, n_render = [], [], [], {}, 0
    for name, img in images.items():
        fr = describe_view(img, mask, p)
        n_render += len(fr)
        m = match_described(photo_features.features[name], fr, p)
        pa.append(m.points_a)
        pb.append(m.points_b)
        src.append(np.full(len(m), name))
        counts.update({f"{name}_keypoints_photo": len(photo_features.features[name]),
                       f"{name}_keypoints_render": len(fr), f"{name}_matches": len(m)})
    return RenderViewMatches(
        photo_points=np.vstack(pa) if pa else np.zeros((0, 2)),
        render_points=np.vstack(pb) if pb else np.zeros((0, 2)),
        source=np.concatenate(src) if src else np.zeros(0, str),
        n_keypoints_render=n_render, counts=counts, wireframe=wire)


# ------------------------------------------------------------ plane cache
#: Plane segmentations per scene and plane settings (computed once per scan:
#: ~1 s per million points).
_PLANES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_PLANES_LOCK = threading.Lock()
_PLANE_FIELDS = ("plane_distance_m", "plane_normal_deg", "plane_min_points", "plane_max_planes",
                 "plane_hypotheses", "plane_sample_points", "plane_cell_m", "normal_neighbours")


def scene_planes(scene, params: LidarViewParams | None = None, seed: int = 0
                 ) -> PlaneSegmentation:
    """The scene's RANSAC planes, one label per element its renders' ``face_id`` names.

    For a point cloud: per point, with the cloud's cached PCA normals. For a
    mesh: per triangle, on the triangles' centroids and normals (a mesh
    render's ``face_id`` is the triangle). Cached on the scene (weakly) per
    plane settings.

    Parameters
    ----------
    scene : CloudScene or Scene
    params : LidarViewParams, optional
    seed : int

    Returns
    -------
    PlaneSegmentation
    """
    p = params or LidarViewParams()
    key = tuple(getattr(p, f) for f in _PLANE_FIELDS) + (int(seed),)
    with _PLANES_LOCK:
        cached = _PLANES.get(scene, {})
        if key in cached:
            return cached[key]
    if getattr(scene, "is_cloud", False):
        scene.build_engine()                      # the normals, computed once and cached
        pts, nrm = scene.xyz, scene.normals
    else:
        tri = scene.vertices[scene.faces]
        pts, nrm = tri.mean(axis=1), scene.face_array("normals")
    planes = segment_planes(pts, nrm, p, seed=seed)
    with _PLANES_LOCK:
        _PLANES.setdefault(scene, {})[key] = planes
    return planes


# ============================================ the keypoint rounds' extra pairs
# With RegistrationParams.lidar_views on and a point-cloud scene, every
# keypoint round (registration.round.match_round) also matches seed 003's two
# view pairs; those matches pass the round's own 2D check and join its
# keypoints before the pose (one set of correspondences, one pose, the same
# seven metrics). The photo's views are described once per photo and size
# (the context's ``lidar_cache``), the planes once per scan (scene_planes).


def check_matches(points_a: np.ndarray, points_b: np.ndarray, features: FeatureParams
                  ) -> np.ndarray:
    """The 2D check of photo ↔ render matches (``features.geometric_model``,
    MAGSAC++), with a homography where a fundamental matrix is not determined.

    From (nearly) the photo's own camera — the last rounds of an iteration —
    photo and render points coincide, every epipolar geometry fits them and
    the fundamental-matrix estimate fails (measured: 0 of 325 correct matches
    kept); the views are then related by a homography (nearly the identity),
    which is checked instead.

    Parameters
    ----------
    points_a, points_b : (M, 2) arrays
        Matched pixels of the two images.
    features : FeatureParams

    Returns
    -------
    (M,) bool array
    """
    inlier, model = verify_geometry(points_a, points_b, features)
    if model is None and features.geometric_model == "fundamental" and len(points_a) >= 4:
        inlier, _ = verify_geometry(points_a, points_b,
                                    replace(features, geometric_model="homography"))
    return inlier


@dataclass
class LidarStageMatches:
    """The lidar views' matches of one round.

    Attributes
    ----------
    photo_points, render_points : (M, 2) float64 arrays
        Pixels ``(x, y)`` at the render's resolution.
    inlier : (M,) bool array
        Passed the round's 2D check.
    source : (M,) array of str
        ``"reflectivity"`` or ``"wireframe"``.
    points_photo, points_render : int
        Keypoints of the photo's and the render's views.
    """

    photo_points: np.ndarray
    render_points: np.ndarray
    inlier: np.ndarray
    source: np.ndarray
    points_photo: int
    points_render: int

    def __len__(self) -> int:
        return int(self.photo_points.shape[0])


def lidar_view_matches(
    scene,
    photo_small: np.ndarray,
    rendered,
    params: LidarViewParams,
    features: FeatureParams,
    cache: dict | None = None,
) -> LidarStageMatches:
    """Match seed 003's view pairs of the photo and a render, checked in 2D.

    Parameters
    ----------
    scene : CloudScene
        The scan (its planes are segmented once and cached).
    photo_small : (h, w, 3) uint8 array
        The photo at the round's matching width (resized to the render's
        size if it differs by rounding).
    rendered : RenderResult
        The round's render.
    params : LidarViewParams
    features : FeatureParams
        The round's 2D check (``geometric_model``, ``geometric_threshold_px``).
    cache : dict, optional
        Keeps the photo's described views between rounds.

    Returns
    -------
    LidarStageMatches
    """
    h, w = rendered.mask.shape
    key = ("lidar_views", (h, w), repr(params))
    side = None if cache is None else cache.get(key)
    if side is None:
        photo = photo_small
        if photo.shape[:2] != (h, w):
            photo = cv2.resize(photo, (w, h), interpolation=cv2.INTER_AREA)
        side = describe_photo_views(photo, params)
        if cache is not None:
            cache[key] = side
    m = match_render_views(side, rendered, scene_planes(scene, params), params)
    inlier = check_matches(m.photo_points, m.render_points, features)
    return LidarStageMatches(m.photo_points, m.render_points, inlier, m.source,
                             side.n_keypoints, m.n_keypoints_render)

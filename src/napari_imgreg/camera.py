"""Pinhole cameras, poses and the geologist's attitude convention.

Conventions (public contract §1–§2):

* Camera frame: OpenCV, x right, y down, z forward (the view direction).
* A world point ``X`` maps to camera coordinates ``R @ X + t``; ``R`` is
  world-to-camera (``cam_from_world``); the camera centre is ``C = -R.T @ t``.
* Pixel centres are at integer coordinates; the first pixel's centre is (0, 0).
* Attitude: ``trend_deg`` is the azimuth of the view direction ξ (camera z),
  clockwise from north (+Y); ``plunge_deg`` is positive downward; ``roll_deg``
  turns the camera x axis (ρ) downward when positive.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, Mapping

import numpy as np

from .validate import MAX_IMAGE_SIDE_PX, FieldValueError, check_number

__all__ = [
    "Intrinsics",
    "Pose",
    "rotation_from_attitude",
    "attitude_from_rotation",
    "match_scale",
    "scaled_size",
    "pixels_to_full",
    "pixels_to_scaled",
    "SENSOR_WIDTHS_MM",
    "ESTIMABLE_FIELDS",
]

#: Focal length bounds per image side: fx ≥ this × width (a view under 170°).
MIN_FOCAL_PER_SIDE = 0.5 / math.tan(math.radians(85.0))
#: fx ≤ this × the longer side (a view of 0.006°, beyond any telephoto).
MAX_FOCAL_PER_SIDE = 10_000.0
#: Largest magnitude of a local-frame coordinate, metres (beyond the Earth).
MAX_COORDINATE_M = 1e8
#: Largest magnitude of a distortion coefficient (fisheye lenses stay below 10).
MAX_DISTORTION = 1000.0
#: The camera fields a registration may estimate (``Intrinsics.estimated``,
#: RESULT.json ``camera.estimated``).
ESTIMABLE_FIELDS = ("fx", "fy", "cx", "cy", "dist")

# Sensor widths (mm) of common field cameras, used when EXIF lacks both the
# 35 mm equivalent focal length and the focal-plane resolution.
SENSOR_WIDTHS_MM: dict[str, float] = {
    "FC6310": 13.2,  # DJI Phantom 4 Pro
    "FC6310S": 13.2,
    "FC330": 6.17,  # DJI Phantom 4
    "FC220": 6.17,  # DJI Mavic Pro
    "L1D-20C": 13.2,  # DJI Mavic 2 Pro (Hasselblad)
    "FC3170": 6.4,  # DJI Mavic Air 2
    "FC7303": 6.3,  # DJI Mini 2
    "Canon EOS 5D Mark III": 36.0,
    "Canon EOS 6D": 35.8,
    "NIKON D800": 35.9,
    "NIKON D7000": 23.6,
    "ILCE-7RM2": 35.9,  # Sony a7R II
}



def as_points(values, k: int, name: str = "points") -> np.ndarray:
    """``values`` as an (N, k) float array: one point (k,), N points (N, k), or a
    grid (..., k) flattened; anything else (a transposed (k, N) array, points
    of another dimension) is refused, not silently reshaped into other points.

    Raises
    ------
    ValueError
        The last axis is not of length ``k``.
    """
    a = np.asarray(values, dtype=np.float64)
    if a.size == 0:
        return a.reshape(0, k)
    if a.ndim == 0 or a.shape[-1] != k:
        raise ValueError(f"{name} must be ({k},) or (N, {k}), got shape {a.shape}")
    return a.reshape(-1, k)


def check_pose(pose: "Pose", what: str = "pose") -> None:
    """Refuse a pose that is not a camera: non-finite values, or an ``R`` that is
    not a rotation (a NaN pose makes the ray engine search for minutes and
    render nothing).

    Raises
    ------
    FieldValueError
    """
    if not (np.all(np.isfinite(pose.R)) and np.all(np.isfinite(pose.t))):
        raise FieldValueError(what, "has non-finite values (NaN or infinity)")
    R = pose.R
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-5) or np.linalg.det(R) <= 0:
        raise FieldValueError(f"{what}.R", "is not a rotation matrix (orthonormal, det +1)")

@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics with optional OpenCV distortion.

    Parameters
    ----------
    width, height : int
        Image size in pixels.
    fx, fy : float
        Focal lengths in pixels.
    cx, cy : float
        Principal point in pixels (pixel centres at integers).
    dist : tuple of float
        OpenCV distortion ``(k1, k2, p1, p2, k3)``; empty for none.
    estimated : tuple of str
        The fields (of :data:`ESTIMABLE_FIELDS`) that are not read from the
        photo's record or EXIF. Before registration: values assumed as a
        start, to be estimated (a record without a focal length gets
        ``("fx", "fy")`` at a 65° field of view); after: the values the
        registration estimated (RESULT.json ``camera.estimated``). Empty: all
        read (known).

    Raises
    ------
    FieldValueError
        (a ``ValueError``) when a value is not finite or out of its range:
        width and height whole numbers in [1, 65535]; fx at least
        0.044 × width and fy 0.044 × height (a view under 170°), at most
        10 000 × the longer side; cx in [−width, 2 width], cy likewise; at
        most 5 distortion coefficients, each within ±1000; ``estimated``
        names outside :data:`ESTIMABLE_FIELDS`. The message names the field
        (``field 'fx' ...``).
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, ...] = field(default_factory=tuple)
    estimated: tuple[str, ...] = field(default_factory=tuple)

    def __post_init__(self) -> None:
        # Checked here, where every camera is made (records, RESULT.json, the
        # GUI, scaling): a focal length of 0 or a NaN would otherwise hang the
        # ray caster or run a registration on nonsense.
        w = check_number(self.width, "width", 1, MAX_IMAGE_SIDE_PX, integer=True)
        h = check_number(self.height, "height", 1, MAX_IMAGE_SIDE_PX, integer=True)
        object.__setattr__(self, "width", w)
        object.__setattr__(self, "height", h)
        # A pinhole sees less than 180°: a focal length below ~1/23 of the
        # image side (a 170° view) is a wrong unit or a typo, as is one of
        # 10 000 image sides (a 0.006° view).
        for name, side in (("fx", w), ("fy", h)):
            value = getattr(self, name)
            if isinstance(value, (int, float)) and not isinstance(value, bool) and value <= 0:
                raise FieldValueError(
                    name, f"must be a positive focal length in pixels, got {value!r}")
            check_number(getattr(self, name), name, MIN_FOCAL_PER_SIDE * side,
                         MAX_FOCAL_PER_SIDE * max(w, h))
            object.__setattr__(self, name, float(getattr(self, name)))
        # The principal point may lie off the image (a crop), not far off.
        check_number(self.cx, "cx", -w, 2 * w)
        check_number(self.cy, "cy", -h, 2 * h)
        object.__setattr__(self, "cx", float(self.cx))
        object.__setattr__(self, "cy", float(self.cy))
        # Hashable and comparable whatever sequence the caller gave (a list
        # from JSON / to_dict): render caches rays per Intrinsics.
        if isinstance(self.dist, (str, bytes)) or not hasattr(self.dist, "__iter__"):
            raise FieldValueError("dist", f"must be a list of numbers, got {self.dist!r}")
        dist = tuple(self.dist)
        if len(dist) > 5:
            raise FieldValueError(
                "dist", f"has {len(dist)} coefficients; only OpenCV's (k1, k2, p1, p2, k3) "
                "are supported")
        object.__setattr__(self, "dist", tuple(
            float(check_number(k, "dist", -MAX_DISTORTION, MAX_DISTORTION)) for k in dist))
        if isinstance(self.estimated, (str, bytes)) or not hasattr(self.estimated, "__iter__"):
            raise FieldValueError("estimated", f"must be a list of camera field names, got "
                                               f"{self.estimated!r}")
        estimated = tuple(self.estimated)
        unknown = [e for e in estimated if e not in ESTIMABLE_FIELDS]
        if unknown:
            raise FieldValueError("estimated", f"names {unknown[0]!r}; only "
                                               f"{', '.join(ESTIMABLE_FIELDS)} can be estimated")
        # One order whatever the caller gave, so equal cameras compare equal.
        object.__setattr__(self, "estimated",
                           tuple(f for f in ESTIMABLE_FIELDS if f in estimated))

    # ------------------------------------------------------------------ build
    @classmethod
    def from_focal_length_mm(
        cls,
        width: int,
        height: int,
        focal_length_mm: float,
        sensor_width_mm: float,
        sensor_height_mm: float | None = None,
    ) -> Intrinsics:
        """Intrinsics from a focal length and the sensor size in millimetres.

        Square pixels are assumed when ``sensor_height_mm`` is not given; the
        principal point is the image centre.
        """
        if focal_length_mm <= 0 or sensor_width_mm <= 0:
            raise ValueError("focal length and sensor width must be positive")
        fx = focal_length_mm * width / sensor_width_mm
        fy = fx if sensor_height_mm is None else focal_length_mm * height / sensor_height_mm
        return cls(width, height, fx, fy, (width - 1) / 2.0, (height - 1) / 2.0)

    @classmethod
    def from_35mm_equivalent(cls, width: int, height: int, focal_35mm: float) -> Intrinsics:
        """Intrinsics from the 35 mm-equivalent focal length.

        The equivalent focal length refers to the 43.27 mm diagonal of a
        36 × 24 mm frame; it is applied to the image diagonal, which is how
        camera makers compute it for any aspect ratio.
        """
        if focal_35mm <= 0:
            raise ValueError("35 mm equivalent focal length must be positive")
        diag_px = math.hypot(width, height)
        f = focal_35mm * diag_px / math.hypot(36.0, 24.0)
        return cls(width, height, f, f, (width - 1) / 2.0, (height - 1) / 2.0)

    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float) -> Intrinsics:
        """Intrinsics from a horizontal field of view in degrees."""
        f = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        return cls(width, height, f, f, (width - 1) / 2.0, (height - 1) / 2.0)

    @classmethod
    def from_exif(cls, exif: Mapping[str, Any], width: int, height: int) -> Intrinsics:
        """Intrinsics from EXIF tags (names as PIL's ``ExifTags.TAGS``).

        Tried in order: ``FocalLength`` with ``FocalPlaneXResolution`` (the
        sensor's true pixel pitch), ``FocalLengthIn35mmFilm``, ``FocalLength``
        with the sensor width of the ``Model`` from :data:`SENSOR_WIDTHS_MM`.

        Raises
        ------
        ValueError
            If no combination of tags gives a focal length in pixels.
        """
        focal_mm = _as_float(exif.get("FocalLength"))
        xres = _as_float(exif.get("FocalPlaneXResolution"))
        unit = int(_as_float(exif.get("FocalPlaneResolutionUnit")) or 2)
        exif_width = _as_float(exif.get("ExifImageWidth")) or width
        if focal_mm and xres:
            unit_mm = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}.get(unit, 25.4)
            # FocalPlaneXResolution is pixels per unit of the full-size image.
            px_per_mm = xres / unit_mm * (width / exif_width)
            f = focal_mm * px_per_mm
            return cls(width, height, f, f, (width - 1) / 2.0, (height - 1) / 2.0)
        f35 = _as_float(exif.get("FocalLengthIn35mmFilm"))
        if f35:
            return cls.from_35mm_equivalent(width, height, f35)
        model = str(exif.get("Model", "")).strip().strip("\x00")
        if focal_mm and model in SENSOR_WIDTHS_MM:
            return cls.from_focal_length_mm(width, height, focal_mm, SENSOR_WIDTHS_MM[model])
        raise ValueError(
            "EXIF gives no usable focal length (need FocalLength with "
            "FocalPlaneXResolution or a known camera Model, or FocalLengthIn35mmFilm)"
        )

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Intrinsics:
        """Intrinsics from the contract's ``camera`` block (pixels or millimetres).

        Raises
        ------
        KeyError, ValueError
            If the block has neither pixel intrinsics nor a focal length and
            sensor width; :class:`~napari_imgreg.validate.FieldValueError`
            (a ``ValueError`` naming the field) when a value is not a finite
            number in its range (see the class).
        """
        width = check_number(d["width"], "width", 1, MAX_IMAGE_SIDE_PX, integer=True)
        height = check_number(d["height"], "height", 1, MAX_IMAGE_SIDE_PX, integer=True)

        def positive(key: str) -> float:
            return check_number(d[key], key, 0.0, math.inf, low_open=True)

        if "fx" in d:
            # The values go to __post_init__ as given, which checks them.
            fx = d["fx"]
            fy = d.get("fy", fx)
            cx = d.get("cx", (width - 1) / 2.0)
            cy = d.get("cy", (height - 1) / 2.0)
            intr = cls(width, height, fx, fy, cx, cy)
        elif "focal_length_mm" in d and "sensor_width_mm" in d:
            intr = cls.from_focal_length_mm(
                width,
                height,
                positive("focal_length_mm"),
                positive("sensor_width_mm"),
                positive("sensor_height_mm") if d.get("sensor_height_mm") else None,
            )
        elif "focal_length_35mm" in d:
            intr = cls.from_35mm_equivalent(width, height, positive("focal_length_35mm"))
        else:
            raise ValueError(
                "camera needs fx (pixels) or focal_length_mm with sensor_width_mm"
            )
        dist = d.get("dist")
        if dist:
            intr = replace(intr, dist=dist)
        estimated = d.get("estimated")
        if estimated:
            intr = replace(intr, estimated=estimated)
        return intr

    def to_dict(self) -> dict[str, Any]:
        """The contract's pixel ``camera`` block (with ``estimated`` when not empty)."""
        out = {
            "width": self.width,
            "height": self.height,
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
            "dist": list(self.dist),
        }
        if self.estimated:
            out["estimated"] = list(self.estimated)
        return out

    @property
    def focal_known(self) -> bool:
        """False when the focal length is an assumption or an estimate
        (``"fx"`` in :attr:`estimated`): the registration estimates it."""
        return "fx" not in self.estimated

    # --------------------------------------------------------------- derived
    @property
    def K(self) -> np.ndarray:
        """Camera matrix, shape (3, 3)."""
        return np.array(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]]
        )

    @property
    def dist_coeffs(self) -> np.ndarray:
        """Distortion as OpenCV wants it, shape (5,) (zeros when none)."""
        d = np.zeros(5)
        d[: len(self.dist)] = self.dist[:5]
        return d

    @property
    def has_distortion(self) -> bool:
        return any(abs(k) > 0 for k in self.dist)

    @property
    def hfov_deg(self) -> float:
        """Horizontal field of view in degrees."""
        return math.degrees(2 * math.atan2(self.width / 2.0, self.fx))

    def scaled(self, scale: float) -> Intrinsics:
        """The same camera at ``scale`` times the resolution.

        Pixel centres stay at integers: a pixel at ``p`` maps to
        ``(p + 0.5) * scale - 0.5``.
        """
        check_number(scale, "scale", 0.0, math.inf, low_open=True)
        if scale == 1.0:
            return self
        w, h = scaled_size(self.width, self.height, scale)
        # Per axis from the rounded size, so the scaled camera fits its image exactly.
        sx, sy = w / self.width, h / self.height
        return Intrinsics(
            w,
            h,
            self.fx * sx,
            self.fy * sy,
            pixels_to_scaled(self.cx, sx),
            pixels_to_scaled(self.cy, sy),
            self.dist,
            self.estimated,
        )

    def rotated(self, quarter_turns: int) -> Intrinsics:
        """The same camera with its image turned by quarter turns, as an EXIF
        orientation turns a photo for display.

        Parameters
        ----------
        quarter_turns : int
            +1: the image turned 90° clockwise (EXIF orientation 6); -1: 90°
            anticlockwise (orientation 8); 2: half a turn (orientation 3).

        Returns
        -------
        Intrinsics
            Of the turned image: width and height, focal lengths and the
            principal point exchanged as the pixels are, the tangential
            distortion turned with them (radial terms do not change).
            :meth:`Pose.rotated` turns the pose to match.
        """
        q = quarter_turns % 4
        if q == 0:
            return self
        d = self.dist_coeffs
        k1, k2, p1, p2, k3 = d
        w, h = self.width, self.height
        if q == 1:  # (u, v) -> (h - 1 - v, u)
            out = Intrinsics(h, w, self.fy, self.fx, h - 1 - self.cy, self.cx,
                             (k1, k2, p2, -p1, k3))
        elif q == 3:  # (u, v) -> (v, w - 1 - u)
            out = Intrinsics(h, w, self.fy, self.fx, self.cy, w - 1 - self.cx,
                             (k1, k2, -p2, p1, k3))
        else:  # (u, v) -> (w - 1 - u, h - 1 - v)
            out = Intrinsics(w, h, self.fx, self.fy, w - 1 - self.cx, h - 1 - self.cy,
                             (k1, k2, -p1, -p2, k3))
        out = replace(out, estimated=self.estimated)
        return out if self.dist else replace(out, dist=())

    # ------------------------------------------------------ project/unproject
    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Project camera-frame points to pixels (with distortion).

        Parameters
        ----------
        points_cam : (N, 3) array
            Points in the camera frame, metres.

        Returns
        -------
        (N, 2) array
            Pixel coordinates (x = column, y = row); NaN for points with z <= 0.
        """
        p = as_points(points_cam, 3, "points_cam")
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xn = p[:, 0] / z
            yn = p[:, 1] / z
        if self.has_distortion:
            xn, yn = _distort(xn, yn, self.dist_coeffs)
        uv = np.stack([self.fx * xn + self.cx, self.fy * yn + self.cy], axis=1)
        uv[z <= 0] = np.nan
        return uv

    def normalized_rays(self, pixels: np.ndarray) -> np.ndarray:
        """Undistorted camera-frame ray directions through pixels.

        Parameters
        ----------
        pixels : (N, 2) array
            Pixel coordinates (x, y).

        Returns
        -------
        (N, 3) array
            Directions with z = 1 (not unit length).
        """
        px = as_points(pixels, 2, "pixels")
        if self.has_distortion:
            import cv2

            und = cv2.undistortPoints(
                px.reshape(-1, 1, 2), self.K, self.dist_coeffs
            ).reshape(-1, 2)
            # OpenCV stops after 5 fixed-point iterations (~0.3 px off for
            # wide-angle lenses): polish with Newton steps on _distort.
            xd = (px[:, 0] - self.cx) / self.fx
            yd = (px[:, 1] - self.cy) / self.fy
            xn, yn = _newton_undistort(und[:, 0], und[:, 1], xd, yd, self.dist_coeffs)
        else:
            xn = (px[:, 0] - self.cx) / self.fx
            yn = (px[:, 1] - self.cy) / self.fy
        return np.stack([xn, yn, np.ones_like(xn)], axis=1)

    def unproject(self, pixels: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Camera-frame points at the given z-depths behind pixels.

        Parameters
        ----------
        pixels : (N, 2) array
            Pixel coordinates (x, y).
        depth : (N,) array
            Depth along the optical axis (camera z), metres.

        Returns
        -------
        (N, 3) array
            Camera-frame points.
        """
        return self.normalized_rays(pixels) * np.asarray(depth, dtype=np.float64).reshape(-1, 1)


# --------------------------------------------------------- reduced resolution
# Matching, previews and the coarse-to-fine stages work on reduced copies of
# a photo. The convention is that of :meth:`Intrinsics.scaled`: pixel (0, 0) is
# the *centre* of the first pixel, so an image ``w`` pixels wide spans x in
# [-0.5, w - 0.5], and a reduction scales the pixel edges, not the centres.
def match_scale(width_px: int, match_width_px: float) -> float:
    """The factor that reduces an image to a working width, never enlarging it.

    Parameters
    ----------
    width_px : int
        Width of the full-resolution image, pixels.
    match_width_px : float
        The working width, pixels (e.g. ``RegistrationParams.match_width``).

    Returns
    -------
    float
        ``min(1, match_width_px / width_px)``: reduced size over full size.

    Examples
    --------
    >>> match_scale(2000, 500)
    0.25
    >>> match_scale(800, 1024)  # a narrower image is used as it is
    1.0
    """
    return min(1.0, match_width_px / width_px)


def scaled_size(width_px: int, height_px: int, scale: float) -> tuple[int, int]:
    """Size of an image reduced by ``scale``: that of :meth:`Intrinsics.scaled`.

    Parameters
    ----------
    width_px, height_px : int
        Full-resolution size, pixels.
    scale : float
        Reduced size over full size (:func:`match_scale`).

    Returns
    -------
    (int, int)
        ``(width, height)`` in pixels, each rounded and at least 1.

    Examples
    --------
    >>> scaled_size(1632, 1224, 0.5)
    (816, 612)
    """
    return max(1, int(round(width_px * scale))), max(1, int(round(height_px * scale)))


def pixels_to_full(points, scale: float):
    """Pixel coordinates in an image reduced by ``scale``, at full resolution.

    Pixel (0, 0) is the centre of the first pixel; the reduction scales the
    pixel edges, so ``p_full = (p + 0.5) / scale - 0.5``. The inverse of
    :func:`pixels_to_scaled`.

    Parameters
    ----------
    points : float or (..., 2) array
        Pixel coordinates (x, y) in the reduced image.
    scale : float
        Reduced size over full size.

    Returns
    -------
    float or (..., 2) array
        Full-resolution pixel coordinates; an array keeps its float dtype.

    Examples
    --------
    >>> pixels_to_full(0.0, 0.5)  # the first reduced pixel covers full pixels 0 and 1
    0.5
    >>> pixels_to_full(-0.5, 0.25)  # the image's left edge stays the left edge
    -0.5
    """
    return (points + 0.5) / scale - 0.5


def pixels_to_scaled(points, scale: float):
    """Full-resolution pixel coordinates in an image reduced by ``scale``.

    ``p_scaled = (p + 0.5) * scale - 0.5`` (pixel (0, 0) is the centre of the
    first pixel); the inverse of :func:`pixels_to_full`.

    Parameters
    ----------
    points : float or (..., 2) array
        Pixel coordinates (x, y) at full resolution.
    scale : float
        Reduced size over full size.

    Returns
    -------
    float or (..., 2) array

    Examples
    --------
    >>> pixels_to_scaled(1.5, 0.5)  # the edge between reduced pixels 0 and 1
    0.5
    """
    return (points + 0.5) * scale - 0.5


def _distort(xn: np.ndarray, yn: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Apply the OpenCV radial-tangential model to normalised coordinates."""
    k1, k2, p1, p2, k3 = d[:5]
    r2 = xn * xn + yn * yn
    radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
    xd = xn * radial + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn)
    yd = yn * radial + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn
    return xd, yd


def _newton_undistort(x, y, xd, yd, d, iterations: int = 2):
    """Refine normalised (x, y) so that _distort(x, y) == (xd, yd)."""
    k1, k2, p1, p2, k3 = d[:5]
    x = np.array(x, dtype=np.float64)
    y = np.array(y, dtype=np.float64)
    for _ in range(iterations):
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
        drad = k1 + 2 * k2 * r2 + 3 * k3 * r2 * r2
        fx, fy = _distort(x, y, d)
        fx = fx - xd
        fy = fy - yd
        a = radial + 2 * x * x * drad + 2 * p1 * y + 6 * p2 * x
        b = 2 * x * y * drad + 2 * p1 * x + 2 * p2 * y
        c = radial + 2 * y * y * drad + 6 * p1 * y + 2 * p2 * x
        det = a * c - b * b
        ok = np.abs(det) > 1e-12
        det = np.where(ok, det, 1.0)
        x = x - np.where(ok, (c * fx - b * fy) / det, 0.0)
        y = y - np.where(ok, (a * fy - b * fx) / det, 0.0)
    return x, y


def _as_float(value: Any) -> float | None:
    """EXIF rationals, tuples and strings to float (None when absent/invalid)."""
    if value is None:
        return None
    try:
        if isinstance(value, tuple) and len(value) == 2:
            v = float(value[0]) / float(value[1]) if float(value[1]) else None
        else:
            v = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return v if v is not None and math.isfinite(v) else None


# ---------------------------------------------------------------- attitude
def rotation_from_attitude(trend_deg: float, plunge_deg: float, roll_deg: float) -> np.ndarray:
    """World-to-camera rotation from trend, plunge and roll (contract §2).

    Parameters
    ----------
    trend_deg : float
        Azimuth of the view direction, degrees clockwise from north (+Y).
    plunge_deg : float
        Angle of the view direction below the horizontal, positive down.
    roll_deg : float
        Rotation about the view direction; positive turns the camera x axis
        downward (clockwise as the photographer sees it).

    Returns
    -------
    (3, 3) array
        ``R`` whose rows are the camera x, y, z axes in world coordinates.

    Examples
    --------
    >>> R = rotation_from_attitude(90.0, 0.0, 0.0)   # looking east
    >>> np.round(R[2], 6).tolist()
    [1.0, 0.0, -0.0]
    """
    T, P, Ro = (math.radians(a) for a in (trend_deg, plunge_deg, roll_deg))
    z = np.array([math.sin(T) * math.cos(P), math.cos(T) * math.cos(P), -math.sin(P)])
    x0 = np.array([math.cos(T), -math.sin(T), 0.0])
    y0 = np.cross(z, x0)
    x = math.cos(Ro) * x0 + math.sin(Ro) * y0
    y = np.cross(z, x)
    return np.stack([x, y, z])


def attitude_from_rotation(R: np.ndarray) -> tuple[float, float, float]:
    """Trend, plunge and roll in degrees from a world-to-camera rotation.

    The inverse of :func:`rotation_from_attitude`. For a vertical view
    (plunge ±90°) the trend is that of the roll-0 x axis, so roll is 0.

    Parameters
    ----------
    R : (3, 3) array
        World-to-camera rotation (rows: camera axes in world coordinates).

    Returns
    -------
    trend_deg, plunge_deg, roll_deg : float
        Trend in [0, 360), plunge in [-90, 90], roll in (-180, 180].
    """
    R = np.asarray(R, dtype=np.float64)
    x, z = R[0], R[2]
    plunge = math.degrees(math.asin(float(np.clip(-z[2], -1.0, 1.0))))
    horizontal = math.hypot(z[0], z[1])
    if horizontal < 1e-9:
        # Vertical view: x0 is undefined from ξ; take the trend for which x is x0.
        trend = math.degrees(math.atan2(-x[1], x[0])) % 360.0
        return _wrap360(trend), float(np.sign(-z[2]) * 90.0), 0.0
    trend = _wrap360(math.degrees(math.atan2(z[0], z[1])))
    T = math.radians(trend)
    x0 = np.array([math.cos(T), -math.sin(T), 0.0])
    y0 = np.cross(z, x0)
    roll = math.degrees(math.atan2(float(x @ y0), float(x @ x0)))
    if roll <= -180.0:  # keep the documented range (-180, 180]
        roll += 360.0
    return trend, plunge, roll


def _wrap360(angle_deg: float) -> float:
    a = angle_deg % 360.0
    return 0.0 if a >= 360.0 - 1e-12 else a


# --------------------------------------------------------------------- pose
@dataclass(frozen=True)
class Pose:
    """A camera pose as ``cam_from_world``: ``X_cam = R @ X_world + t``.

    Parameters
    ----------
    R : (3, 3) array
        World-to-camera rotation.
    t : (3,) array
        Translation, metres.
    """

    R: np.ndarray
    t: np.ndarray

    def __post_init__(self) -> None:
        R = np.asarray(self.R, dtype=np.float64).reshape(3, 3)
        t = np.asarray(self.t, dtype=np.float64).reshape(3)
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)

    @classmethod
    def from_center(cls, R: np.ndarray, center: np.ndarray) -> Pose:
        """Pose from a rotation and the camera centre in world coordinates."""
        R = np.asarray(R, dtype=np.float64)
        return cls(R, -R @ np.asarray(center, dtype=np.float64))

    @classmethod
    def from_attitude(
        cls, trend_deg: float, plunge_deg: float, roll_deg: float, center: np.ndarray
    ) -> Pose:
        """Pose from trend/plunge/roll (contract §2) and the camera centre."""
        return cls.from_center(rotation_from_attitude(trend_deg, plunge_deg, roll_deg), center)

    @classmethod
    def from_rvec_tvec(cls, rvec: np.ndarray, tvec: np.ndarray) -> Pose:
        """Pose from OpenCV's Rodrigues vector and translation."""
        import cv2

        R, _ = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))
        return cls(R, np.asarray(tvec, dtype=np.float64).reshape(3))

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Pose:
        """Pose from the contract's ``pose`` block (``R`` and ``t``).

        Raises
        ------
        KeyError
            ``R`` or ``t`` missing.
        FieldValueError
            (a ``ValueError``) ``R`` is not a finite 3 × 3 rotation matrix
            (orthonormal to 1e-4, determinant +1), or ``t`` not 3 finite
            numbers of at most 1e8 m.
        """
        try:
            R = np.array(d["R"], dtype=np.float64)
        except (TypeError, ValueError, OverflowError):
            raise FieldValueError("R", "must be 3 rows of 3 numbers") from None
        try:
            t = np.array(d["t"], dtype=np.float64)
        except (TypeError, ValueError, OverflowError):
            raise FieldValueError("t", "must be 3 numbers") from None
        if R.shape != (3, 3) or not np.isfinite(R).all():
            raise FieldValueError("R", "must be 3 rows of 3 finite numbers")
        if not (np.allclose(R @ R.T, np.eye(3), atol=1e-4) and np.linalg.det(R) > 0):
            raise FieldValueError("R", "is not a rotation matrix (orthonormal, determinant +1)")
        if t.shape != (3,) or not np.isfinite(t).all() or np.abs(t).max() > MAX_COORDINATE_M:
            raise FieldValueError("t", f"must be 3 finite numbers within ±{MAX_COORDINATE_M:g} m, "
                                  f"got {np.asarray(d['t']).tolist()!r}")
        return cls(R, t)

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates, shape (3,)."""
        return -self.R.T @ self.t

    @property
    def view_direction(self) -> np.ndarray:
        """Unit view direction ξ (camera z) in world coordinates, shape (3,)."""
        return self.R[2].copy()

    @property
    def attitude(self) -> tuple[float, float, float]:
        """(trend_deg, plunge_deg, roll_deg)."""
        return attitude_from_rotation(self.R)

    @property
    def rvec(self) -> np.ndarray:
        """Rodrigues rotation vector, shape (3,)."""
        import cv2

        return cv2.Rodrigues(self.R)[0].ravel()

    @property
    def matrix(self) -> np.ndarray:
        """4 × 4 ``cam_from_world`` matrix."""
        M = np.eye(4)
        M[:3, :3] = self.R
        M[:3, 3] = self.t
        return M

    def transform(self, points_world: np.ndarray) -> np.ndarray:
        """World points (N, 3) to camera coordinates (N, 3)."""
        p = as_points(points_world, 3, "points_world")
        return p @ self.R.T + self.t

    def inverse_transform(self, points_cam: np.ndarray) -> np.ndarray:
        """Camera points (N, 3) to world coordinates (N, 3)."""
        p = as_points(points_cam, 3, "points_cam")
        return (p - self.t) @ self.R

    def project(self, intrinsics: Intrinsics, points_world: np.ndarray) -> np.ndarray:
        """World points (N, 3) to pixels (N, 2); NaN behind the camera."""
        return intrinsics.project(self.transform(points_world))

    def rays(self, intrinsics: Intrinsics, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World rays through pixels.

        Returns
        -------
        origin : (3,) array
            The camera centre.
        directions : (N, 3) array
            Unit directions in world coordinates.
        """
        d = intrinsics.normalized_rays(pixels) @ self.R
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return self.center, d

    def rotated(self, quarter_turns: int) -> Pose:
        """The pose of the same camera with its image turned by quarter turns
        (see :meth:`Intrinsics.rotated`): the centre stays, the camera turns
        about its view direction (+1, image turned clockwise: roll − 90°)."""
        q = quarter_turns % 4
        Q = {0: np.eye(3),
             1: np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
             2: np.diag([-1.0, -1.0, 1.0]),
             3: np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])}[q]
        return Pose(Q @ self.R, Q @ self.t)

    def with_center(self, center: np.ndarray) -> Pose:
        return Pose.from_center(self.R, center)

    def to_dict(self) -> dict[str, Any]:
        """The contract's ``pose`` block."""
        trend, plunge, roll = self.attitude
        return {
            "R": self.R.tolist(),
            "t": self.t.tolist(),
            "position": self.center.tolist(),
            "trend_deg": trend,
            "plunge_deg": plunge,
            "roll_deg": roll,
        }

    def rotation_error_deg(self, other: Pose) -> float:
        """Angle of the relative rotation between two poses, degrees."""
        c = (np.trace(self.R @ other.R.T) - 1.0) / 2.0
        return math.degrees(math.acos(float(np.clip(c, -1.0, 1.0))))

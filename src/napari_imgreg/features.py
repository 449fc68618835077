"""Keypoints, descriptors and matches between a photo and a render.

Detection and description are separate choices, as in Kehl et al. (2018):
"FAST–SIFT" detects with FAST and describes with SIFT. OpenCV's MSER applied
to a colour image runs Forssén's *maximally stable colour regions* (MSCR), so
``"MSCR"`` is MSER on RGB and ``"MSER"`` on grey.

Matching is a k-nearest-neighbour search with Lowe's ratio test and a
symmetry (mutual best) check; the survivors are verified geometrically with a
fundamental matrix or homography by OpenCV's USAC (MAGSAC++). What survives
are the *feature inliers* of the quality metrics.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace

import cv2
import numpy as np

__all__ = [
    "FeatureParams",
    "Features",
    "Matches",
    "DETECTORS",
    "DESCRIPTORS",
    "PRESETS",
    "preset",
    "available",
    "detect_and_describe",
    "match_features",
]

#: Detectors, each with the OpenCV factory and its default threshold; the
#: threshold is scaled by ``FeatureParams.threshold_scale``.
DETECTORS = ("SIFT", "FAST", "AGAST", "ORB", "AKAZE", "BRISK", "KAZE", "MSER", "MSCR")
#: Descriptors; binary ones are matched with Hamming distance.
DESCRIPTORS = ("SIFT", "ORB", "AKAZE", "BRISK", "KAZE")
_BINARY = {"ORB", "AKAZE", "BRISK"}
_FACTORY = {
    "SIFT": "SIFT_create",
    "FAST": "FastFeatureDetector_create",
    "AGAST": "AgastFeatureDetector_create",
    "ORB": "ORB_create",
    "AKAZE": "AKAZE_create",
    "BRISK": "BRISK_create",
    "KAZE": "KAZE_create",
    "MSER": "MSER_create",
    "MSCR": "MSER_create",
}


@dataclass
class FeatureParams:
    """Detection, description, matching and verification settings.

    Attributes
    ----------
    detector, descriptor : str
        From :data:`DETECTORS` and :data:`DESCRIPTORS`. AKAZE descriptors
        need AKAZE keypoints.
    max_features : int
        Keypoints kept per image after even selection (500–50 000).
    threshold_scale : float
        Multiplies the detector's default threshold; < 1 finds more, weaker
        points (0.05–4).
    grid : tuple of int
        (columns, rows) of the cells for spatially even selection: each cell
        keeps its strongest ``max_features / cells`` points.
    ratio : float
        Lowe's ratio test (0.5–0.95): a match is kept when its distance is
        below ``ratio`` times the second best.
    symmetric : bool
        Keep only mutual best matches.
    geometric_model : {"fundamental", "homography", "none"}
        Model for the USAC verification of the matches.
    geometric_threshold_px : float
        USAC inlier threshold, pixels at the matching resolution (0.5–20).
    """

    detector: str = "SIFT"
    descriptor: str = "SIFT"
    max_features: int = 8000
    threshold_scale: float = 1.0
    grid: tuple[int, int] = (8, 6)
    ratio: float = 0.8
    symmetric: bool = True
    geometric_model: str = "fundamental"
    geometric_threshold_px: float = 3.0

    def __post_init__(self) -> None:
        self.detector = self.detector.upper()
        self.descriptor = self.descriptor.upper()
        self.grid = tuple(int(g) for g in self.grid)  # type: ignore[assignment]
        if self.detector not in DETECTORS:
            raise ValueError(f"unknown detector {self.detector!r}; choose from {DETECTORS}")
        if self.descriptor not in DESCRIPTORS:
            raise ValueError(f"unknown descriptor {self.descriptor!r}; choose from {DESCRIPTORS}")
        if self.descriptor == "AKAZE" and self.detector != "AKAZE":
            raise ValueError("AKAZE descriptors need AKAZE keypoints")
        if self.geometric_model not in ("fundamental", "homography", "none"):
            raise ValueError("geometric_model must be 'fundamental', 'homography' or 'none'")

    @property
    def name(self) -> str:
        """E.g. ``"FAST–SIFT"`` (detection–description)."""
        return f"{self.detector}–{self.descriptor}"

    def to_dict(self) -> dict:
        d = asdict(self)
        d["grid"] = list(self.grid)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> FeatureParams:
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise KeyError(f"unknown feature parameter(s): {', '.join(sorted(unknown))}")
        return cls(**d)


#: Named presets: the paper's combinations.
PRESETS: dict[str, FeatureParams] = {
    "SIFT": FeatureParams("SIFT", "SIFT"),
    "FAST-SIFT": FeatureParams("FAST", "SIFT", threshold_scale=1.0),
    "MSCR-SIFT": FeatureParams("MSCR", "SIFT", max_features=4000),
    "ORB": FeatureParams("ORB", "ORB", ratio=0.8),
    "AKAZE": FeatureParams("AKAZE", "AKAZE"),
    "BRISK": FeatureParams("BRISK", "BRISK"),
    "KAZE": FeatureParams("KAZE", "KAZE"),
}


def preset(name: str) -> FeatureParams:
    """A copy of a named preset (case-insensitive, ``–`` or ``-``)."""
    key = name.upper().replace("–", "-")
    if key not in PRESETS:
        raise KeyError(f"unknown preset {name!r}; choose from {', '.join(PRESETS)}")
    return replace(PRESETS[key])


def available(name: str) -> bool:
    """Whether this OpenCV build has the detector/descriptor ``name``."""
    return hasattr(cv2, _FACTORY.get(name.upper(), ""))


def _require(name: str):
    factory = getattr(cv2, _FACTORY[name], None)
    if factory is None:
        raise RuntimeError(
            f"{name} is not in this OpenCV build ({cv2.__version__}); "
            "OpenCV 5 moved it to opencv-contrib-python-headless — install "
            "opencv-python-headless<5 (napari-imgreg's requirement)"
        )
    return factory


def _detector(name: str, scale: float, n: int):
    f = _require(name)
    if name == "SIFT":
        return f(nfeatures=0, contrastThreshold=0.04 * scale)
    if name == "FAST":
        return f(threshold=max(1, int(round(20 * scale))), nonmaxSuppression=True)
    if name == "AGAST":
        return f(threshold=max(1, int(round(10 * scale))), nonmaxSuppression=True)
    if name == "ORB":
        return f(nfeatures=max(n * 2, 500), fastThreshold=max(1, int(round(20 * scale))))
    if name == "AKAZE":
        return f(threshold=0.001 * scale)
    if name == "BRISK":
        return f(thresh=max(1, int(round(30 * scale))))
    if name == "KAZE":
        return f(threshold=0.001 * scale)
    # MSER/MSCR: a lower delta finds more regions.
    return f(delta=max(1, int(round(5 * scale))))


def _descriptor(name: str):
    f = _require(name)
    return f()


@dataclass
class Features:
    """Keypoints and descriptors of one image.

    Attributes
    ----------
    points : (N, 2) float32 array
        Pixel positions (x, y) at full resolution.
    descriptors : (N, D) array
        float32 (SIFT, KAZE) or uint8 (binary descriptors).
    sizes, responses : (N,) float32 arrays
    n_detected : int
        Keypoints found before the even selection.
    """

    points: np.ndarray
    descriptors: np.ndarray
    sizes: np.ndarray
    responses: np.ndarray
    n_detected: int

    def __len__(self) -> int:
        return len(self.points)


def _even_selection(
    points: np.ndarray, responses: np.ndarray, n_max: int, grid: tuple[int, int],
    shape: tuple[int, int],
) -> np.ndarray:
    """Indices of the strongest keypoints per grid cell, so points cover the image."""
    n = len(points)
    if n <= n_max:
        return np.arange(n)
    h, w = shape
    cols, rows = grid
    cell = (np.minimum((points[:, 1] * rows / h).astype(int), rows - 1) * cols
            + np.minimum((points[:, 0] * cols / w).astype(int), cols - 1))
    order = np.lexsort((-responses, cell))  # by cell, strongest first
    cell_sorted = cell[order]
    starts = np.searchsorted(cell_sorted, cell_sorted, side="left")
    rank = np.arange(n) - starts
    per_cell = max(1, n_max // (cols * rows))
    # Each cell keeps at most its share; if that is still more than n_max (a
    # grid finer than n_max cells) the strongest win, so exactly n_max remain.
    first = order[rank < per_cell]
    first = first[np.argsort(-responses[first], kind="stable")][:n_max]
    if len(first) < n_max:  # cells with few points leave room: fill by strength
        rest = np.setdiff1d(np.arange(n), first)
        rest = rest[np.argsort(-responses[rest], kind="stable")][: n_max - len(first)]
        first = np.concatenate([first, rest])
    return np.sort(first)


def detect_and_describe(
    gray: np.ndarray,
    params: FeatureParams,
    mask: np.ndarray | None = None,
    color: np.ndarray | None = None,
) -> Features:
    """Detect keypoints, select them evenly and describe them.

    Parameters
    ----------
    gray : (H, W) uint8 array
        The filtered image.
    params : FeatureParams
    mask : (H, W) bool array, optional
        Where to detect (e.g. the render's surface, eroded from its rim).
    color : (H, W, 3) uint8 array, optional
        Colour image for MSCR (MSER on colour); grey is used otherwise.

    Returns
    -------
    Features
    """
    m = None if mask is None else mask.astype(np.uint8) * 255
    det_name = params.detector
    detector = _detector(det_name, params.threshold_scale, params.max_features)
    same = params.descriptor == det_name
    if same:
        # One scale-space pyramid for both steps; select descriptor rows after.
        kps, desc = detector.detectAndCompute(gray, m)
        kps = list(kps)
        if desc is None:
            kps = []
    elif det_name in ("MSER", "MSCR"):
        source = color if (det_name == "MSCR" and color is not None) else gray
        kps = list(detector.detect(source, m))
        for k in kps:  # MSER gives no response; prefer larger regions
            k.response = k.size
    else:
        kps = list(detector.detect(gray, m))
    n_detected = len(kps)
    if kps:
        pts = np.array([k.pt for k in kps], np.float32)
        resp = np.array([k.response for k in kps], np.float32)
        keep = _even_selection(pts, resp, params.max_features, params.grid, gray.shape)
        kps = [kps[i] for i in keep]
        if same:
            desc = desc[keep]
    if kps and not same:
        if params.descriptor == "SIFT":
            for k in kps:  # detectors such as FAST give tiny sizes; SIFT needs a scale
                if k.size < 7:
                    k.size = 7.0
        kps, desc = _descriptor(params.descriptor).compute(gray, kps)
    if not kps or desc is None:
        dtype = np.uint8 if params.descriptor in _BINARY else np.float32
        return Features(np.zeros((0, 2), np.float32), np.zeros((0, 32), dtype),
                        np.zeros(0, np.float32), np.zeros(0, np.float32), n_detected)
    return Features(
        np.array([k.pt for k in kps], np.float32),
        desc,
        np.array([k.size for k in kps], np.float32),
        np.array([k.response for k in kps], np.float32),
        n_detected,
    )


@dataclass
class Matches:
    """Correspondences between two images.

    Attributes
    ----------
    idx_a, idx_b : (M,) int arrays
        Indices into the two :class:`Features` of the putative matches (after
        the ratio and symmetry tests).
    inlier : (M,) bool array
        Survivors of the geometric verification (the *feature inliers*).
    model : (3, 3) array or None
        The fundamental matrix or homography found.
    """

    idx_a: np.ndarray
    idx_b: np.ndarray
    inlier: np.ndarray
    model: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.idx_a)

    @property
    def n_inliers(self) -> int:
        return int(self.inlier.sum())


def _knn(desc_q: np.ndarray, desc_t: np.ndarray, binary: bool) -> list:
    if binary:
        matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    else:
        matcher = cv2.FlannBasedMatcher({"algorithm": 1, "trees": 4}, {"checks": 64})
    return matcher.knnMatch(desc_q, desc_t, k=2)


def _ratio_best(knn: list, ratio: float, n_query: int) -> np.ndarray:
    """Best train index per query (−1 when the ratio test fails)."""
    best = np.full(n_query, -1, np.int64)
    for pair in knn:
        if len(pair) == 2:
            m, n = pair
            if m.distance < ratio * n.distance:
                best[m.queryIdx] = m.trainIdx
        elif len(pair) == 1:
            best[pair[0].queryIdx] = pair[0].trainIdx
    return best


def match_features(a: Features, b: Features, params: FeatureParams) -> Matches:
    """Match features of image a to image b, then verify geometrically.

    Returns
    -------
    Matches
        Empty when either image has fewer than 2 features.
    """
    empty = Matches(np.zeros(0, int), np.zeros(0, int), np.zeros(0, bool))
    if len(a) < 2 or len(b) < 2:
        return empty
    binary = params.descriptor in _BINARY
    da = a.descriptors if binary else a.descriptors.astype(np.float32)
    db = b.descriptors if binary else b.descriptors.astype(np.float32)
    best_ab = _ratio_best(_knn(da, db, binary), params.ratio, len(a))
    idx_a = np.flatnonzero(best_ab >= 0)
    idx_b = best_ab[idx_a]
    if params.symmetric and len(idx_a):
        best_ba = _ratio_best(_knn(db, da, binary), params.ratio, len(b))
        mutual = best_ba[idx_b] == idx_a
        idx_a, idx_b = idx_a[mutual], idx_b[mutual]
    if len(idx_a) == 0:
        return empty
    inlier, model = verify_geometry(a.points[idx_a], b.points[idx_b], params)
    return Matches(idx_a, idx_b, inlier, model)


def verify_geometry(
    pts_a: np.ndarray, pts_b: np.ndarray, params: FeatureParams
) -> tuple[np.ndarray, np.ndarray | None]:
    """USAC (MAGSAC++) verification with a fundamental matrix or homography.

    Returns
    -------
    inlier : (M,) bool array
    model : (3, 3) array or None
    """
    n = len(pts_a)
    if params.geometric_model == "none":
        return np.ones(n, bool), None
    need = 8 if params.geometric_model == "fundamental" else 4
    if n < need:
        return np.zeros(n, bool), None
    pa = np.ascontiguousarray(pts_a, np.float64)
    pb = np.ascontiguousarray(pts_b, np.float64)
    try:
        if params.geometric_model == "fundamental":
            model, mask = cv2.findFundamentalMat(
                pa, pb, cv2.USAC_MAGSAC, params.geometric_threshold_px, 0.999, 10_000
            )
        else:
            model, mask = cv2.findHomography(
                pa, pb, cv2.USAC_MAGSAC, params.geometric_threshold_px, maxIters=10_000,
                confidence=0.999,
            )
    except cv2.error:
        return np.zeros(n, bool), None
    if model is None or mask is None:
        return np.zeros(n, bool), None
    return mask.ravel().astype(bool), model[:3]

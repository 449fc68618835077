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

from dataclasses import dataclass, field, replace
from typing import ClassVar

import cv2
import numpy as np

from ..validate import StageParams, check_ranges

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
    "match_guided",
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
class FeatureParams(StageParams):
    """Detection, description, matching and verification settings.

    Attributes
    ----------
    detector, descriptor : str
        From :data:`DETECTORS` and :data:`DESCRIPTORS`. AKAZE descriptors
        need AKAZE keypoints.
    max_features : int
        Keypoints kept per image after even selection (10–1 000 000; the GUI
        offers 500–50 000).
    threshold_scale : float
        Multiplies the detector's default threshold; < 1 finds more, weaker
        points (0.05–4).
    grid : tuple of int
        (columns, rows) of the cells for spatially even selection: each cell
        keeps its strongest ``max_features / cells`` points; each 1–64.
    ratio : float
        Lowe's ratio test (0.3–1; 1 keeps the nearest neighbour): a match is kept when its distance is
        below ``ratio`` times the second best.
    symmetric : bool
        Keep only mutual best matches.
    geometric_model : {"fundamental", "homography", "none"}
        Model for the USAC verification of the matches.
    geometric_threshold_px : float
        USAC inlier threshold, pixels at the matching resolution (0.5–20).
    upright : bool
        Describe every keypoint at orientation 0 (the image's up) instead of
        its estimated dominant orientation. Right when the two images share
        their up direction to within about 15° — a photo and the render from
        its prior do, thanks to the phone's tilt sensors — and much better
        across a change of light: the dominant gradient direction of a shaded
        bump turns with the sun, and a descriptor computed in a turned frame
        no longer matches (on the registration benchmark's changed-light
        photos upright SIFT found twice the correct matches).
    root_sift : bool
        RootSIFT (Arandjelović & Zisserman 2012): float descriptors are
        L1-normalised and square-rooted, so the Euclidean matcher compares
        them with the Hellinger kernel; a few more correct matches for free.
    invariant_channel : bool
        Also detect and describe on the illumination-invariant image of each
        colour image (:func:`napari_imgreg.registration.filters.illumination_invariant`,
        Maddern et al. 2014); its keypoints are matched only among themselves.
        Used by the registration for matching from a distant start, where
        relief shading under another sun defeats the luminance features.
    guided_radius_px : float
        Radius of guided matching (:func:`match_guided`), pixels at the
        matching resolution, 0–500; 0 turns it off. Used when the render is from an
        estimated pose, so a feature's match lies within a few pixels of it.
    """

    KIND: ClassVar[str] = "feature"

    detector: str = "SIFT"
    descriptor: str = "SIFT"
    max_features: int = 8000
    threshold_scale: float = 1.0
    grid: tuple[int, int] = (8, 6)
    ratio: float = 0.8
    symmetric: bool = True
    geometric_model: str = "fundamental"
    geometric_threshold_px: float = 3.0
    upright: bool = False
    root_sift: bool = False
    invariant_channel: bool = False
    guided_radius_px: float = 0.0

    #: Inclusive valid range of each numeric field (every element of ``grid``).
    RANGES: ClassVar[dict[str, tuple[float, float]]] = {
        "max_features": (10, 1_000_000),
        "threshold_scale": (0.05, 4.0),
        "grid": (1, 64),
        "ratio": (0.3, 1.0),
        "geometric_threshold_px": (0.5, 20.0),
        "guided_radius_px": (0.0, 500.0),
    }

    def __post_init__(self) -> None:
        for name in ("detector", "descriptor"):
            if not isinstance(getattr(self, name), str):
                raise ValueError(f"{name} must be a name such as 'SIFT', "
                                 f"got {getattr(self, name)!r}")
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
        check_ranges(self)

    @property
    def name(self) -> str:
        """E.g. ``"FAST–SIFT"`` (detection–description)."""
        return f"{self.detector}–{self.descriptor}"


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
    channel : (N,) int8 array or None
        Which image each keypoint comes from when several were combined
        (:meth:`concat`); keypoints are matched only within their channel.
        None: one channel.
    """

    points: np.ndarray
    descriptors: np.ndarray
    sizes: np.ndarray
    responses: np.ndarray
    n_detected: int
    channel: np.ndarray | None = None
    _index: object = field(default=None, init=False, repr=False, compare=False)

    def __len__(self) -> int:
        return len(self.points)

    def index(self, binary: bool):
        """A nearest-neighbour index of all descriptors, built once and kept: the
        photo's features are matched against a new render every round."""
        if self._index is None:
            self._index = _make_index(self.descriptors, binary)
        return self._index

    @property
    def channels(self) -> np.ndarray:
        """(N,) int8: the channel of every keypoint (zeros for one channel)."""
        if self.channel is None:
            return np.zeros(len(self.points), np.int8)
        return self.channel

    @classmethod
    def concat(cls, parts: list[Features]) -> Features:
        """One set from several (same descriptor type); ``parts[k]`` becomes channel ``k``."""
        parts = list(parts)
        if len(parts) == 1:
            return parts[0]
        nonempty = [p for p in parts if len(p)]
        desc = (np.vstack([p.descriptors for p in nonempty]) if nonempty
                else parts[0].descriptors)
        return cls(
            np.vstack([p.points.reshape(-1, 2) for p in parts]).astype(np.float32),
            desc,
            np.concatenate([p.sizes for p in parts]).astype(np.float32),
            np.concatenate([p.responses for p in parts]).astype(np.float32),
            int(sum(p.n_detected for p in parts)),
            np.concatenate([np.full(len(p), k, np.int8) for k, p in enumerate(parts)]),
        )


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
    # Upright descriptors need the keypoints before description: detect first.
    same = params.descriptor == det_name and not params.upright
    if params.descriptor == det_name and params.upright:
        kps = list(detector.detect(gray, m))
    elif same:
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
    if kps and params.upright:
        # One keypoint per place: detectors that give several orientations of
        # a point (SIFT) would otherwise describe it several times alike.
        seen: set[tuple[float, float, float]] = set()
        unique = []
        for k in kps:
            key = (round(k.pt[0], 2), round(k.pt[1], 2), round(k.size, 2))
            if key not in seen:
                seen.add(key)
                k.angle = 0.0
                unique.append(k)
        kps = unique
    if kps and not same:
        if params.descriptor == "SIFT" and det_name != "SIFT":
            for k in kps:  # detectors such as FAST give tiny sizes; SIFT needs a scale
                if k.size < 7:
                    k.size = 7.0
        describer = detector if params.descriptor == det_name else _descriptor(params.descriptor)
        kps, desc = describer.compute(gray, kps)
    if not kps or desc is None:
        dtype = np.uint8 if params.descriptor in _BINARY else np.float32
        return Features(np.zeros((0, 2), np.float32), np.zeros((0, 32), dtype),
                        np.zeros(0, np.float32), np.zeros(0, np.float32), n_detected)
    if params.root_sift and params.descriptor not in _BINARY:
        desc = desc.astype(np.float32)
        desc /= np.abs(desc).sum(axis=1, keepdims=True) + 1e-7
        desc = np.sqrt(desc)
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


def _make_index(desc_t: np.ndarray, binary: bool):
    """A trained matcher over ``desc_t`` (query it with ``knnMatch(q, k=2)``)."""
    if binary:
        matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    else:
        matcher = cv2.FlannBasedMatcher({"algorithm": 1, "trees": 4}, {"checks": 64})
        desc_t = desc_t.astype(np.float32)
    matcher.add([desc_t])
    matcher.train()
    return matcher


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


def _match_one(a: Features, b: Features, params: FeatureParams,
               sel_a: np.ndarray, sel_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ratio (and symmetry) test between the subsets ``sel_a`` and ``sel_b``."""
    if len(sel_a) < 2 or len(sel_b) < 2:
        return np.zeros(0, int), np.zeros(0, int)
    binary = params.descriptor in _BINARY
    da = a.descriptors[sel_a]
    db = b.descriptors[sel_b]
    if not binary:
        da, db = da.astype(np.float32), db.astype(np.float32)
    if not params.symmetric:
        best_ab = _ratio_best(_knn(da, db, binary), params.ratio, len(da))
        idx_a = np.flatnonzero(best_ab >= 0)
        return sel_a[idx_a], sel_b[best_ab[idx_a]]
    # Mutual best matches, each passing the ratio test. All of b is queried
    # against a (whose index is kept when a is the photo's whole set), then
    # only the points of a that some b chose are queried back: the same pairs
    # as two full searches, in about half the time.
    index_a = a.index(binary) if len(sel_a) == len(a) else _make_index(da, binary)
    best_ba = _ratio_best(index_a.knnMatch(db, k=2), params.ratio, len(db))
    chosen = np.unique(best_ba[best_ba >= 0])
    if len(chosen) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    back = _ratio_best(_make_index(db, binary).knnMatch(da[chosen], k=2), params.ratio,
                       len(chosen))
    best_ab = np.full(len(da), -1, np.int64)
    best_ab[chosen] = back
    idx_b = np.flatnonzero(best_ba >= 0)
    idx_a = best_ba[idx_b]
    mutual = best_ab[idx_a] == idx_b
    idx_a, idx_b = idx_a[mutual], idx_b[mutual]
    order = np.argsort(idx_a, kind="stable")
    return sel_a[idx_a[order]], sel_b[idx_b[order]]


def match_features(a: Features, b: Features, params: FeatureParams) -> Matches:
    """Match features of image a to image b, then verify geometrically.

    Keypoints of several channels (:meth:`Features.concat`) are matched only
    within their channel; the verification sees all matches together.

    Returns
    -------
    Matches
        Empty when either image has fewer than 2 features.
    """
    empty = Matches(np.zeros(0, int), np.zeros(0, int), np.zeros(0, bool))
    if len(a) < 2 or len(b) < 2:
        return empty
    ca, cb = a.channels, b.channels
    ia, ib = [], []
    for c in np.unique(ca):
        x, y = _match_one(a, b, params, np.flatnonzero(ca == c), np.flatnonzero(cb == c))
        ia.append(x)
        ib.append(y)
    idx_a, idx_b = np.concatenate(ia), np.concatenate(ib)
    if len(idx_a) == 0:
        return empty
    inlier, model = verify_geometry(a.points[idx_a], b.points[idx_b], params)
    return Matches(idx_a, idx_b, inlier, model)


def _best_two(owner: np.ndarray, other: np.ndarray, dist: np.ndarray, n: int):
    """Per owner index: best partner, its distance and the second-best distance."""
    order = np.lexsort((dist, owner))
    o, p, d = owner[order], other[order], dist[order]
    first = np.ones(len(o), bool)
    first[1:] = o[1:] != o[:-1]
    best = np.full(n, -1, np.int64)
    d1 = np.full(n, np.inf)
    d2 = np.full(n, np.inf)
    best[o[first]] = p[first]
    d1[o[first]] = d[first]
    second = np.zeros(len(o), bool)
    second[1:] = first[:-1] & ~first[1:]  # the entry right after a group's first
    d2[o[second]] = d[second]
    return best, d1, d2


def match_guided(a: Features, b: Features, params: FeatureParams,
                 radius_px: float | None = None) -> Matches:
    """Match keypoints only to keypoints of ``b`` within ``radius_px`` of the same place.

    For a render from an estimated pose, a photo feature's counterpart lies
    within a few pixels of it: comparing descriptors only there is cheap (no
    global nearest-neighbour search) and keeps repeated structures elsewhere
    in the image (bed after bed of sandstone) out of the ratio test, so more
    true matches survive. Ratio and symmetry tests and the geometric
    verification are as in :func:`match_features`; the ratio test compares
    the best candidate with the second best *within the radius* (a lone
    candidate passes it).

    Parameters
    ----------
    a, b : Features
    params : FeatureParams
    radius_px : float, optional
        Defaults to ``params.guided_radius_px``.
    """
    from scipy.spatial import cKDTree

    empty = Matches(np.zeros(0, int), np.zeros(0, int), np.zeros(0, bool))
    r = float(params.guided_radius_px if radius_px is None else radius_px)
    if len(a) < 2 or len(b) < 2 or r <= 0:
        return empty
    pairs = cKDTree(a.points).sparse_distance_matrix(cKDTree(b.points), r, output_type="ndarray")
    i = pairs["i"].astype(np.int64)
    j = pairs["j"].astype(np.int64)
    same = a.channels[i] == b.channels[j]
    i, j = i[same], j[same]
    if len(i) == 0:
        return empty
    if params.descriptor in _BINARY:
        x = np.bitwise_xor(a.descriptors[i], b.descriptors[j])
        dist = np.unpackbits(x, axis=1).sum(axis=1).astype(np.float64)
    else:
        diff = a.descriptors[i].astype(np.float32) - b.descriptors[j].astype(np.float32)
        dist = np.sqrt(np.einsum("ij,ij->i", diff, diff)).astype(np.float64)
    best_ab, d1, d2 = _best_two(i, j, dist, len(a))
    ok = (best_ab >= 0) & (d1 < params.ratio * d2)
    idx_a = np.flatnonzero(ok)
    idx_b = best_ab[idx_a]
    if params.symmetric and len(idx_a):
        best_ba, e1, e2 = _best_two(j, i, dist, len(b))
        mutual = (best_ba[idx_b] == idx_a) & (e1[idx_b] < params.ratio * e2[idx_b])
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

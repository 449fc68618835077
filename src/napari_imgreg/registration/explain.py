"""The likely cause of a registration that did not verify, in words.

The six rules of the paper (:func:`~napari_imgreg.registration.quality.evaluate_rules`)
advise on the *parameters* of the next trial. When a whole registration fails
the cause is more often in the inputs: the sensor record's camera position,
heading or focal length, or the photo itself (over- or underexposed, blurred,
mostly covered). :func:`diagnose` looks at what the trials measured and at
the photo, and names the cause it finds evidence for, with the fix, so that a
new user knows what to change. It only reads: it changes no pose, grade or
status, and runs in well under a second.

Each check needs clear evidence; none says more than it measured:

- the photo's exposure (share of pure white or near-black pixels);
- blur or low contrast: the photo has far fewer distinct points than the
  render of the model from the same pose (named after the settings changed
  from their defaults that thin out its points, a raised detection
  threshold first, when there are any);
- the sensor pose far off: from it, photo and render have almost nothing in
  common although the photo has plenty of distinct points;
- the focal length of the record: the matched 2D-3D pairs, refitted with the
  focal length free, fit a clearly different one clearly better;
- matches in a small part of the photo only;
- a best pose far beyond the sensor record's stated accuracy (a failed result),
  or a registered pose that shows how far the record was off.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any, NamedTuple, Sequence

import numpy as np

from ..camera import Intrinsics, Pose
from .pose import reprojection_errors
from .resection import refine_camera

__all__ = ["diagnose", "photo_exposure", "focal_refit", "FocalRetry", "focal_retry_start",
           "match_spread", "nothing_in_common", "prior_offset", "prior_offset_hint",
           "fewer_points_settings"]

#: A photo with this share of pure-white pixels (luminance ≥ 250) is overexposed.
OVEREXPOSED_SHARE = 0.25
#: A photo with this mean luminance (0–255) or less is very dark.
DARK_MEAN = 40.0
#: Fewer photo points than this share of the render's, from the same pose: blurred.
BLUR_POINT_RATIO = 0.25
#: "Almost nothing in common": fewer consistent matches than this.
FEW_MATCHES = 20
#: A refitted focal length this far off (relative) with an error this much smaller.
FOCAL_OFF = 0.08
FOCAL_GAIN = 0.7
#: Grid of the photo for :func:`match_spread`; matches in this share of its cells or fewer.
SPREAD_GRID = (4, 4)
SPREAD_SHARE = 0.25


def photo_exposure(photo_rgb: np.ndarray) -> tuple[float, float]:
    """(share of pure-white pixels, mean luminance 0–255) of a photo."""
    step = max(1, int(max(photo_rgb.shape[:2]) // 512))
    a = np.asarray(photo_rgb[::step, ::step, :3], dtype=np.float32)
    y = a @ np.float32([0.299, 0.587, 0.114])
    return float(np.mean(y >= 250.0)), float(y.mean())


def focal_refit(corr, pose: Pose, intrinsics: Intrinsics,
                min_pairs: int = 20, with_pose: bool = False) -> tuple | None:
    """Refit a trial's 2D–3D inliers with the focal length free.

    Returns
    -------
    (fx, error_given_px, error_free_px) or None
        The refitted focal length and the median reprojection errors with the
        given and with the refitted camera; None with too few pairs.
        ``with_pose``: the refitted pose as a fourth item.
    """
    if corr is None or corr.xyz is None or pose is None:
        return None
    use = corr.lifted & corr.pose_inlier
    if int(use.sum()) < min_pairs:
        return None
    X, u = corr.xyz[use], corr.photo_points[use]
    try:
        e0 = float(np.median(reprojection_errors(intrinsics, pose, X, u)))
        pose1, f, _, _ = refine_camera(X, u, pose, (intrinsics.fx, intrinsics.fy),
                                       (intrinsics.cx, intrinsics.cy))
        cam = replace(intrinsics, fx=float(f[0]), fy=float(f[0]) * intrinsics.fy / intrinsics.fx)
        e1 = float(np.median(reprojection_errors(cam, pose1, X, u)))
    except Exception:  # a diagnosis never breaks a registration
        return None
    if not (math.isfinite(e0) and math.isfinite(e1) and f[0] > 0):
        return None
    return (float(f[0]), e0, e1, pose1) if with_pose else (float(f[0]), e0, e1)


class FocalRetry(NamedTuple):
    """What :func:`focal_retry_start` found: the trial whose matches fit
    another focal length far better, that focal length and the pose refitted
    with it, and the median reprojection errors (pixels) with the record's
    camera and with the refitted one."""

    trial: Any
    fx: float
    pose: Pose
    error_given_px: float
    error_free_px: float


def focal_retry_start(trials: Sequence, intrinsics: Intrinsics) -> FocalRetry | None:
    """The trial to estimate the focal length from, and the focal length to
    start with, when the record's looks wrong; None otherwise.

    Of the unverified keypoint trials with a pose, the one with the most 3D
    inliers is refitted with the focal length free (:func:`focal_refit`);
    a fit at least :data:`FOCAL_OFF` away from the record's and with a median
    error at most :data:`FOCAL_GAIN` of the record's is evidence that the
    record's focal length is wrong.

    Returns
    -------
    FocalRetry or None
        The trial, the refitted fx (pixels), the pose refitted with it (a
        focal length that wrong puts the trial's own camera tens of metres off
        along its view: the start for the focal length's trial) and the two
        fits' errors.
    """
    fits = []
    for t in trials:
        if getattr(t, "matcher", "keypoints") != "keypoints" or t.pose is None or t.verified:
            continue
        camera = t.intrinsics or intrinsics
        if not camera.focal_known:
            continue
        fit = focal_refit(t.correspondences, t.pose, camera, with_pose=True)
        if fit is not None:
            fits.append((int(t.metrics.get("inliers_3d") or 0), fit, t, camera))
    if not fits:
        return None
    _, (fx, e0, e1, pose), t, camera = max(fits, key=lambda x: x[0])
    if abs(fx / camera.fx - 1.0) >= FOCAL_OFF and e1 <= FOCAL_GAIN * e0:
        return FocalRetry(t, fx, pose, e0, e1)
    return None


def nothing_in_common(trials: Sequence) -> tuple[int, int] | None:
    """From the sensor pose, photo and render share almost nothing although
    the photo has plenty of distinct points: (consistent matches, photo
    points) of the keypoint trials from the prior, or None when that is not so
    (or a trial verified). The heading may be far off: the search around the
    prior covers ±3σ only."""
    if any(t.verified for t in trials):
        return None
    from_prior = [t for t in trials if getattr(t, "matcher", "keypoints") == "keypoints"
                  and t.origin == "prior"]
    if not from_prior:
        return None
    inl = max(int(t.metrics.get("feature_inliers") or 0) for t in from_prior)
    inl3 = max(int(t.metrics.get("inliers_3d") or 0) for t in from_prior)
    pts_photo = int(from_prior[0].metrics.get("points_photo") or 0)
    if inl < FEW_MATCHES and inl3 < 7 and pts_photo >= 500:
        return inl, pts_photo
    return None


def match_spread(corr, width: int, height: int) -> tuple[int, int] | None:
    """(cells of the photo holding pose inliers, cells) on :data:`SPREAD_GRID`."""
    if corr is None:
        return None
    use = corr.pose_inlier
    if int(use.sum()) < 7:
        return None
    p = corr.photo_points[use]
    gx, gy = SPREAD_GRID
    ix = np.clip((p[:, 0] / width * gx).astype(int), 0, gx - 1)
    iy = np.clip((p[:, 1] / height * gy).astype(int), 0, gy - 1)
    counts = np.bincount(iy * gx + ix, minlength=gx * gy)
    return int((counts >= 3).sum()), gx * gy


def _hfov(fx: float, width: int) -> float:
    return math.degrees(2.0 * math.atan(width / 2.0 / fx))


def _heading_diff(a: float, b: float) -> float:
    """a − b in (−180, 180]."""
    d = (a - b + 180.0) % 360.0 - 180.0
    return 180.0 if d == -180.0 else d


def prior_offset(pose: Pose, prior) -> tuple[str, list[str]] | None:
    """How a pose differs from the sensor record, when far beyond its sigma.

    Returns
    -------
    (what, checks) or None
        ``what``: the differences in words ("the camera position by 27 m and
        the heading by 20°"); ``checks``: the sensors to check. None when
        the pose lies within three sigma of the record.
    """
    if pose is None:
        return None
    sig = prior.sigma
    delta = pose.center - prior.pose.center
    d = float(np.linalg.norm(delta))
    moved = bool(np.hypot(delta[0], delta[1]) > 3.0 * float(sig.position_m)
                 or abs(delta[2]) > 3.0 * float(sig.altitude_m))
    a = pose.rotation_error_deg(prior.pose)
    s_ang = float(sig.angles_deg)
    if not moved and a <= 3.0 * s_ang:
        return None
    dtrend = _heading_diff(pose.attitude[0], prior.pose.attitude[0])
    dplunge = pose.attitude[1] - prior.pose.attitude[1]
    parts, checks = [], []
    if moved:
        parts.append(f"the camera position by {d:.0f} m")
        checks.append("the GPS fix (wait for a good fix, or place the camera on the DEM map)")
    if abs(dtrend) > 3.0 * s_ang:
        parts.append(f"the heading by {abs(dtrend):.0f}°")
        checks.append("the compass (calibrate it, away from the car and metal)")
    if abs(dplunge) > 3.0 * s_ang:
        parts.append(f"the tilt (plunge) by {abs(dplunge):.0f}°")
    if not parts:
        parts.append(f"the view direction by {a:.0f}°")
    if len(checks) < len(parts):
        checks.append("the orientation sensor")
    return ", ".join(parts[:-1]) + (" and " if len(parts) > 1 else "") + parts[-1], checks


def prior_offset_hint(pose: Pose, prior, registered: bool) -> str | None:
    """How far the pose lies from the sensor record, when far beyond its sigma."""
    offset = prior_offset(pose, prior)
    if offset is None:
        return None
    what, checks = offset
    s_pos, s_ang = float(prior.sigma.position_m), float(prior.sigma.angles_deg)
    if registered:
        return (f"The sensor record was off: {what}, beyond its stated accuracy "
                f"({s_pos:g} m, {s_ang:g}°); the registration found the pose anyway and "
                f"verified it. For the next photos check {' and '.join(checks)}.")
    return (f"The best pose found differs from the sensor record in {what}, far beyond the "
            f"record's stated accuracy ({s_pos:g} m, {s_ang:g}°): unless the record is that far "
            "off, this pose is wrong — do not map on it.")


#: Names of the filters' switches in a hint (the others: their field name).
_FILTER_LABELS = {"wallis": "Wallis filter", "clahe": "CLAHE",
                  "gradient": "gradient magnitude"}


def _filter_changes(filters, default) -> list[str]:
    """The fields of one image's filters that differ from ``default``, in words
    ("Wallis off", "gamma 2.5"); a sub-filter's settings only when it is on."""
    changes = []
    for name, value in filters.to_dict().items():
        base = getattr(default, name)
        if value == base:
            continue
        group = name.split("_")[0]
        if group in ("wallis", "clahe", "gradient") and name != group \
                and not getattr(filters, group):
            continue
        label = _FILTER_LABELS.get(name, name.replace("_", " "))
        if isinstance(value, bool):
            changes.append(f"{label} {'on' if value else 'off'}")
        else:
            changes.append(f"{label} {value:g}")
    return changes


def fewer_points_settings(params) -> list[str]:
    """The settings of a registration, changed from their defaults, that leave
    the photo fewer distinct points: a raised detection threshold, a smaller
    matching width, the photo's filters (each a short phrase; empty when
    none is changed or ``params`` is unknown).

    A higher threshold drops the weak points of a soft or low-contrast photo
    far more than those of a crisp render, so it can make a sound photo look
    blurred: the hint says so before it blames the photo.
    """
    from .params import RegistrationParams

    if not isinstance(params, RegistrationParams):
        return []
    default = RegistrationParams()
    out = []
    scale = params.features.threshold_scale
    base = default.features.threshold_scale
    if scale > base:
        out.append(f"the feature detection threshold is ×{scale:g} (default ×{base:g}), which "
                   "keeps only the strongest points")
    if params.match_width < default.match_width:
        out.append(f"images are matched {params.match_width} px wide (default "
                   f"{default.match_width} px)")
    defaults = [RegistrationParams.default_filters("photo"),
                RegistrationParams.for_cloud().photo_filters]
    if params.photo_filters not in defaults:
        # Against the default it differs least from (a point cloud's has gradient on).
        changes = min((_filter_changes(params.photo_filters, d) for d in defaults), key=len)
        if changes:
            out.append(f"the photo's filters differ from the defaults ({', '.join(changes)})")
    return out


def diagnose(trials: Sequence, best, status: str, prior, camera: Intrinsics,
             photo_rgb: np.ndarray, appearance: bool = True) -> list[str]:
    """:func:`_diagnose`, never raising: advice must not break a registration."""
    try:
        return _diagnose(trials, best, status, prior, camera, photo_rgb, appearance)
    except Exception:  # noqa: BLE001
        return []


def _diagnose(trials: Sequence, best, status: str, prior, camera: Intrinsics,
              photo_rgb: np.ndarray, appearance: bool = True) -> list[str]:
    """Lines naming the likely cause of a result and its fix, most likely first.

    Parameters
    ----------
    trials : list of Trial
        All trials of the registration, in order.
    best : Trial
        The one the result reports.
    status : str
        ``"registered"`` or ``"failed"``.
    prior : Prior
        The sensor prior (its pose, sigma and camera).
    camera : Intrinsics
        The result's camera.
    photo_rgb : (H, W, 3) uint8 array
    appearance : bool
        The model renders with its own appearance (a texture, colours, a
        scan's intensity). Without (a bare mesh's shading), keypoints rarely
        match from any pose: their counts then say nothing about the photo
        or the sensor pose, and those two checks are skipped.

    Returns
    -------
    list of str
        Empty when nothing is clearly wrong.
    """
    out: list[str] = []
    if status == "registered":
        hint = prior_offset_hint(best.pose, prior, True)
        return [hint] if hint else []
    intr = prior.intrinsics
    w, h = intr.width, intr.height
    keypoint = [t for t in trials if getattr(t, "matcher", "keypoints") == "keypoints"]
    first = keypoint[0] if keypoint else (trials[0] if trials else None)

    # The photo itself.
    white, mean = photo_exposure(photo_rgb)
    exposure_bad = False
    if white >= OVEREXPOSED_SHARE:
        exposure_bad = True
        share = "nearly all" if white >= 0.95 else f"{white:.0%}"
        out.append(f"The photo is overexposed: {share} of it is pure white, where nothing "
                   "can be matched. Use a photo exposed for the rock (on a phone, tap the rock "
                   "face before shooting), or register it with control points.")
    elif mean <= DARK_MEAN:
        exposure_bad = True
        out.append(f"The photo is very dark (mean brightness {mean:.0f} of 255): little of the "
                   "rock's detail can be matched. Use a brighter exposure of the same view, or "
                   "register it with control points.")
    pts_photo = pts_render = 0
    if first is not None:
        pts_photo = int(first.metrics.get("points_photo") or 0)
        pts_render = int(first.metrics.get("points_render") or 0)
    if (appearance and not exposure_bad and pts_render > 0 and pts_photo < 1000
            and pts_photo < BLUR_POINT_RATIO * pts_render):
        own = fewer_points_settings(getattr(first, "params", None))
        if own:
            # The user's own setting is the first suspect: a photo is not
            # blamed for what a raised threshold or a filter took from it.
            out.append(f"The photo has far fewer distinct points than the render of the model "
                       f"({pts_photo} against {pts_render}), and settings changed from their "
                       f"defaults explain part of it: {'; '.join(own)}. Set them back and run "
                       "again; if the photo still has far fewer points, it is probably blurred "
                       "(camera shake, out of focus), hazy or low in contrast — a sharp photo "
                       "of the same view registers best, otherwise add control points by hand.")
        else:
            out.append(f"The photo has far fewer distinct points than the render of the model "
                       f"({pts_photo} against {pts_render}): it is probably blurred (camera "
                       "shake, out of focus), hazy or low in contrast. A sharp photo of the same "
                       "view registers best; otherwise add control points by hand.")

    # The focal length of the sensor record.
    if "fx" not in (camera.estimated or ()) and getattr(intr, "focal_known", True):
        refit = focal_retry_start(keypoint, camera)
        if refit is not None:
            fx, e0, e1 = refit.fx, refit.error_given_px, refit.error_free_px
            given = (refit.trial.intrinsics or camera).fx
            out.append(
                f"The focal length looks wrong: the matches fit fx ≈ {fx:.0f} px (a "
                f"{_hfov(fx, w):.0f}° horizontal view) far better than the given "
                f"{given:.0f} px ({_hfov(given, w):.0f}°): reprojection error {e0:.1f} → "
                f"{e1:.1f} px. Correct the focal length (or the sensor width) in the sensor "
                "record, or delete it there so that it is estimated during registration.")

    # The sensor pose.
    common = nothing_in_common(trials) if appearance and not exposure_bad else None
    if common is not None:
        inl, pts_photo = common
        s = prior.sigma
        all_round = (", then headings all round"
                     if getattr(first.params, "auto_adapt", False) else "")
        searched = (f", and the search around it (heading ±{3 * s.angles_deg:g}°, position "
                    f"±{s.position_m:g} m{all_round}) found no better start"
                    if getattr(first.params, "search_prior", False) else "")
        out.append(
            f"From the sensor record's pose, photo and render have almost nothing in common "
            f"({inl} consistent matches, although the photo has {pts_photo} distinct "
            f"points){searched}. Most likely the camera position "
            "or the heading in the sensor record is far off — or the photo shows another "
            "place, or is mirrored or upside down. Compare the photo with the render from "
            "the sensor pose: if they show different parts of the outcrop, move the camera "
            "on the DEM map and turn it toward what the photo shows, then register again; "
            "or register with control points.")

    # Where the matches are.
    if best is not None and best.pose is not None and not exposure_bad:
        spread = match_spread(best.correspondences, w, h)
        if spread is not None and spread[0] <= SPREAD_SHARE * spread[1]:
            out.append(
                f"The matches hold only {spread[0]} of {spread[1]} parts of the photo (is the "
                "rest vegetation, sky, foreground or deep shadow?): a pose held by one patch "
                "tilts easily, so it could not be verified. Add control points in the other "
                "parts of the photo, or use a photo showing more of the outcrop.")
        hint = prior_offset_hint(best.pose, prior, False)
        if hint:
            out.append(hint)
    return out

"""Cloud registration benchmark (issue 16, first must-show): photos registered
to generated terrestrial laser scans, ours beside the plain baseline.

The scenes and photos are ``bench_register.py``'s (its generator, cache,
success and false-verdict rules, reused by import); the reference is not the
mesh but a two-station terrestrial scan of the photos' own surface
(``<scene>/lidar-s<SCAN_VERSION>/scan.laz``, made by ``bench_lidar_scan.py``
through :mod:`napari_imgreg.sample.scan`: 1 mrad step, ~3.8 M points,
intensity = per-rock-type reflectance × within-bed texture × |cos incidence|
× range falloff × 2 % noise, 5 mm range noise, no colour). The rough tiers
(``rough_same_light``, ``rough_changed_light``, asked for by name) use the scan
of the rough scene's true surface (``rough-r2/lidar-s<SCAN_VERSION>/``).

Each photo is registered by every method in the same process, one after the
other, from the same sensor prior:

* ``ours``: the automatic pipeline on the cloud scene with the cloud preset
  (:meth:`RegistrationParams.for_cloud`: keypoints on gradient magnitude);
* ``default``: the automatic pipeline's defaults (``RegistrationParams()``)
  on the cloud scene, the before-figure of the preset;
* ``baseline``: :meth:`RegistrationParams.baseline_cloud` (intensity splat,
  gradient images, SIFT, EPnP, one round, no verification);
* ``unknown_focal``: ours with the sensor record cut to ``{width, height}``
  and no focal length in the EXIF (``bench_unknown_focal.prior_of``);
* ``seed003``: :func:`napari_imgreg.registration.seed003.register_seed003`
  (reflectivity + wireframe + HOG + DLT) when that module exists, else "not run".

Success: status ``registered`` and median check-point error < 4 px at 1632 px
width, the check points projected through the camera the result reports;
false verdict: ``registered`` or graded good/excellent with an error ≥ 4 px
(``bench_register.py``'s rules). The rows also give the median over the
check points on the scan's own surface (``cp_on_scan_px``): a scan from the
cliff's foot may not cover the frame's near ground. Per photo the benchmark also measures, at
the true camera and the matching width (768 px), how alike the scan's
intensity render and the photo are: the correlation coefficient of their grey
levels and of their gradient magnitudes over the rendered surface, and how
many keypoint matches are *correct* (lifted 3D point within 4 px of its photo
point through the true camera) with grey-level and with gradient filters.

    nice -n 19 .venv/bin/python benchmarks/bench_register_cloud.py --report docs/benchmarks.md
    nice -n 19 .venv/bin/python benchmarks/bench_register_cloud.py --quick       # smoke run
    nice -n 19 .venv/bin/python benchmarks/bench_register_cloud.py --from-rows \\
        benchmarks/_cache/bench_register_cloud_rows.json --report docs/benchmarks.md

Rows are written to ``benchmarks/_cache/bench_register_cloud_rows.json`` after
every registration (a stopped run keeps what it measured; ``--resume`` skips
the photo × method pairs already there).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import bench_register as br  # noqa: E402  (the scenes, generator, cache and rules)
from _report import markers, write_section  # noqa: E402

from napari_imgreg import Scene, render  # noqa: E402
from napari_imgreg._allocator import tune_allocator  # noqa: E402
from napari_imgreg._atomic import atomic_write  # noqa: E402
from napari_imgreg.camera import match_scale  # noqa: E402
from napari_imgreg.io.photos import load_photo  # noqa: E402
from napari_imgreg.prior import prior_for_photo  # noqa: E402
from napari_imgreg.registration.features import detect_and_describe, match_features  # noqa: E402
from napari_imgreg.registration.filters import (  # noqa: E402
    FilterParams,
    apply_filters,
    gradient_magnitude,
    reduce_for_matching,
    to_gray,
)
from napari_imgreg.registration.params import RegistrationParams  # noqa: E402
from napari_imgreg.registration.pipeline import register  # noqa: E402
from napari_imgreg.sample import load_truth  # noqa: E402
from napari_imgreg.sample.scan import SCAN_VERSION  # noqa: E402

NAME = "bench_register_cloud"
MARK_START, MARK_END = markers(NAME)
METHODS = ("ours", "default", "baseline", "unknown_focal", "seed003")
DEFAULT_METHODS = ("ours", "baseline", "unknown_focal", "seed003")
TIERS = ("same_light", "changed_light", "rough_same_light", "rough_changed_light")
DEFAULT_TIERS = ("same_light", "changed_light")
#: Issue 16's targets.
TARGETS = {"same_light": 0.95, "changed_light": 0.80, "false_verdicts": 0.02,
           "median_cp_px": 1.5, "unknown_ratio": 0.90, "focal_error": 0.01}
#: Mesh rows of the same photos (``bench_unknown_focal.py``: ``known`` is the
#: default pipeline on the mesh, ``unknown`` with width/height-only records;
#: ``bench_register.py``'s rough runs: ``ours``, ``baseline``).
MESH_ROWS = ("bench_unknown_focal_rows.json", "rows_r2_seed1.json", "rows_r2_seed2.json")
MESH_METHOD = {"known": "ours", "unknown": "unknown_focal", "ours": "ours", "baseline": "baseline"}


# ------------------------------------------------------------------ data
def scan_path(scene_dir: Path, tier: str) -> Path:
    """The scan of the surface ``tier``'s photos show (made once, by bench_lidar_scan)."""
    import bench_lidar_scan as bls

    surface = "rough" if tier.startswith("rough") else "plain"
    model_dir, out_dir = bls.scan_dir(scene_dir, surface, 1.0)
    laz = out_dir / "scan.laz"
    if not (out_dir / "bench.json").is_file() or not laz.is_file():
        bls.run_scene(model_dir, out_dir, 1.0, force=False)
    return laz


def tier_folder(scene_dir: Path, tier: str) -> Path:
    if tier == "same_light":
        return scene_dir / "same_light"
    if tier == "changed_light":
        return br.changed_folder(scene_dir, br.CHANGED_STRENGTH)
    return br.rough_folder(scene_dir) / tier


def load_cloud(laz: Path, scene_dir: Path):
    """The scan as a CloudScene, with the scene's georeference and DEM (as a user has them)."""
    scene = Scene.load(laz, georef=scene_dir / "georef.json", dem=scene_dir / "dem.tif")
    t0 = time.perf_counter()
    scene.build_engine()  # normals and spacing: computed once, cached beside the scan
    return scene, time.perf_counter() - t0


# --------------------------------------------------------------- methods
def params_of(method: str) -> RegistrationParams:
    if method == "default":
        return RegistrationParams()
    if method == "baseline":
        return RegistrationParams.baseline_cloud()
    return RegistrationParams.for_cloud()


def _seed003():
    """H2's ``register_seed003`` when it exists (imported lazily), else None."""
    try:
        from napari_imgreg.registration.seed003 import register_seed003
    except ImportError:
        return None
    return register_seed003


def _cp(reg, truth) -> np.ndarray:
    """Check-point errors (px at 1632 px width) through the camera the result reports."""
    cam = reg.intrinsics
    err = np.linalg.norm(reg.pose.project(cam, truth.check_xyz) - truth.check_pixels, axis=1)
    return np.where(np.isfinite(err), err, 1e6) * br.REFERENCE_WIDTH / cam.width


_ON_SCAN: dict[Path, np.ndarray] = {}


def on_scan(scene, photo_path: Path, truth) -> np.ndarray:
    """(C,) bool: which check points lie on the scan's surface (the scan, rendered
    from the true camera, shows a point within 1 m of them at their pixel). The
    frame's check points include near ground a scan from the cliff's foot may
    not cover: a user maps only where the model is. Cached per photo."""
    if photo_path not in _ON_SCAN:
        r = render(scene, truth.intrinsics, truth.pose, scale=1.0, mode="color")
        h, w = r.mask.shape
        px = np.round(truth.check_pixels).astype(int)
        inside = (px[:, 0] >= 0) & (px[:, 1] >= 0) & (px[:, 0] < w) & (px[:, 1] < h)
        near = np.zeros(len(px), bool)
        seen = r.xyz[px[inside, 1], px[inside, 0]]
        near[inside] = np.linalg.norm(seen - truth.check_xyz[inside], axis=1) < 1.0  # NaN: False
        _ON_SCAN[photo_path] = near
    return _ON_SCAN[photo_path]


def evaluate(scene, photo_path: Path, method: str, tmp: Path) -> dict | None:
    """One registration and its scores; None when the method cannot run here."""
    import bench_unknown_focal as buf

    truth = load_truth(photo_path)
    photo = load_photo(photo_path)
    if method == "unknown_focal":
        prior = buf.prior_of(photo, scene, "unknown", tmp)
    else:
        prior = prior_for_photo(photo, scene)
    t0 = time.perf_counter()
    if method == "seed003":
        fn = _seed003()
        if fn is None:
            return None
        reg = fn(scene, photo.image, prior, None, photo_name=photo_path.name)
    else:
        reg = register(scene, photo.image, prior, params_of(method), photo_path.name)
    seconds = time.perf_counter() - t0
    cp = _cp(reg, truth)
    cp_med = float(np.median(cp))
    scan_cp = on_scan(scene, photo_path, truth)
    registered = reg.status == "registered"
    claims = registered or reg.grade in ("good", "excellent")
    return {
        "method": method,
        "status": reg.status,
        "grade": reg.grade,
        "Q": round(float(reg.q), 3),
        "success": bool(registered and cp_med < br.SUCCESS_PX),
        "false_verdict": bool(claims and cp_med >= br.SUCCESS_PX),
        "cp_median_px": round(cp_med, 3),
        # The same over the check points on the scan's own surface (see on_scan).
        "cp_on_scan_px": (round(float(np.median(cp[scan_cp])), 3) if scan_cp.any() else None),
        "check_points_on_scan": f"{int(scan_cp.sum())}/{len(scan_cp)}",
        "rotation_error_deg": round(reg.pose.rotation_error_deg(truth.pose), 4),
        "position_error_m": round(float(np.linalg.norm(reg.pose.center - truth.pose.center)), 4),
        "focal_error": round(reg.intrinsics.fx / truth.intrinsics.fx - 1.0, 6),
        "estimated": list(getattr(reg.intrinsics, "estimated", ()) or ()),
        "seconds": round(seconds, 3),
        "n_trials": len(reg.trials),
        "winning_stage": (reg.trials[reg.best_trial].origin
                          if reg.best_trial is not None and registered and reg.trials else None),
        "uncertainty_px": (None if reg.uncertainty is None
                           else reg.uncertainty.to_dict().get("reprojection_px")),
        # The whole estimate: its metres and degrees are what the sigmas of
        # projected lines are drawn from.
        "uncertainty": None if reg.uncertainty is None else reg.uncertainty.to_dict(),
        "hints": list(reg.hints),
        "trials": [{"origin": t.origin, "render_mode": t.render_mode, "verified": t.verified,
                    "grade": t.grade, "feature_inliers": t.metrics.get("feature_inliers"),
                    "inliers_3d": t.metrics.get("inliers_3d"),
                    "cp_median_px": br._trial_cp(t, truth), "seconds": round(t.seconds, 3)}
                   for t in reg.trials],
        "prior_rotation_error_deg": round(truth.raw["prior_error"]["rotation_deg"], 3),
        "prior_position_error_m": round(truth.raw["prior_error"]["position_m"], 3),
    }


# ------------------------------------------------------------- diagnosis
def _correct_matches(scene, photo_rgb, truth, photo_f: FilterParams, render_f: FilterParams,
                     width: int) -> dict:
    """Keypoint matches at the true camera: putative, feature inliers, and correct ones."""
    params = RegistrationParams()
    fp = params.features
    scale = match_scale(truth.intrinsics.width, width)
    rendered = render(scene, truth.intrinsics, truth.pose, scale=scale)
    small, _ = reduce_for_matching(photo_rgb, width)
    gp = apply_filters(small, photo_f)
    gr = apply_filters(rendered.rgb, render_f, mask=rendered.mask)
    mask = rendered.mask
    import cv2

    inner = cv2.erode(mask.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    fa = detect_and_describe(gp, fp, color=small)
    fb = detect_and_describe(gr, fp, mask=inner, color=rendered.rgb)
    m = match_features(fa, fb, fp)
    if not len(m):
        return {"putative": 0, "inliers": 0, "correct": 0, "correct_inliers": 0}
    pa = fa.points[m.idx_a] / scale
    xyz, ok = rendered.lift(fb.points[m.idx_b])
    proj = truth.pose.project(truth.intrinsics, np.nan_to_num(xyz))
    err = np.linalg.norm(proj - pa, axis=1) * br.REFERENCE_WIDTH / truth.intrinsics.width
    correct = ok & (err < br.SUCCESS_PX)
    return {"putative": int(len(m)), "inliers": int(m.inlier.sum()), "correct": int(correct.sum()),
            "correct_inliers": int((correct & m.inlier).sum())}


def diagnose(scene, photo_path: Path, width: int = 768, dump: Path | None = None) -> dict:
    """How alike the intensity render and the photo are at the true camera."""
    truth = load_truth(photo_path)
    photo = load_photo(photo_path).image
    scale = match_scale(truth.intrinsics.width, width)
    rendered = render(scene, truth.intrinsics, truth.pose, scale=scale)
    small, _ = reduce_for_matching(photo, width)
    m = rendered.mask
    gp, gr = to_gray(small).astype(np.float64), to_gray(rendered.rgb).astype(np.float64)
    r_grey = float(np.corrcoef(gp[m], gr[m])[0, 1])
    dp = gradient_magnitude(to_gray(small), 1.0).astype(np.float64)
    dr = gradient_magnitude(to_gray(rendered.rgb), 1.0, m).astype(np.float64)
    import cv2

    inner = cv2.erode(m.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    r_grad = float(np.corrcoef(dp[inner], dr[inner])[0, 1])
    out = {"r_grey": round(r_grey, 3), "r_gradient": round(r_grad, 3),
           "coverage": round(float(m.mean()), 3), "r_grey_relit": None}
    sun = prior_for_photo(load_photo(photo_path), scene).sun
    if sun is not None:
        # What the pipeline matches against: the render relit for the photo's sun.
        from napari_imgreg.registration.stages.relight import render_sunlit

        relit = render_sunlit(scene, truth.intrinsics, truth.pose, sun, scale=scale,
                              survey_sun_dir=scene.survey_sun)
        ml = relit.mask
        out["r_grey_relit"] = round(float(np.corrcoef(
            gp[ml], to_gray(relit.rgb).astype(np.float64)[ml])[0, 1]), 3)
    wallis = FilterParams(wallis=True)
    grad = FilterParams(gradient=True, wallis=True)
    out["matches_grey"] = _correct_matches(scene, photo, truth, wallis, wallis, width)
    out["matches_gradient"] = _correct_matches(scene, photo, truth, grad, grad, width)
    if dump is not None:
        from PIL import Image

        dump.mkdir(parents=True, exist_ok=True)
        stem = f"{photo_path.parent.parent.name}-{photo_path.parent.name}-{photo_path.stem}"
        Image.fromarray(np.concatenate([to_gray(small), to_gray(rendered.rgb)], axis=1)).save(
            dump / f"{stem}-grey.png")
        Image.fromarray(np.concatenate([apply_filters(small, grad),
                                        apply_filters(rendered.rgb, grad, mask=m)], axis=1)).save(
            dump / f"{stem}-gradient.png")
    return out


# --------------------------------------------------------------- summary
def _median(values) -> float | None:
    v = [x for x in values if x is not None and np.isfinite(x)]
    return float(statistics.median(v)) if v else None


def _f(v, fmt="{:.2f}") -> str:
    return "–" if v is None else fmt.format(v)


def summarize(rows: list[dict]) -> dict:
    out = {}
    tiers = [t for t in TIERS if any(r["tier"] == t for r in rows)]
    for tier in tiers + ["all"]:
        for method in METHODS:
            sel = [r for r in rows if r.get("method") == method
                   and (r["tier"] == tier or (tier == "all" and r["tier"] in DEFAULT_TIERS))]
            if not sel:
                continue
            reg = [r for r in sel if r["status"] == "registered"]
            out[(tier, method)] = {
                "n": len(sel), "success": sum(r["success"] for r in sel),
                "registered": len(reg), "false_verdicts": sum(r["false_verdict"] for r in sel),
                "cp_median": _median([r["cp_median_px"] for r in reg]),
                "seconds": _median([r["seconds"] for r in sel]),
                "focal": _median([abs(r["focal_error"]) for r in reg]),
            }
    return out


def mesh_rows(cache: Path, photos: set[tuple[str, int, str]]) -> list[dict]:
    """Cached mesh rows of the same photos (tier, seed, photo), method renamed to ours'."""
    out = []
    for name in MESH_ROWS:
        p = cache / name
        if not p.is_file():
            continue
        for r in json.loads(p.read_text()):
            key = (r.get("tier"), r.get("scene_seed"), r.get("photo"))
            method = MESH_METHOD.get(r.get("method", r.get("mode")))
            if key in photos and method:
                out.append({**r, "method": method, "source": name})
    return out



def _span(values, fmt: str = "{:.1f}") -> str:
    """``a–b``, or ``a`` when both ends print alike."""
    lo, hi = fmt.format(min(values)), fmt.format(max(values))
    return lo if lo == hi else f"{lo}–{hi}"


def _false_verdict_reasons(false: list[dict]) -> list[str]:
    """Why the false verdicts happened, from what their rows record (relit or
    not, focal length estimated or not)."""
    relit = [r for r in false if (r.get("trials") or [{}])[-1].get("render_mode") == "sunlit"]
    unlit = [r for r in false if r not in relit]

    def who(part: list) -> str:
        if len(part) == len(false):
            return "It" if len(part) == 1 else "They"
        return f"{len(part)} of them"

    out = []
    if unlit:
        out.append(
            f"{who(unlit)} had no known sun (the survey's diffuse light, no capture "
            "time), so the intensity render was not relit; area matching fails on it, and the "
            "edge and intensity-pattern stages end on a shared bias that the split halves "
            "cannot see (method §4, *where the estimate is known to be too small*).")
    if relit:
        focal = [r for r in relit if r.get("method") == "unknown_focal"]
        text = (f"{who(relit)} {'was' if len(relit) == 1 else 'were'} matched against the render relit for the photo's "
                "sun, whose shading is drawn only by the relief the scan resolves: a bias every "
                "match shares, counted in the estimate only by the shading share "
                "(method §4)")
        if focal:
            errs = [abs(r.get("focal_error") or 0.0) * 100 for r in focal]
            lead = ("its focal length was" if len(relit) == 1
                    else f"{len(focal)} of them had the focal length")
            text += (f"; {lead} estimated too ({_span(errs)} % off), which absorbs part of "
                     "that bias")
        out.append(text + ".")
    return out

def report(rows: list[dict], diag: list[dict], meta: dict, mesh: list[dict]) -> str:
    s = summarize(rows)

    def key(r):
        return (r["tier"], r["scene_seed"], r["photo"])

    # The mesh figures of each method's own photos.
    sm = {}
    for m in METHODS:
        keys = {key(r) for r in rows if r["method"] == m}
        sel = [r for r in mesh if r["method"] == m and key(r) in keys]
        sm.update({k: v for k, v in summarize(sel).items() if k[1] == m})
    seeds = sorted({r["scene_seed"] for r in rows})
    tiers = [t for t in TIERS if any(r["tier"] == t for r in rows)]
    n_photos = len({(r["tier"], r["scene_seed"], r["photo"]) for r in rows})
    lines = [
        MARK_START, "## Registration to lidar scans (issue 16, must-show 1)", "",
        f"{n_photos} photos ({', '.join(tiers)}; large scenes, seeds "
        f"{', '.join(map(str, seeds))}; 1632×1224) registered to a generated two-station "
        f"terrestrial scan of their own surface (scan version {meta.get('scan_version')}: "
        f"{meta.get('points', '–')} points, 1 mrad, intensity = per-rock-type reflectance × "
        "within-bed texture (15 % log-std at 0.15–5 m, half correlated with the visible albedo "
        "within the bed) × |cos incidence| × range falloff × 2 % noise, 5 mm range noise, no "
        "colour), from the sensor priors of `bench_register.py`. *ours*: the automatic pipeline "
        "with `RegistrationParams.for_cloud()` (keypoints on gradient magnitude); *default*: "
        "`RegistrationParams()` on the cloud; *baseline*: `RegistrationParams.baseline_cloud()` "
        "(intensity splat, gradient images, SIFT, EPnP); *unknown_focal*: ours with a "
        "width/height-only record and no EXIF focal length; *seed003*: `register_seed003` "
        "(reflectivity + wireframe + HOG + DLT). Success: `registered` and median check-point "
        "error < 4 px at 1632 px width through the camera the result reports; false verdict: "
        "`registered` or graded good/excellent with ≥ 4 px. *mesh*: the same photos registered "
        "to the textured mesh (cached rows).", "",
        "| tier | method | success | target | false verdicts | check-point error, median (px) "
        "| focal error, median | time, median (s) | mesh: success / error (px) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for tier in tiers + ["all"]:
        for method in METHODS:
            v = s.get((tier, method))
            if v is None:
                if method == "seed003" and tier != "all" and meta.get("seed003_missing"):
                    lines.append(f"| {tier} | seed003 | not run (`register_seed003` not "
                                 "importable when measured) | | | | | | |")
                continue
            n = v["n"]
            target = ""
            if method in ("ours", "default", "baseline"):
                t = TARGETS.get(tier) if tier in TARGETS else None
                target = f"≥ {t:.0%}" if t else ""
            elif method == "unknown_focal":
                o = s.get((tier, "ours"))
                target = (f"≥ {0.9 * o['success'] / o['n']:.0%} (90 % of ours)" if o else "")
            focal = (f"{100 * v['focal']:.2f} %" if method in ("unknown_focal", "seed003")
                     and v["focal"] is not None else "–")
            mv = sm.get((tier, method))
            mesh_cell = (f"{mv['success']}/{mv['n']} / {_f(mv['cp_median'])}" if mv else "–")
            label = "both plain tiers" if tier == "all" else tier
            lines.append(
                f"| {label} | {method} | {v['success']}/{n} ({v['success'] / n:.0%}) | {target} | "
                f"{v['false_verdicts']}/{n} | {_f(v['cp_median'])} | {focal} | "
                f"{_f(v['seconds'], '{:.1f}')} | {mesh_cell} |")
    counts = {m: sum(r["method"] == m for r in rows) for m in METHODS}
    lines += ["", "Photos per method (each photo × method is one registration in the same "
              "process, from the same prior): " + ", ".join(
                  f"{m} {n}" for m, n in counts.items() if n) + ".",
              "", "Targets (issue 16):", ""]

    def mark(ok):
        return "✅" if ok else "❌"

    for tier in ("same_light", "changed_light"):
        v = s.get((tier, "ours"))
        if v:
            r = v["success"] / v["n"]
            lines.append(f"- {mark(r >= TARGETS[tier])} `{tier}` ≥ {TARGETS[tier]:.0%}: "
                         f"{v['success']}/{v['n']} ({r:.0%}).")
    a = s.get(("all", "ours"))
    if a:
        r = a["false_verdicts"] / a["n"]
        lines.append(f"- {mark(r <= TARGETS['false_verdicts'])} ≤ 2 % false verdicts: "
                     f"{a['false_verdicts']}/{a['n']} ({r:.0%}).")
        lines.append(f"- {mark(a['cp_median'] is not None and a['cp_median'] <= 1.5)} median "
                     f"check-point error ≤ 1.5 px: {_f(a['cp_median'])} px over the "
                     f"{a['registered']} registered photos.")
    rough = [r for r in rows if r["tier"].startswith("rough") and r["method"] in
             ("ours", "unknown_focal")]
    if rough:
        # Not the tiers; the same false-verdict bound, which is what matters most.
        fv = sum(r["false_verdict"] for r in rough)
        lines.append(f"- {mark(fv <= TARGETS['false_verdicts'] * len(rough))} (harder tiers, "
                     f"rough surface: relief finer than the scan's spacing, phone effects) "
                     f"≤ 2 % false verdicts, ours and unknown_focal: {fv}/{len(rough)}.")
    u = s.get(("all", "unknown_focal"))
    if a and u:
        # Against ours on the same photos (unknown_focal may have run on fewer).
        keys = {(r["tier"], r["scene_seed"], r["photo"]) for r in rows
                if r["method"] == "unknown_focal" and r["tier"] in DEFAULT_TIERS}
        known = [r for r in rows if r["method"] == "ours"
                 and (r["tier"], r["scene_seed"], r["photo"]) in keys]
        k_ok = sum(r["success"] for r in known)
        ratio = (u["success"] / u["n"]) / (k_ok / len(known)) if k_ok else 0.0
        lines.append(f"- {mark(k_ok > 0 and ratio >= 0.9)} unknown focal ≥ 90 % of the "
                     f"known-intrinsics rate (same photos): {u['success']}/{u['n']} against "
                     f"ours' {k_ok}/{len(known)}" + (f" ({ratio:.0%})." if k_ok else "."))
        lines.append(f"- {mark(u['focal'] is not None and u['focal'] <= 0.01)} median focal "
                     f"error ≤ 1 %: {_f(u['focal'] and 100 * u['focal'])} % over its "
                     f"{u['registered']} registered photos.")
    if diag:
        def med(key, sub=None):
            vals = [d[key][sub] if sub else d[key] for d in diag]
            return _median(vals)

        lines += ["", "At the true camera (768 px, medians over the photos): correlation of the "
                  f"intensity render's and the photo's grey levels r = {_f(med('r_grey'))} "
                  f"(relit for the photo's sun, as the pipeline matches it: "
                  f"{_f(med('r_grey_relit'))}), of "
                  f"their gradient magnitudes r = {_f(med('r_gradient'))}; correct keypoint "
                  f"matches (of putative) with Wallis on grey levels "
                  f"{_f(med('matches_grey', 'correct'), '{:.0f}')} (of "
                  f"{_f(med('matches_grey', 'putative'), '{:.0f}')}), on gradient magnitude "
                  f"{_f(med('matches_gradient', 'correct'), '{:.0f}')} (of "
                  f"{_f(med('matches_gradient', 'putative'), '{:.0f}')}).", "",
                  "| tier | seed | photo | r grey | r grey, relit | r gradient | "
                  "correct / putative, grey | correct / putative, gradient |",
                  "|---|---|---|---|---|---|---|---|"]
        for d in diag:
            g, gg = d["matches_grey"], d["matches_gradient"]
            lines.append(f"| {d['tier']} | {d['scene_seed']} | {d['photo']} | {d['r_grey']:.2f} | "
                         f"{_f(d.get('r_grey_relit'))} | {d['r_gradient']:.2f} | {g['correct']} / {g['putative']} | "
                         f"{gg['correct']} / {gg['putative']} |")
    lines += NOTES
    ours = [r for r in rows if r["method"] == "ours"]
    failed = [r for r in ours if r["status"] != "registered"]
    moving = [r for r in failed if any("still moving" in h for h in r.get("hints", []))]
    if failed:
        cps = [r["cp_median_px"] for r in failed]
        unc = [r["uncertainty_px"] for r in failed if r.get("uncertainty_px") is not None]
        near = sum(c < br.SUCCESS_PX for c in cps)
        lines.append(
            f"- *Why ours fails where it does* (from the rows): from the prior (the baseline's "
            f"unmoved poses are {_f(_median([r['cp_median_px'] for r in rows if r['method'] == 'baseline']), '{:.0f}')} px "
            f"off, median), the stages (area matching, edge alignment, mutual information) bring "
            f"the {len(failed)} photos ours does not register to {min(cps):.1f}–{max(cps):.1f} px "
            f"(median {_median(cps):.1f}; {near} of them under 4 px), but {len(moving)} of the "
            f"{len(failed)} end with *the pose was still moving after the last round* (4 rounds, "
            f"0.05° / 0.05 m), and their error estimates are "
            + (f"{min(unc):.1f}–{max(unc):.1f} px." if unc else "missing.")
            + " Relaxing the convergence test is not the answer: before relighting, a pose "
            "8.5 px off (seed 1, changed_light IMG_0001) had an estimate of 3.1 px and would "
            "have become a false verdict.")
    false = [r for r in rows if r["false_verdict"] and r["method"] in ("ours", "unknown_focal")]
    if false:
        stages = sorted({r["winning_stage"] or "–" for r in false})
        unc = [r["uncertainty_px"] for r in false if r.get("uncertainty_px") is not None]
        tiers_ = sorted({r["tier"] for r in false})
        lines.append(
            f"- *The false verdicts* ({len(false)}, {', '.join(tiers_)}): "
            f"{'poses' if len(false) > 1 else 'a pose'} "
            f"{_span([r['cp_median_px'] for r in false])} px off, won by "
            f"{' and '.join(stages)}, whose error {'estimates' if len(false) > 1 else 'estimate'} "
            "said " + (f"{_span(unc)} px" if unc else "nothing")
            + ". " + " ".join(_false_verdict_reasons(false)))
    lines += ["", f"Reproduce: `{meta['command']}` ({meta['cpus']} cores shared with other work, "
              f"Python {meta['python']}; load average {meta['load']}; {meta['wall_min']:.0f} min). "
              f"Per-photo rows: `{meta['rows']}`.", MARK_END]
    return "\n".join(lines)


#: Measured once beside the runs (2026-12-02, 2 cores under load 9–17), kept
#: in the report: what they answer is not in the rows.
NOTES = [
    "",
    "Measured beside the runs (seed 1):",
    "",
    "- *Scan realism, before/after* (scan version 1: flat beds; version 2: the within-bed "
    "texture), `diagnose()` at the true camera on `lidar-s1/` and `lidar-s2/`: grey-level "
    "correlation of the intensity render with the photo 0.28 → 0.34 (same_light IMG_0001), "
    "0.26 → 0.31 (IMG_0002), 0.21 → 0.26 (changed_light IMG_0001); gradient-magnitude "
    "correlation 0.34 → 0.36, 0.30 → 0.32, 0.35 → 0.36. The texture's own correlation with the "
    "albedo's within-bed pattern is 0.5 by construction (`ScanSpec.texture_albedo_correlation`); "
    "at the photo, relief shading under the sun (photo) and under the scanner's beam (cos "
    "incidence) differ and bring it to these values.",
    "- *Keypoints cannot match these renders*: rendered from the **true** camera, SIFT (the "
    "registration's upright RootSIFT, ratio and symmetry tests) found 0–2 correct matches of "
    "1–14 putative ones per photo (table above), on Wallis-filtered grey levels and on "
    "gradient magnitude alike (variants tried on two photos — σ 1–3 px, with and without a 3 × 3 median against "
    "the two stations' interleaved intensities, at 768 and 512 px — gave at most 1). Hence `for_cloud()` runs one "
    "keypoint trial and no search (before relighting, *default* and *ours* gave the same "
    "pose on same_light IMG_0001 — area matching, 3.72 px — default in 78 s after 4 keypoint "
    "trials with 0 3D inliers, ours in 40 s).",
    "- *Relighting the cloud for the photo's sun* (the EXIF capture time's sun; the scan's "
    "intensity holds none, so the render is shaded by its PCA normals and the sun's cast "
    "shadows traced through the surfels): grey-level r at the true camera 0.26 → 0.50–0.57 "
    "(changed_light) and 0.31–0.34 → 0.48–0.52 (same_light; the *relit* column above). "
    "Seed 1, ours, before → after in one process: registered changed_light 1/4 → 4/4 and "
    "same_light 1/4 → 4/4, check points 2.7–8.7 px → 1.4–2.2 px, 22–37 s → 10–14 s per "
    "photo. The SIFT matches stay at 0–5: area matching against the relit render does it.",
    "- *Area matching at the photo's width* (`for_cloud()`: `area.width` 1632, the default "
    "1024), both scenes, same photos and priors, 1024 px → 1632 px: ours 16/16 → 16/16, "
    "median check-point error 1.71 → 1.07 px; unknown_focal (its first 8 photos, 2 per "
    "scene and tier) 8/8 → 7/8, 2.11 → 1.15 px, median focal error 0.82 % → 0.33 % "
    "(the 1024 px rows: `benchmarks/_cache/bench_register_cloud_rows_s{1,2}.json`).",
    "- The splat render's depth lies in front of the true surface (median 9 cm on the "
    "cliff, 24 cm on the gentle ground, 10th percentile 39 cm; same_light IMG_0001): "
    "the lifted points stay on their pixel rays (a pose from perfect 2D matches and the "
    "render's 3D points reprojects the check points within 10⁻⁶ px), so registration is "
    "not biased by it, but 3D positions taken from the render are.",
]


# ------------------------------------------------------------------ main
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true",
                        help="smoke run: scene seed 1, 1 photo of same_light, ours and baseline")
    parser.add_argument("--scenes", type=int, default=2)
    parser.add_argument("--first-seed", type=int, default=1)
    parser.add_argument("--photos", type=int, default=4,
                        help="cameras per scene (the cached scenes have 4)")
    parser.add_argument("--limit", type=int, default=None, help="photos per scene and tier to run")
    parser.add_argument("--tiers", default=",".join(DEFAULT_TIERS), help=f"of {','.join(TIERS)}")
    parser.add_argument("--methods", default=",".join(DEFAULT_METHODS),
                        help=f"of {','.join(METHODS)}")
    parser.add_argument("--cache", type=Path, default=br.DEFAULT_CACHE)
    parser.add_argument("--rows", type=Path, default=None, help="rows JSON (default in the cache)")
    parser.add_argument("--resume", action="store_true",
                        help="keep the rows file's rows and skip what they already hold")
    parser.add_argument("--no-diagnose", action="store_true",
                        help="skip the true-camera similarity measurements")
    parser.add_argument("--dump", type=Path, default=None,
                        help="folder for the photo | render images at the true camera")
    parser.add_argument("--from-rows", type=Path, nargs="+", default=None, metavar="ROWS.json",
                        help="report from earlier runs' rows (and their .meta.json), merged")
    parser.add_argument("--report", type=Path, help="markdown file whose section to rewrite")
    args = parser.parse_args(argv)
    tune_allocator()  # as the CLI and the workers do: the figures are the product's

    if args.from_rows:
        rows, diag, metas = [], [], []
        for path in args.from_rows:
            data = json.loads(path.read_text())
            rows += data["rows"]
            diag += data["diagnosis"]
            metas.append(json.loads(path.with_suffix(".meta.json").read_text()))
        meta = dict(metas[0])
        meta["command"] = " && ".join(m["command"] for m in metas)
        meta["load"] = "; ".join(m["load"] for m in metas)
        meta["wall_min"] = sum(m["wall_min"] for m in metas)
        meta["rows"] = ", ".join(m["rows"] for m in metas)
        meta["points"] = ", ".join(m["points"] for m in metas)
        meta["seed003_missing"] = all(m.get("seed003_missing") for m in metas)
        keys = {(r["tier"], r["scene_seed"], r["photo"]) for r in rows}
        section = report(rows, diag, meta, mesh_rows(args.cache, keys))
        print(section)
        if args.report:
            write_section(args.report, section, MARK_START, MARK_END)
        return 0

    tiers = ["same_light"] if args.quick else [t for t in args.tiers.split(",") if t]
    methods = ["ours", "baseline"] if args.quick else [m for m in args.methods.split(",") if m]
    for t in tiers:
        if t not in TIERS:
            parser.error(f"unknown tier {t!r} (of {', '.join(TIERS)})")
    for m in methods:
        if m not in METHODS:
            parser.error(f"unknown method {m!r} (of {', '.join(METHODS)})")
    n_scenes = 1 if args.quick else args.scenes
    limit = 1 if args.quick else args.limit
    seeds = list(range(args.first_seed, args.first_seed + n_scenes))
    rows_path = (args.rows or args.cache / f"{NAME}_rows{'_quick' if args.quick else ''}.json").resolve()
    rows: list[dict] = []
    diag: list[dict] = []
    if args.resume and rows_path.is_file():
        old = json.loads(rows_path.read_text())
        rows, diag = old["rows"], old["diagnosis"]
    done = {(r["tier"], r["scene_seed"], r["photo"], r["method"]) for r in rows}
    # Diagnoses of an older version (without the relit render's r) are redone.
    diag = [d for d in diag if "r_grey_relit" in d]
    diagnosed = {(d["tier"], d["scene_seed"], d["photo"]) for d in diag}
    seed003_missing = "seed003" in methods and _seed003() is None
    t_start = time.perf_counter()
    points, load_s = [], []

    def save() -> None:
        rows_path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_write(rows_path) as fh:
            json.dump({"rows": rows, "diagnosis": diag}, fh, indent=1)

    with tempfile.TemporaryDirectory(prefix="bench_cloud_") as tmpdir:
        tmp = Path(tmpdir)
        for seed in seeds:
            scene_dir = br.scene_folder(args.cache, "large", seed, args.photos)
            by_scan: dict[Path, list[str]] = {}
            for tier in tiers:
                by_scan.setdefault(scan_path(scene_dir, tier), []).append(tier)
            for laz, scan_tiers in by_scan.items():
                t0 = time.perf_counter()
                scene, engine_s = load_cloud(laz, scene_dir)
                load_s.append(round(time.perf_counter() - t0, 1))
                points.append(scene.n_points)
                print(f"{laz.relative_to(args.cache)}: {scene.n_points:,} points, loaded in "
                      f"{load_s[-1]:.0f} s (normals {engine_s:.0f} s)", flush=True)
                for tier in scan_tiers:
                    photos = sorted(tier_folder(scene_dir, tier).glob("IMG_*.jpg"))[:limit]
                    for photo_path in photos:
                        key = (tier, seed, photo_path.name)
                        if not args.no_diagnose and key not in diagnosed:
                            d = diagnose(scene, photo_path, dump=args.dump)
                            diag.append({"tier": tier, "scene_seed": seed, "photo": photo_path.name, **d})
                            save()
                            print(f"{tier:19s} seed {seed} {photo_path.name} true camera: r grey "
                                  f"{d['r_grey']:.2f} (relit {_f(d['r_grey_relit'])}), r gradient "
                                  f"{d['r_gradient']:.2f}, correct "
                                  f"matches grey {d['matches_grey']['correct']}/"
                                  f"{d['matches_grey']['putative']}, gradient "
                                  f"{d['matches_gradient']['correct']}/"
                                  f"{d['matches_gradient']['putative']}", flush=True)
                        for method in methods:
                            if key + (method,) in done:
                                continue
                            row = evaluate(scene, photo_path, method, tmp)
                            if row is None:
                                continue
                            rows.append({"tier": tier, "scene_seed": seed, "photo": photo_path.name, **row})
                            save()
                            print(f"{tier:19s} seed {seed} {photo_path.name} {method:13s} "
                                  f"{row['status']:10s} {row['grade']:9s} cp {row['cp_median_px']:9.2f} px "
                                  f"(on the scan {row['cp_on_scan_px'] or float('nan'):6.2f}) "
                                  f"focal {100 * row['focal_error']:+6.2f} % {row['seconds']:6.1f} s "
                                  f"trials {row['n_trials']}"
                                  + (" SUCCESS" if row["success"] else "")
                                  + (" FALSE-VERDICT" if row["false_verdict"] else ""), flush=True)
                del scene
    save()
    cmd = "nice -n 19 .venv/bin/python benchmarks/bench_register_cloud.py" + (
        " --quick" if args.quick else "")
    if not args.quick:
        if args.scenes != 2:
            cmd += f" --scenes {args.scenes}"
        if args.rows:
            cmd += f" --rows {args.rows}"
        if args.resume:
            cmd += " --resume"
        if args.first_seed != 1:
            cmd += f" --first-seed {args.first_seed}"
        if args.limit:
            cmd += f" --limit {args.limit}"
        if tiers != list(DEFAULT_TIERS):
            cmd += " --tiers " + ",".join(tiers)
        if methods != list(DEFAULT_METHODS):
            cmd += " --methods " + ",".join(methods)
    if args.report:
        cmd += f" --report {args.report}"
    meta = {
        "scan_version": SCAN_VERSION,
        "points": ", ".join(f"{p / 1e6:.2f} M" for p in points) or "–",
        "load_s": load_s,
        "seed003_missing": seed003_missing,
        "command": cmd,
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
        "load": ", ".join(f"{x:.1f}" for x in os.getloadavg()),
        "wall_min": (time.perf_counter() - t_start) / 60,
        "rows": (str(rows_path.relative_to(HERE.parent)) if HERE.parent in rows_path.parents
                 else str(rows_path)),
    }
    with atomic_write(rows_path.with_suffix(".meta.json")) as fh:
        json.dump(meta, fh, indent=1)
    keys = {(r["tier"], r["scene_seed"], r["photo"]) for r in rows}
    section = report(rows, diag, meta, mesh_rows(args.cache, keys))
    print(section)
    if args.report:
        write_section(args.report, section, MARK_START, MARK_END)
    return 0


if __name__ == "__main__":
    sys.exit(main())

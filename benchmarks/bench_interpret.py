"""Interpretation benchmark: true bed boundaries and faults, drawn on the photos, projected
with the *estimated* poses, against the true 3D traces.

For each photo of the generated sample scenes, every true 3D trace in
``truth_lines.geojson`` (bed boundaries and the fault) is projected into the
photo with the TRUE camera pose; its visible stretches (first hit of the true
camera's ray) become the lines a geologist would draw, in pixels. The photo is
then registered with :func:`napari_imgreg.registration.pipeline.register` from its sensor
prior, and the drawn lines are projected back onto the mesh with the
ESTIMATED pose. We report the 3D distance of the projected points to the true
traces (median, 95th percentile) and the orientation error of the bedding
planes fitted to the bed-boundary traces (true bedding 12°/200°, fault
65°/100°). The same lines projected with the true pose give the method's
floor. The section of ``docs/benchmarks.md`` between the ``bench_interpret``
markers is rewritten (atomically); other sections are kept.

    python benchmarks/bench_interpret.py --report docs/benchmarks.md

Targets (issue 5): median distance ≤ 0.10 m at ~100 m range; median bedding
dip error ≤ 2° (Morago et al. report 3.65° median against a compass).

Issue 14: the lines are also drawn *as a geologist would* (rows "geologist"):
each visible stretch simplified (Douglas–Peucker, 2 px) so it is straight
where the contact looks straight (2-vertex lines) and bent where it crosses
relief, every vertex moved by a ±1.5 px wobble. A trace is *well posed* when
its true 3D stretch leaves the true camera's viewing plane by ≥ 3 times the
drawing's footprint (range × 1.5 px / focal length, RMS). Reported: dips
given to ill-posed traces (must be 0), the median dip error over all dipped
traces (≤ 2°), the share of well-posed traces that keep a dip (≥ 80 %), and
the share of dipped traces whose true error is within 2σ (≥ 90 %), and the
same for plunge/trend. "Before" columns measure the same drawings with
today's vetting (planarity, relief, surface effect; no viewing-plane test).
Registered poses are cached (``--poses``) so reruns skip registration.

Issue 16 (rows "cloud", subsection between the ``bench_interpret_clouds``
markers inside this section): the registration benchmark's scenes that have a
generated terrestrial scan of their surface
(``_cache/large-seed{1,2}-n4-g3-b2/lidar-s<version>/scan.laz``, made by
``bench_lidar_scan.py`` when missing: 2 stations, 1 mrad, 5 mm range noise) are
measured on the mesh and on the cloud with the same photos (``same_light``)
and the same drawn traces: with the pose registered on the mesh on both, and
on the cloud also with the pose registered on the cloud itself (its default
settings, ``RegistrationParams.for_cloud``), as a user with only the scan has
it. Poses are cached beside the others.
``--clouds-only`` reruns that subsection alone.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from napari_imgreg import Scene
from napari_imgreg._atomic import atomic_write
from napari_imgreg.interpret.project import Interpretation, project_interpretations
from napari_imgreg.io.photos import load_photo
from napari_imgreg.prior import prior_for_photo
from napari_imgreg.registration.pipeline import register
from napari_imgreg.sample import load_truth, sample_scene
from napari_imgreg.sample.drawing import (
    JITTER_PX,
    MIN_DRAWN_PX,
    SIMPLIFY_PX,
    densify_polyline,
    hand_drawn,
    visible_stretches,
)
from napari_imgreg.camera import Pose
from napari_imgreg.interpret.structural import (
    FitThresholds,
    fisher_mean,
    fit_line,
    normal_from_dip,
    uniform_along,
    vector_from_plunge_trend,
)
from napari_imgreg.interpret.uncertainty import PoseUncertainty, viewing_plane

from _report import markers, write_section  # noqa: E402  (benchmarks/ is on sys.path)

MARK_START, MARK_END = markers("bench_interpret")
MARK_CLOUD_START, MARK_CLOUD_END = markers("bench_interpret_clouds")
#: Issue 16: scenes of the registration benchmark with a generated scan of their
#: surface (the model the photos were made from), and the photos measured on both.
CACHE = Path(__file__).parent / "_cache"
CLOUD_SCENES = ("large-seed1-n4-g3-b2", "large-seed2-n4-g3-b2")
CLOUD_TIER = "same_light"
TARGET_MEDIAN_M, TARGET_DIP_DEG, PAPER_MEDIAN_DEG = 0.10, 2.0, 3.65
# The drawing (napari_imgreg.sample.drawing, shared with the sample's example
# drawings): MIN_DRAWN_PX, shorter visible stretches are not drawn; JITTER_PX, a
# hand-drawn line's wobble at each vertex (σ, pixels); SIMPLIFY_PX, a geologist's
# line is straight where the contact deviates less than this.
#: The drawing's error the geologist declares (``project --pixel-noise``;
#: the benchmark's ``--pixel-noise``): the default 1.5 px.
DECLARED_PX = (JITTER_PX,)
#: Well posed: the true stretch leaves its viewing plane by at least one drawing
#: footprint (RMS) and was drawn bent; ill posed: drawn straight (2 vertices) or
#: under half a footprint (its bend is lost in the hand's noise). Between: neither.
WELL_POSED_FOOTPRINTS, ILL_POSED_FOOTPRINTS = 1.0, 0.5
#: Today's vetting, for the "before" figures: no viewing-plane test.
BEFORE = FitThresholds(min_view_spread=0.0, min_ray_angle_deg=0.0, require_camera=False)


def _dense(line: np.ndarray, per_m: float = 50.0) -> np.ndarray:
    """A polyline resampled every 2 cm (for point-to-line distances)."""
    return densify_polyline(line, per_m)


def drawn_lines(scene: Scene, intr, pose, truth_lines: dict) -> list[tuple[Interpretation, int]]:
    """What a geologist draws: visible stretches of the true traces, in pixels
    (:func:`napari_imgreg.sample.drawing.visible_stretches`).

    Returns (interpretation, index of the true line) pairs; each
    interpretation's ``truth_xyz`` attribute holds its true 3D stretch.
    """
    out = []
    for stretch in visible_stretches(scene, intr, pose, truth_lines, MIN_DRAWN_PX):
        k = stretch.truth_index
        item = Interpretation("LineString", stretch.pixels,
                              {"label": stretch.label, "truth": k, "id": f"contact{k}",
                               "contact": f"contact{k}"})
        item.truth_xyz = stretch.xyz
        out.append((item, k))
    return out


def _normal_angle(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(math.acos(min(1.0, abs(float(a @ b)))))


def geologist(drawn, rng) -> list:
    """The lines simplified as a hand draws them, with a ±JITTER_PX wobble per vertex."""
    out = []
    for d, k in drawn:
        item = Interpretation("LineString", hand_drawn(d.pixels, rng), d.properties)
        item.truth_xyz = d.truth_xyz
        out.append((item, k))
    return out


def _posedness(xyz: np.ndarray, true_pose, intr) -> float:
    """How far the true stretch leaves the true viewing plane (RMS), in units of
    the drawing's footprint there (range × JITTER_PX / focal length)."""
    if len(xyz) < 3:
        return 0.0
    spread = viewing_plane(xyz, true_pose.center)[1]
    rng = float(np.median(np.linalg.norm(xyz - true_pose.center, axis=1)))
    return spread / (rng * JITTER_PX / intr.fx)


def _trace_truth(item, geology, kind):
    """True plunge/trend of the stretch (its 3D line) and the true plane.

    The line is fitted to the true stretch resampled evenly along its 3D
    length, as ``measure`` fits the projected trace
    (:func:`~napari_imgreg.interpret.structural.uniform_along`): the truth
    file's vertices are denser where the trace bends, and a bent trace's
    best-fit line depends on how it is sampled (up to 2° of trend on the
    large scene's long traces, issue 14), so the two must be sampled alike.
    """
    line = fit_line(uniform_along([item.truth_xyz]))
    g = geology["fault" if kind == "fault" else "bedding"]
    return line, g["dip_deg"], g["dip_direction_deg"]


def _ang(a: float, b: float, period: float = 360.0) -> float:
    return abs((a - b + period / 2) % period - period / 2)


def evaluate(scene, intr, pose, drawn, true_dense, source, geology, true_pose=None,
             pose_unc=None, full=False, declared_px=JITTER_PX, before=True) -> dict:
    from napari_imgreg.interpret.uncertainty import UncertaintyParams

    t0 = time.perf_counter()
    unc = UncertaintyParams(drawing_px=declared_px) if full else UncertaintyParams()
    features = project_interpretations(scene, intr, pose, [d for d, _ in drawn], source=source,
                                       pose_uncertainty=pose_unc, uncertainty=unc)
    elapsed = time.perf_counter() - t0
    checks = []
    dist, ranges, parts = [], [], []
    bed = normal_from_dip(geology["bedding"]["dip_deg"], geology["bedding"]["dip_direction_deg"])
    fault = normal_from_dip(geology["fault"]["dip_deg"], geology["fault"]["dip_direction_deg"])
    orient = {"bed_boundary": [], "fault": []}
    n_traces = {"bed_boundary": 0, "fault": 0}
    covered, drawn_len = 0.0, 0.0
    for f, (d_item, k) in zip(features, drawn):
        tree = true_dense[k]
        kind = "fault" if f.label == "fault" else "bed_boundary"
        n_traces[kind] += 1
        if not f.parts:
            continue
        pts = f.points
        dist.append(tree.query(pts)[0])
        ranges.append(np.linalg.norm(pts - pose.center, axis=1))
        parts.append(len(f.parts))
        covered += f.length_m
        t1 = time.perf_counter()
        m = f.measure()
        measure_s = time.perf_counter() - t1
        if full:
            before_m = f.measure(BEFORE) if before else None
            posed = _posedness(d_item.truth_xyz, true_pose, intr)
            bent = len(d_item.pixels) > 2
            row = {"kind": kind, "well_posed": bent and posed >= WELL_POSED_FOOTPRINTS,
                   "ill_posed": not bent or posed < ILL_POSED_FOOTPRINTS, "posedness": posed,
                   "measure_s": measure_s, "n_vertices": len(d_item.pixels)}
            line, tdip, tddir = _trace_truth(d_item, geology, kind)
            for tag, mm in (("after", m), ("before", before_m)):
                row[f"{tag}_dip"] = abs(mm.dip_deg - tdip) if mm is not None and mm.has_plane else None
            row["dip_sigma"] = m.dip_sigma_deg
            row["ddir_err"] = _ang(m.dip_direction_deg, tddir) if m.has_plane else None
            row["ddir_sigma"] = m.dip_direction_sigma_deg
            if line is not None and m.plunge_deg is not None:
                d0 = vector_from_plunge_trend(line.plunge_deg, line.trend_deg)
                d1 = vector_from_plunge_trend(m.plunge_deg, m.trend_deg)
                if d0 @ d1 < 0:  # a near-horizontal line: compare the same sense
                    row["plunge_err"] = abs(line.plunge_deg + m.plunge_deg)
                    row["trend_err"] = _ang(line.trend_deg + 180.0, m.trend_deg)
                else:
                    row["plunge_err"] = abs(line.plunge_deg - m.plunge_deg)
                    row["trend_err"] = _ang(line.trend_deg, m.trend_deg)
                row["plunge_sigma"], row["trend_sigma"] = m.plunge_sigma_deg, m.trend_sigma_deg
                row["true_plunge"] = line.plunge_deg
            checks.append(row)
        if m.has_plane:
            n = normal_from_dip(m.dip_deg, m.dip_direction_deg)
            true_n = fault if kind == "fault" else bed
            true_dip = geology["fault" if kind == "fault" else "bedding"]["dip_deg"]
            orient[kind].append((abs(m.dip_deg - true_dip), _normal_angle(n, true_n), n))
    d = np.concatenate(dist) if dist else np.zeros(0)
    r = np.concatenate(ranges) if ranges else np.zeros(0)
    return {
        "seconds": elapsed,
        "samples": int(sum(f.samples for f in features)),
        "dist": d,
        "range": r,
        "parts": parts,
        "orient": orient,
        "n_traces": n_traces,
        "features": features,
        "checks": checks,
    }


class _Cached:
    """A registration read back from the pose cache (what the benchmark uses of it)."""

    def __init__(self, d: dict, intrinsics_cls):
        self.status, self.grade = d["status"], d["quality"]["grade"]
        self.intrinsics = intrinsics_cls.from_dict(d["camera"])
        self.pose = Pose.from_dict(d["pose"])
        self.data = d


def _register(scene, name, pt, size, poses: Path | None):
    """Register the photo, or read its result from the cache file ``poses``."""
    from napari_imgreg.camera import Intrinsics

    cache = json.loads(poses.read_text()) if poses and poses.exists() else {}
    key = f"{size}/{name}"
    if key in cache:
        return _Cached(cache[key], Intrinsics), cache[key].get("register_s", math.nan)
    photo = load_photo(pt.photo)
    prior = prior_for_photo(photo, scene)
    t1 = time.perf_counter()
    reg = register(scene, photo.image, prior, photo_name=name)
    reg_s = time.perf_counter() - t1
    if poses:
        d = reg.to_dict()
        d["register_s"] = reg_s
        cache[key] = d
        with atomic_write(poses) as fh:
            json.dump(cache, fh)
    reg.data = reg.to_dict()
    return reg, reg_s


def run(sizes: list[str], photos_limit: int | None, poses: Path | None = None) -> dict:
    out: dict = {"scenes": []}
    for size in sizes:
        folder = sample_scene(size)
        truth = load_truth(folder)
        t0 = time.perf_counter()
        scene = Scene.load(folder / "outcrop.obj", dem=folder / "dem.tif")
        scene.build_engine()
        load_s = time.perf_counter() - t0
        true_dense = [cKDTree(_dense(np.asarray(f["geometry"]["coordinates"], np.float64)))
                      for f in truth.lines["features"]]
        rows = []
        names = sorted(truth.photos)[:photos_limit] if photos_limit else sorted(truth.photos)
        for name in names:
            pt = truth.photos[name]
            drawn = drawn_lines(scene, pt.intrinsics, pt.pose, truth.lines)
            reg, reg_s = _register(scene, name, pt, size, poses)
            pose_unc = PoseUncertainty.from_result(reg.data, reg.intrinsics.fx)
            geo = geologist(drawn, np.random.default_rng(100 + len(rows)))
            geo_est = {px: evaluate(scene, reg.intrinsics, reg.pose, geo, true_dense, name,
                                    truth.geology, pt.pose, pose_unc, full=True, declared_px=px)
                       for px in DECLARED_PX}
            est = evaluate(scene, reg.intrinsics, reg.pose, drawn, true_dense, name, truth.geology)
            floor = evaluate(scene, pt.intrinsics, pt.pose, drawn, true_dense, name, truth.geology)
            rng = np.random.default_rng(len(rows))
            shaky = [(Interpretation("LineString",
                                     d.pixels + rng.normal(0, JITTER_PX, d.pixels.shape),
                                     d.properties), k) for d, k in drawn]
            hand = evaluate(scene, reg.intrinsics, reg.pose, shaky, true_dense, name,
                            truth.geology)
            rows.append({
                "photo": name, "status": reg.status, "grade": reg.grade, "register_s": reg_s,
                "rot_err_deg": reg.pose.rotation_error_deg(pt.pose),
                "pos_err_m": float(np.linalg.norm(reg.pose.center - pt.pose.center)),
                "n_drawn": len(drawn), "est": est, "true": floor, "hand": hand, "geo": geo_est,
                "pose_unc": pose_unc, "features": geo_est[DECLARED_PX[0]]["features"],
            })
            print(f"{size} {name}: {reg.status} ({reg.grade}), rot err "
                  f"{rows[-1]['rot_err_deg']:.3f}°, pos err {rows[-1]['pos_err_m']:.3f} m; "
                  f"{len(drawn)} lines, median dist {np.median(est['dist']):.3f} m "
                  f"(true pose {np.median(floor['dist']):.3f} m), projection {est['seconds']:.3f} s")
        out["scenes"].append({"size": size, "n_triangles": scene.n_faces, "load_s": load_s,
                              "defensible": {px: _defensible(rows, truth.geology, px)
                                             for px in DECLARED_PX},
                              "width": truth.photos[names[0]].intrinsics.width,
                              "height": truth.photos[names[0]].intrinsics.height, "rows": rows})
    return out


def _summary(rows: list[dict], which: str) -> dict:
    registered = [r for r in rows if r["status"] == "registered" or which == "true"]
    d = np.concatenate([r[which]["dist"] for r in registered]) if registered else np.zeros(0)
    rng = np.concatenate([r[which]["range"] for r in registered]) if registered else np.zeros(0)
    bed = [o for r in registered for o in r[which]["orient"]["bed_boundary"]]
    fault = [o for r in registered for o in r[which]["orient"]["fault"]]
    n_bed = sum(r[which]["n_traces"]["bed_boundary"] for r in registered)
    parts = [p for r in registered for p in r[which]["parts"]]
    seconds = sum(r[which]["seconds"] for r in registered)
    samples = sum(r[which]["samples"] for r in registered)
    poles = np.array([o[2] for o in bed]) if bed else np.zeros((0, 3))
    fm = fisher_mean(poles) if len(poles) else None
    return {
        "n_photos": len(registered),
        "n_points": len(d),
        "median_m": float(np.median(d)) if len(d) else math.nan,
        "p95_m": float(np.percentile(d, 95)) if len(d) else math.nan,
        "range_m": float(np.median(rng)) if len(rng) else math.nan,
        "bed_dip_err": float(np.median([o[0] for o in bed])) if bed else math.nan,
        "bed_normal_err": float(np.median([o[1] for o in bed])) if bed else math.nan,
        "bed_normal_p90": float(np.percentile([o[1] for o in bed], 90)) if bed else math.nan,
        "bed_planes": len(bed),
        "bed_traces": n_bed,
        "fault_normal_err": float(np.median([o[1] for o in fault])) if fault else math.nan,
        "fault_planes": len(fault),
        "split_share": float(np.mean([p > 1 for p in parts])) if parts else math.nan,
        "fisher": fm,
        "ms_per_1000_samples": 1000 * seconds / max(samples, 1) * 1000,
    }


def _share(flags) -> float:
    flags = list(flags)
    return float(np.mean(flags)) if flags else math.nan


def _defensible(rows: list[dict], geology: dict, px: float) -> dict:
    """Issue 14's figures over the geologist-drawn traces of registered photos."""
    from napari_imgreg.interpret.project import measure_features, merge_interpretations

    reg = [r for r in rows if r["status"] == "registered"]
    c = [x for r in reg for x in r["geo"][px]["checks"]]
    dipped = [x for x in c if x["after_dip"] is not None]
    dipped_before = [x for x in c if x["before_dip"] is not None]
    well = [x for x in c if x["well_posed"]]
    ill = [x for x in c if x["ill_posed"]]
    lines_ = [x for x in c if x.get("plunge_sigma") is not None]
    trends = [x for x in lines_ if x.get("trend_sigma") is not None and x["true_plunge"] < 80]
    # Contacts seen on several photos, combined (ids contact<k> repeat across photos).
    merged = merge_interpretations(*[r["geo"][px]["features"] for r in reg])
    combined = [m for m in measure_features(merged) if m.id.startswith("contact:")]
    comb_err = []
    for m in combined:
        if m.has_plane:
            g = geology["fault" if m.label == "fault" else "bedding"]
            comb_err.append((abs(m.dip_deg - g["dip_deg"]), m.dip_sigma_deg))
    alone = 0
    for m in combined:
        if m.has_plane:
            members = [x for x in merged if x.properties.get("contact") == m.id.split(":", 1)[1]]
            alone += all(not x.measure().has_plane for x in members)
    return {
        "n": len(c), "n_well": len(well), "n_ill": len(ill),
        "two_vertex": sum(x["n_vertices"] == 2 for x in c),
        "ill_dipped": sum(x["after_dip"] is not None for x in ill),
        "ill_dipped_before": sum(x["before_dip"] is not None for x in ill),
        "n_dipped": len(dipped), "n_dipped_before": len(dipped_before),
        "median_dip": float(np.median([x["after_dip"] for x in dipped])) if dipped else math.nan,
        "median_dip_before": (float(np.median([x["before_dip"] for x in dipped_before]))
                              if dipped_before else math.nan),
        "well_kept": _share(x["after_dip"] is not None for x in well),
        "well_kept_before": _share(x["before_dip"] is not None for x in well),
        "dip_2s": _share(x["after_dip"] <= 2 * x["dip_sigma"] for x in dipped),
        "ddir_2s": _share(x["ddir_err"] <= 2 * x["ddir_sigma"] for x in dipped
                          if x["ddir_sigma"] is not None),
        "plunge_2s": _share(x["plunge_err"] <= 2 * x["plunge_sigma"] for x in lines_),
        "trend_2s": _share(x["trend_err"] <= 2 * x["trend_sigma"] for x in trends),
        "n_lines": len(lines_),
        "median_dip_sigma": float(np.median([x["dip_sigma"] for x in dipped])) if dipped else math.nan,
        "median_plunge_err": float(np.median([x["plunge_err"] for x in lines_])) if lines_ else math.nan,
        "median_plunge_sigma": (float(np.median([x["plunge_sigma"] for x in lines_]))
                                if lines_ else math.nan),
        "measure_ms": 1000 * float(np.median([x["measure_s"] for x in c])) if c else math.nan,
        "n_combined": len(combined), "combined_planes": len(comb_err), "combined_alone": alone,
        "combined_median": float(np.median([e for e, _ in comb_err])) if comb_err else math.nan,
        "combined_2s": _share(e <= 2 * sg for e, sg in comb_err if sg is not None),
        "pose_unc": sorted({r["pose_unc"].source for r in reg}),
    }


#: The issue-14 figures of the previous report (declared 1.5 px), shown beside
#: the new ones: (ill-posed dipped, median dip error, well-posed kept, dip ≤ 2σ,
#: dip direction ≤ 2σ, plunge ≤ 2σ, trend ≤ 2σ).
PREVIOUS = {"small": (0, 1.25, 0.87, 1.00, 0.97, 0.96, 0.92),
            "large": (0, 0.82, 0.85, 0.98, 0.98, 0.96, 0.96)}


def _previous_lines(result: dict) -> list[str]:
    """Before (previous version) → after, declared 1.5 px."""
    out = ["", "Before → after this pass (declared 1.5 px; before = the previous report): the "
           "photos were registered anew by today's pipeline (the previous report's poses were "
           "cached from an older one; rotations moved by up to 0.01°), and their `uncertainty` "
           "is the block-bootstrap estimate (issue 13). With those poses a 3-vertex trace bent "
           "by 0.499 drawing footprints made 3.2° with the viewing rays, passed the 3° limit and "
           "was 8.1° off (3.2 σ), as a trace at 2.9° was before the limit was raised from 2°; "
           "near the rays a plane's dip error outgrows the Monte Carlo's σ, and the limit is "
           "now 4°, which keeps the same well-posed traces.", "",
           "| scene | dips given to ill-posed traces | median dip error | well-posed with a dip "
           "| dip ≤ 2σ | dip direction ≤ 2σ | plunge ≤ 2σ | trend ≤ 2σ |",
           "|---|---|---|---|---|---|---|---|"]
    for sc in result["scenes"]:
        d = sc["defensible"].get(JITTER_PX) or next(iter(sc["defensible"].values()))
        b = PREVIOUS.get(sc["size"])
        if b is None:
            continue
        now = (d["ill_dipped"], d["median_dip"], d["well_kept"], d["dip_2s"], d["ddir_2s"],
               d["plunge_2s"], d["trend_2s"])
        cells = [f"{b[0]} → **{now[0]}**", f"{b[1]:.2f}° → **{now[1]:.2f}°**"]
        cells += [f"{x:.0%} → **{y:.0%}**" for x, y in zip(b[2:], now[2:])]
        out.append(f"| {sc['size']} | " + " | ".join(cells) + " |")
    return out


def _defensible_lines(result: dict) -> list[str]:
    ok = lambda good: "✅" if good else "❌"  # noqa: E731
    out = [
        "",
        "### Measurements a structural geologist can defend (issue 14)",
        "",
        f"Lines drawn as a geologist would: each visible stretch simplified (Douglas–Peucker, "
        f"{SIMPLIFY_PX:g} px) — straight where the contact looks straight (2-vertex lines), bent "
        f"where it crosses relief — and every vertex moved by a ±{JITTER_PX} px wobble; projected "
        "with the estimated pose and `project --pixel-noise` as in the column *declared*: "
        f"{JITTER_PX} px (the default, the wobble alone) and, where given, "
        f"{math.hypot(JITTER_PX, SIMPLIFY_PX / math.sqrt(3)):.1f} px (the wobble and the "
        f"simplification's {SIMPLIFY_PX:g} px / √3 together: this drawing's whole error), "
        "measured by `measure`'s defaults (200 Monte Carlo samples). "
        f"*Well posed*: drawn bent, and the true 3D stretch leaves the true camera's viewing "
        f"plane by ≥ {WELL_POSED_FOOTPRINTS:g} × the drawing's footprint (range × {JITTER_PX} px "
        f"/ focal length), RMS; *ill posed*: drawn straight (2 vertices) or under "
        f"{ILL_POSED_FOOTPRINTS:g} footprint (the bend is lost in the hand's noise); the rest "
        "are neither. *Before* = the "
        "same drawings without the viewing-plane test (planarity, relief, surface effect and "
        "the dip-σ limit only).",
        "",
        "| scene | declared | traces (2-vertex) | well posed / ill posed | dips given to ill-posed traces "
        "(before) | dipped traces (before) | median dip error of all dipped (before) | target "
        "| well-posed traces with a dip (before) | target | dip error ≤ 2σ | dip direction ≤ 2σ "
        "| plunge ≤ 2σ | trend ≤ 2σ | target | median σ dip / plunge | measure time per trace |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    notes = []
    for sc, px in [(sc, px) for sc in result["scenes"] for px in sc["defensible"]]:
        d = sc["defensible"][px]
        cover = min(d["dip_2s"], d["plunge_2s"], d["trend_2s"])
        out.append(
            f"| {sc['size']} | {px:.1f} px | {d['n']} ({d['two_vertex']}) | {d['n_well']} / {d['n_ill']} | "
            f"**{d['ill_dipped']}** ({d['ill_dipped_before']}) {ok(d['ill_dipped'] == 0)} | "
            f"{d['n_dipped']} ({d['n_dipped_before']}) | **{d['median_dip']:.2f}°** "
            f"({d['median_dip_before']:.2f}°) | ≤ 2° {ok(d['median_dip'] <= 2)} | "
            f"**{d['well_kept']:.0%}** ({d['well_kept_before']:.0%}) | ≥ 80 % "
            f"{ok(d['well_kept'] >= 0.8)} | {d['dip_2s']:.0%} | {d['ddir_2s']:.0%} | "
            f"{d['plunge_2s']:.0%} | {d['trend_2s']:.0%} | ≥ 90 % {ok(cover >= 0.9)} | "
            f"{d['median_dip_sigma']:.2f}° / {d['median_plunge_sigma']:.2f}° | "
            f"{d['measure_ms']:.0f} ms |")
        notes.append(
            f"{sc['size']}, {px:.1f} px: {d['n_combined']} contacts drawn on several photos were combined; "
            f"{d['combined_planes']} of them give a plane (median dip error "
            f"{d['combined_median']:.2f}°, {d['combined_2s']:.0%} within 2σ), {d['combined_alone']} "
            f"where no single photo's trace did; pose uncertainty: {', '.join(d['pose_unc'])}")
    out += _previous_lines(result)
    out += ["", "; ".join(notes) + ".",
            "",
            "The σ of each angle is a Monte Carlo over the pose's expected error (RESULT.json "
            "`uncertainty`; a default from the reprojection error when absent), the drawing's "
            "±1.5 px at each vertex and the mesh resolution (0.1 × edge length); see "
            "[interpretation §3](interpretation.md#3-measurements-and-the-stereonet)."]
    return out


def report(result: dict) -> str:
    from napari_imgreg.interpret.structural import dip_dip_direction

    lines = [
        MARK_START,
        "## Interpretation mapping and bedding from traces (issue 5)",
        "",
        "The true 3D bed boundaries and fault traces of each generated scene are drawn on each "
        "photo (projected with the **true** pose, visible stretches only, as pixel polylines), "
        "the photo is registered from its sensor prior with `pipeline.register`, and the "
        "drawn lines are projected onto the mesh with the **estimated** pose (about one ray "
        "per pixel, split where they leave the surface). Distance = each projected point to "
        "the true 3D trace. Bedding error = angle between the plane fitted to a bed-boundary "
        "trace (where the trace crosses enough relief for a well-posed plane) and the true "
        "bedding (12°/200°); |Δdip| = difference of dip angles alone. Rows \"true pose\" "
        "project the same lines with the true camera: the floor set by the drawing and the "
        "mesh. Rows \"drawn ±1.5 px\" add a hand's wobble: every drawn vertex moved by a "
        "Gaussian of σ = 1.5 px (vertices are ~5–10 px apart). Since issue 14 a trace's "
        "plane is given only where the drawing determines it at the declared ±1.5 px (it leaves "
        "the viewing plane, dip σ ≤ 5°), so these rows keep fewer planes than before (the "
        "previous version gave 192/218 small and 243/285 large with |Δdip| 0.08° / 0.04° on "
        "the exact drawings, and 164/218 at 2.39° on the wobbly ones, where the new vetting "
        "gives 60/218 at 1.01°); the issue-14 table below draws as a geologist does.",
        "",
        "| scene | pose | photos | points | range (median) | distance median | 95th pct. | "
        "target | bedding planes / traces | \\|Δdip\\| median | bedding normal error median "
        "(90th pct.) | target | fault normal error |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for sc in result["scenes"]:
        for which, name in (("est", "estimated"), ("hand", f"estimated, drawn ±{JITTER_PX} px"),
                            ("true", "true pose")):
            s = _summary(sc["rows"], which)
            ok_d = "✅" if s["median_m"] <= TARGET_MEDIAN_M else "❌"
            ok_a = "✅" if s["bed_dip_err"] <= TARGET_DIP_DEG else "❌"
            fault = (f"{s['fault_normal_err']:.2f}° ({s['fault_planes']})"
                     if s["fault_planes"] else "– (no plane)")
            lines.append(
                f"| {sc['size']}, {sc['n_triangles']:,} triangles, {sc['width']}×{sc['height']} px"
                f" | {name} | {s['n_photos']} | {s['n_points']:,} | {s['range_m']:.0f} m | "
                f"{s['median_m'] * 100:.1f} cm | {s['p95_m'] * 100:.1f} cm | "
                f"≤ 10 cm {ok_d if which != 'true' else ''} | {s['bed_planes']} / {s['bed_traces']} | "
                f"{s['bed_dip_err']:.2f}° | {s['bed_normal_err']:.2f}° ({s['bed_normal_p90']:.2f}°) | "
                f"≤ 2° {ok_a if which != 'true' else ''} | {fault} |"
            )
    lines += ["", "Per photo (estimated pose):", "",
              "| scene | photo | registration | rotation error | position error | lines drawn | "
              "distance median / 95th pct. | traces split | projection time |",
              "|---|---|---|---|---|---|---|---|---|"]
    for sc in result["scenes"]:
        for r in sc["rows"]:
            e = r["est"]
            split = np.mean([p > 1 for p in e["parts"]]) if e["parts"] else math.nan
            lines.append(
                f"| {sc['size']} | {r['photo']} | {r['status']} ({r['grade']}) | "
                f"{r['rot_err_deg']:.3f}° | {r['pos_err_m'] * 100:.1f} cm | {r['n_drawn']} | "
                f"{np.median(e['dist']) * 100:.1f} / {np.percentile(e['dist'], 95) * 100:.1f} cm | "
                f"{split:.0%} | {e['seconds'] * 1000:.0f} ms ({e['samples']:,} rays) |"
            )
    fisher_lines = []
    for sc in result["scenes"]:
        s = _summary(sc["rows"], "est")
        fm = s["fisher"]
        if fm is not None and fm.alpha95_deg is not None:
            dip, ddir = dip_dip_direction(fm.vector)
            fisher_lines.append(
                f"{sc['size']}: Fisher mean of {fm.n} bedding poles {dip:.2f}°/{ddir:.1f}° "
                f"(true 12°/200°), α95 {fm.alpha95_deg:.2f}°, κ {fm.kappa:.0f}")
    if all("defensible" in sc for sc in result["scenes"]):
        lines += _defensible_lines(result)
    if result.get("clouds_section"):
        lines += ["", result["clouds_section"]]
    lines += [
        "",
        "; ".join(fisher_lines) + ".",
        "",
        f"Targets: median distance ≤ {TARGET_MEDIAN_M * 100:.0f} cm at ~100 m range; median "
        f"bedding dip error ≤ {TARGET_DIP_DEG:.0f}° (Morago et al. report a {PAPER_MEDIAN_DEG}° "
        "median against a compass-clinometer). Traces whose plane was rejected (in their viewing "
        "plane, dip σ > 5°, nearly straight, planarity < 0.75, or within 10° of the outcrop "
        "face) count in \"traces\" but not in \"planes\"; their plunge/trend is still measured.",
        "",
        f"Reproduce: `.venv/bin/python benchmarks/bench_interpret.py --report docs/benchmarks.md` "
        f"(deterministic scenes; Python {platform.python_version()}, NumPy {np.__version__}).",
        MARK_END,
    ]
    return "\n".join(lines)




def samples_table(result: dict, seeds: int = 12) -> str:
    """The Monte Carlo's accuracy/time trade-off on the longest dipped trace:
    the RMS error of the dip σ at N samples against 5000 samples, and the time."""
    from napari_imgreg.interpret.uncertainty import UncertaintyParams

    feats = [f for sc in result["scenes"] for r in sc["rows"] for f in r["features"]
             if f.parts and f.kind == "trace"]
    dipped = [f for f in feats if f.measure().has_plane]
    f = max(dipped or feats, key=lambda f: f.n_points)
    ref = f.measure(uncertainty=UncertaintyParams(samples=5000)).dip_sigma_deg
    out = [f"Trace {f.id} ({f.n_points} points), dip σ {ref:.3f}° at 5000 samples:", "",
           "| samples | error of the σ (RMS) | 1/sqrt(2N) | time per trace |", "|---|---|---|---|"]
    for n in (25, 50, 100, 200, 500, 1000):
        sig, secs = [], []
        for seed in range(seeds):
            t0 = time.perf_counter()
            sig.append(f.measure(uncertainty=UncertaintyParams(samples=n, seed=seed + 1)).dip_sigma_deg)
            secs.append(time.perf_counter() - t0)
        err = float(np.sqrt(np.mean((np.array(sig) / ref - 1.0) ** 2)))
        out.append(f"| {n} | {err:.1%} | {1 / math.sqrt(2 * n):.1%} | "
                   f"{1000 * float(np.median(secs)):.0f} ms |")
    return "\n".join(out)


def stereonet(scene_result: dict, path: Path) -> None:
    """The stereonet of one scene's geologist-drawn traces, measured as `measure` does."""
    from napari_imgreg.interpret.project import measure_features, merge_interpretations
    from napari_imgreg.interpret.structural import save_stereonet

    reg = [r for r in scene_result["rows"] if r["status"] == "registered"]
    features = merge_interpretations(*[r["features"] for r in reg])
    measurements = measure_features(features)
    save_stereonet(path, measurements, colors={"fault": "red", "sandstone": "goldenrod",
                                               "mudstone": "dimgrey"},
                   title=f"{scene_result['size']} sample scene: {len(reg)} photos, "
                   "traces drawn as a geologist would")


# ------------------------------------------------------------ issue 16: clouds
def run_clouds(names: list[str], photos_limit: int | None, poses: Path | None,
               cache: Path = CACHE) -> list[dict]:
    """Each scene's traces on its mesh and on its scan: same photos, poses, drawings.

    The drawn lines are the mesh's visible stretches of the true traces (as
    in :func:`run`); the pose is the photo's registration on the mesh (cached
    in ``poses`` under ``<scene>/<tier>/<photo>``). Each drawing is projected
    onto both surfaces with the estimated and with the true pose, and the
    geologist's version of it (simplified, ±1.5 px) with the estimated pose;
    and onto the cloud with the photo's registration on the cloud (cached
    under ``<scene>/<tier>/cloud-s<scan version>/<photo>``), exact and as the
    geologist drew it.
    """
    import bench_register_cloud as brc

    from napari_imgreg.sample import load_truth as load_photo_truth
    from napari_imgreg.sample.scan import SCAN_VERSION

    out = []
    for name in names:
        folder = cache / name
        if not (folder / "outcrop.obj").is_file():
            print(f"{name}: no cached scene ({folder}); run benchmarks/bench_register.py first")
            continue
        scan = brc.scan_path(folder, CLOUD_TIER)  # scanned now when missing
        geology = json.loads((folder / "geology.json").read_text())
        truth_lines = json.loads((folder / "truth_lines.geojson").read_text())
        photos = sorted((folder / CLOUD_TIER).glob("IMG_*.jpg"))[:photos_limit]
        if not photos:
            print(f"{name}: no photos in {folder / CLOUD_TIER}")
            continue
        t0 = time.perf_counter()
        mesh = Scene.load(folder / "outcrop.obj", dem=folder / "dem.tif")
        mesh.build_engine()
        t1 = time.perf_counter()
        cloud = Scene.load(scan, georef=folder / "georef.json", dem=folder / "dem.tif")
        cloud.build_engine()
        t2 = time.perf_counter()
        true_dense = [cKDTree(_dense(np.asarray(f["geometry"]["coordinates"], np.float64)))
                      for f in truth_lines["features"]]
        rows = []
        first = None
        for k, jpg in enumerate(photos):
            pt = load_photo_truth(jpg)
            first = first or pt
            drawn = drawn_lines(mesh, pt.intrinsics, pt.pose, truth_lines)
            reg, _ = _register(mesh, jpg.name, pt, f"{name}/{CLOUD_TIER}", poses)
            pose_unc = PoseUncertainty.from_result(reg.data, reg.intrinsics.fx)
            creg, creg_s = _register(cloud, jpg.name, pt,
                                     f"{name}/{CLOUD_TIER}/cloud-s{SCAN_VERSION}", poses)
            cloud_unc = PoseUncertainty.from_result(creg.data, creg.intrinsics.fx)
            geo = geologist(drawn, np.random.default_rng(100 + k))
            row = {"photo": jpg.name, "status": reg.status, "grade": reg.grade,
                   "rot_err_deg": reg.pose.rotation_error_deg(pt.pose),
                   "pos_err_m": float(np.linalg.norm(reg.pose.center - pt.pose.center)),
                   "n_drawn": len(drawn),
                   "cloud_reg": {"status": creg.status, "grade": creg.grade,
                                 "rot_err_deg": creg.pose.rotation_error_deg(pt.pose),
                                 "pos_err_m": float(np.linalg.norm(creg.pose.center
                                                                   - pt.pose.center)),
                                 "seconds": creg_s}}
            for kind, surface in (("mesh", mesh), ("cloud", cloud)):
                row[kind] = {
                    "est": evaluate(surface, reg.intrinsics, reg.pose, drawn, true_dense,
                                    jpg.name, geology),
                    "true": evaluate(surface, pt.intrinsics, pt.pose, drawn, true_dense,
                                     jpg.name, geology),
                    "geo": evaluate(surface, reg.intrinsics, reg.pose, geo, true_dense, jpg.name,
                                    geology, pt.pose, pose_unc, full=True,
                                    declared_px=JITTER_PX, before=False),
                }
            row["cloud"]["creg"] = evaluate(cloud, creg.intrinsics, creg.pose, drawn, true_dense,
                                            jpg.name, geology)
            row["cloud"]["cgeo"] = evaluate(cloud, creg.intrinsics, creg.pose, geo, true_dense,
                                            jpg.name, geology, pt.pose, cloud_unc, full=True,
                                            declared_px=JITTER_PX, before=False)
            for kind in ("mesh", "cloud"):
                for part in row[kind].values():  # the features are not needed further
                    part.pop("features", None)
            rows.append(row)
            m, c = row["mesh"]["est"]["dist"], row["cloud"]["est"]["dist"]
            print(f"{name} {jpg.name}: {reg.status} ({reg.grade}), {len(drawn)} lines; median "
                  f"line error mesh {np.median(m):.3f} m, cloud {np.median(c):.3f} m; "
                  f"projection mesh {row['mesh']['est']['seconds']:.2f} s, cloud "
                  f"{row['cloud']['est']['seconds']:.2f} s; registered on the cloud: "
                  f"{creg.status} ({creg.grade}), line error "
                  f"{np.median(row['cloud']['creg']['dist']):.3f} m", flush=True)
        edges = mesh.vertices[mesh.faces[:, 0]] - mesh.vertices[mesh.faces[:, 1]]
        out.append({"name": name, "rows": rows, "n_points": cloud.n_points,
                    "n_triangles": mesh.n_faces, "spacing_m": float(np.median(cloud.spacing)),
                    "mesh_edge_m": float(np.median(np.linalg.norm(edges, axis=1))),
                    "load_s": {"mesh": t1 - t0, "cloud": t2 - t1},
                    "width": first.intrinsics.width, "height": first.intrinsics.height})
    return out


def _cloud_summary(rows: list[dict], kind: str, which: str) -> dict:
    """Line error and dips of one surface kind over the registered photos.

    ``which``: ``est`` (the pose registered on the mesh), ``true``, or
    ``creg`` (the pose registered on the cloud; ``kind`` "cloud" only).
    """
    def status(r):
        return r["cloud_reg"]["status"] if which == "creg" else r["status"]

    reg = [r for r in rows if status(r) == "registered" or which == "true"]
    s = _summary([{"status": status(r), which: r[kind][which]} for r in reg], which)
    out = {"n_photos": len(reg), "n_points": s["n_points"], "median_m": s["median_m"],
           "p95_m": s["p95_m"], "range_m": s["range_m"], "bed_planes": s["bed_planes"],
           "bed_traces": s["bed_traces"], "bed_dip_err": s["bed_dip_err"],
           "split_share": s["split_share"],
           "seconds_per_photo": (float(np.median([r[kind][which]["seconds"] for r in reg]))
                                 if reg else math.nan)}
    if which in ("est", "creg"):
        c = [x for r in reg for x in r[kind]["geo" if which == "est" else "cgeo"]["checks"]]
        dipped = [x for x in c if x["after_dip"] is not None]
        lines_ = [x for x in c if x.get("plunge_sigma") is not None]
        out.update({
            "geo_traces": len(c), "geo_dipped": len(dipped),
            "geo_well": sum(x["well_posed"] for x in c),
            "geo_well_dipped": sum(x["well_posed"] and x["after_dip"] is not None for x in c),
            "geo_ill_dipped": sum(x["ill_posed"] and x["after_dip"] is not None for x in c),
            "geo_median_dip": (float(np.median([x["after_dip"] for x in dipped]))
                               if dipped else math.nan),
            "geo_dip_2s": _share(x["after_dip"] <= 2 * x["dip_sigma"] for x in dipped),
            "geo_median_plunge": (float(np.median([x["plunge_err"] for x in lines_]))
                                  if lines_ else math.nan),
            "geo_median_dip_sigma": (float(np.median([x["dip_sigma"] for x in dipped]))
                                     if dipped else math.nan),
        })
    return out


def _cell(value, fmt: str = "{:.2f}°") -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "–"
    return fmt.format(value)


def cloud_section(clouds: list[dict], photos_limit: int | None = None) -> str:
    """The issue-16 subsection: mesh and cloud side by side, same photos."""
    from napari_imgreg.interpret.on_cloud import CloudProjectionParams

    gap = CloudProjectionParams().gap_spacings
    lines = [
        MARK_CLOUD_START,
        "### Traces on lidar point clouds, beside the mesh (issue 16)",
        "",
        "The registration benchmark's scenes with a generated terrestrial scan of their surface "
        "(`bench_lidar_scan`: 2 stations 55 m in front of the cliff, 1 mrad, 5 mm range noise, "
        "intensity only) and their same-light photos. Each photo's drawn lines (the true traces' "
        "visible stretches, as above) are projected onto the **mesh** (one ray per sample) and "
        "onto the **cloud** (read from one splat render of the photo's camera; split where the "
        f"range jumps by more than {gap:g} point spacings × the range factor plus the oblique "
        "allowance, [interpretation §2](interpretation.md#2-project-onto-the-model)) with the "
        "same pose: the photo's registration on the mesh, and the true pose (the floor); and onto "
        "the cloud with the photo's registration **on the cloud** (from the sensor prior, the "
        "cloud's default settings `RegistrationParams.for_cloud()`: what a geologist with only "
        "the scan gets). Line error = "
        "each projected point's distance to the true 3D trace; |Δdip| = bedding planes from the "
        "exact drawings (as in the first table); *geologist* = the same lines simplified and "
        "drawn ±1.5 px (as in the issue-14 table), declared 1.5 px: traces given a dip, their "
        "median dip error, the share within 2σ, and the median plunge error of all traces. "
        "Facets (polygons) are not benchmarked here: the generated outcrops expose no bedding "
        "surfaces to draw them on (the facet path is tested on known planes, "
        "`tests/test_interpret.py`).",
        "",
        "| scene | surface | pose | photos | line points | line error median | 95th pct. "
        "| traces split | bedding planes / traces | \\|Δdip\\| median | geologist: dipped / "
        "traces (well posed with a dip / well posed; ill posed with a dip) | median dip error "
        "| dip ≤ 2σ | median σ dip | median plunge error | projection per photo |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for sc in clouds:
        for kind in ("mesh", "cloud"):
            surface = (f"mesh, {sc['n_triangles']:,} triangles (edge "
                       f"{sc['mesh_edge_m'] * 100:.0f} cm)" if kind == "mesh" else
                       f"cloud, {sc['n_points']:,} points (spacing {sc['spacing_m'] * 100:.1f} cm)")
            poses_ = [("est", "registered on the mesh"), ("true", "true")]
            if kind == "cloud" and all("cloud_reg" in r for r in sc["rows"]):
                poses_.append(("creg", "**registered on the cloud**"))
            for which, pose_name in poses_:
                s = _cloud_summary(sc["rows"], kind, which)
                if which in ("est", "creg"):
                    geo = (f"{s['geo_dipped']} / {s['geo_traces']} ({s['geo_well_dipped']} / "
                           f"{s['geo_well']}; {s['geo_ill_dipped']})")
                    geo_cells = [geo, f"**{_cell(s['geo_median_dip'])}**",
                                 _cell(s["geo_dip_2s"], "{:.0%}"),
                                 _cell(s["geo_median_dip_sigma"]), _cell(s["geo_median_plunge"])]
                else:
                    geo_cells = ["", "", "", "", ""]
                lines.append(
                    f"| {sc['name']} | {surface} | {pose_name} | {s['n_photos']} | "
                    f"{s['n_points']:,} | **{s['median_m'] * 100:.1f} cm** | "
                    f"{s['p95_m'] * 100:.1f} cm | {_cell(s['split_share'], '{:.0%}')} | "
                    f"{s['bed_planes']} / {s['bed_traces']} | {_cell(s['bed_dip_err'])} | "
                    + " | ".join(geo_cells)
                    + f" | {s['seconds_per_photo'] * 1000:.0f} ms |")
    own = [(sc["name"], _cloud_summary(sc["rows"], "cloud", "creg"),
            _cloud_summary(sc["rows"], "mesh", "est")) for sc in clouds
           if all("cloud_reg" in r for r in sc["rows"])]
    if own:
        lines += ["", "With only the scan (its own registration): "
                  + "; ".join(f"{n}: {c['n_photos']} photos registered, line error median "
                              f"{c['median_m'] * 100:.1f} cm (the mesh's own "
                              f"{m['median_m'] * 100:.1f} cm), geologist's dips "
                              f"{_cell(c['geo_median_dip'])} ({_cell(m['geo_median_dip'])})"
                              for n, c, m in own)
                  + f" — targets: line error ≤ {TARGET_MEDIAN_M * 100:.0f} cm, dip error ≤ "
                  f"{TARGET_DIP_DEG:g}° "
                  + ("✅" if all(c["median_m"] <= TARGET_MEDIAN_M
                               and c["geo_median_dip"] <= TARGET_DIP_DEG for _, c, _ in own)
                     else "❌")
                  + ". The cloud registration's residual (about 1 px, `bench_register_cloud`) "
                  "is a few centimetres at these ranges: it, not the splat surface (the true-pose "
                  "rows), sets the line error; the traces' dips hold, and fewer of them are "
                  "given one, as their σ includes the larger pose uncertainty."]
    lines += ["", "Per photo (median line error on the mesh and on the cloud with the pose "
              "registered on the mesh; on the cloud with the pose registered on the cloud):", "",
              "| scene | photo | registration on the mesh | rotation error | position error "
              "| registration on the cloud | rotation error | position error | lines drawn "
              "| mesh | cloud | cloud, its own pose |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for sc in clouds:
        for r in sc["rows"]:
            c = r.get("cloud_reg")
            own = (f"{c['status']} ({c['grade']}) | {c['rot_err_deg']:.3f}° | "
                   f"{c['pos_err_m'] * 100:.1f} cm" if c else "– | – | –")
            own_err = (f"{np.median(r['cloud']['creg']['dist']) * 100:.1f} cm"
                       if c and c["status"] == "registered" else "–")
            lines.append(
                f"| {sc['name']} | {r['photo']} | {r['status']} ({r['grade']}) | "
                f"{r['rot_err_deg']:.3f}° | {r['pos_err_m'] * 100:.1f} cm | {own} | "
                f"{r['n_drawn']} | {np.median(r['mesh']['est']['dist']) * 100:.1f} cm | "
                f"{np.median(r['cloud']['est']['dist']) * 100:.1f} cm | {own_err} |")
    loads = "; ".join(f"{sc['name']}: mesh {sc['load_s']['mesh']:.1f} s, cloud "
                      f"{sc['load_s']['cloud']:.1f} s" for sc in clouds)
    lines += ["", f"Load and engine build (the cloud's PCA normals from their cache beside the "
              f"scan, or computed once and cached): {loads}. "
              "Times on the shared 2-core machine under `nice`; the cloud's projection time "
              "includes its one render of the photo's camera.",
              "",
              "Reproduce: `.venv/bin/python benchmarks/bench_interpret.py --clouds-only "
              + (f"--photos {photos_limit} " if photos_limit else "")
              + "--report docs/benchmarks.md` (the scenes and scans cached by `bench_register.py` and "
              "`bench_lidar_scan.py`; the registrations cached in `_cache/interpret_poses.json`).",
              MARK_CLOUD_END]
    return "\n".join(lines)


def _existing_cloud_section(path: Path | None) -> str | None:
    """The clouds subsection already in the report (kept when not rerun)."""
    if path is None or not path.exists():
        return None
    text = path.read_text(encoding="utf-8")
    if MARK_CLOUD_START in text and MARK_CLOUD_END in text:
        body = text.split(MARK_CLOUD_START, 1)[1].split(MARK_CLOUD_END, 1)[0]
        return MARK_CLOUD_START + body + MARK_CLOUD_END
    return None


def write_cloud_section(path: Path, section: str) -> None:
    """Put the clouds subsection inside this benchmark's section (atomically)."""
    text = path.read_text(encoding="utf-8") if path.exists() else ""
    if MARK_CLOUD_START in text and MARK_CLOUD_END in text:
        write_section(path, section, MARK_CLOUD_START, MARK_CLOUD_END)
        return
    if MARK_END not in text:
        raise SystemExit(f"{path}: no {MARK_END} marker to put the clouds subsection before")
    text = text.replace(MARK_END, section + "\n" + MARK_END, 1)
    with atomic_write(path, encoding="utf-8") as fh:
        fh.write(text)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="+", default=["small", "large"],
                        choices=["small", "large"])
    parser.add_argument("--photos", type=int, help="at most this many photos per scene")
    parser.add_argument("--report", type=Path, help="markdown file to update")
    parser.add_argument("--json", type=Path, help="also write the summary figures")
    parser.add_argument("--poses", type=Path, default=Path(__file__).parent / "_cache" /
                        "interpret_poses.json",
                        help="cache of the registrations (RESULT.json bodies) so reruns skip "
                        "registering; delete it to re-register")
    parser.add_argument("--pixel-noise", type=float, nargs="+",
                        default=[JITTER_PX, math.hypot(JITTER_PX, SIMPLIFY_PX / math.sqrt(3))],
                        help="drawing errors declared to `project` for the geologist rows "
                        "(default 1.5 px, the wobble, and 1.9 px, wobble and simplification)")
    parser.add_argument("--stereonet", type=Path,
                        help="also draw the stereonet of the first scene's geologist-drawn traces "
                        "(all photos, contacts combined; the image of docs/interpretation.md)")
    parser.add_argument("--samples-table", action="store_true",
                        help="also print the Monte Carlo accuracy/time table")
    parser.add_argument("--clouds", nargs="*", default=list(CLOUD_SCENES),
                        help="issue 16: cached scenes measured on their scan beside their mesh "
                        "(default: %(default)s; none: keep the report's subsection)")
    parser.add_argument("--clouds-only", action="store_true",
                        help="measure only the cloud scenes and rewrite only their subsection")
    args = parser.parse_args()
    from napari_imgreg._allocator import tune_allocator

    tune_allocator()  # the product's allocator settings: figures as the CLI's
    global DECLARED_PX
    DECLARED_PX = tuple(args.pixel_noise)
    clouds = cloud_text = None
    if args.clouds:
        clouds = run_clouds(args.clouds, args.photos, args.poses)
        cloud_text = cloud_section(clouds, args.photos) if clouds else None
    if args.clouds_only:
        if cloud_text is None:
            raise SystemExit("no cloud scene was measured")
        print(cloud_text)
        if args.report:
            write_cloud_section(args.report, cloud_text)
        if args.json:
            with atomic_write(args.json) as fh:
                json.dump({sc["name"]: {f"{kind}_{which}": _cloud_summary(sc["rows"], kind, which)
                                        for kind, which in (("mesh", "est"), ("mesh", "true"),
                                                            ("cloud", "est"), ("cloud", "true"),
                                                            ("cloud", "creg"))}
                           for sc in clouds}, fh, indent=2)
        return
    result = run(args.sizes, args.photos, args.poses)
    result["clouds_section"] = cloud_text or _existing_cloud_section(args.report)
    section = report(result)
    print(section)
    if args.samples_table:
        print(samples_table(result))
    if args.stereonet:
        stereonet(result["scenes"][0], args.stereonet)
    if args.report:
        write_section(args.report, section, MARK_START, MARK_END)
    if args.json:
        summary = {sc["size"]: {w: {k: v for k, v in _summary(sc["rows"], w).items() if k != "fisher"}
                                for w in ("est", "hand", "true")} for sc in result["scenes"]}
        for sc in result["scenes"]:
            summary[sc["size"]]["defensible"] = {f"{px:.2f}": d for px, d in sc["defensible"].items()}
        with atomic_write(args.json) as fh:
            json.dump(summary, fh, indent=2)


if __name__ == "__main__":
    main()

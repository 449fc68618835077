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
from napari_imgreg.interpret.structural import fisher_mean, normal_from_dip

from _report import markers, write_section  # noqa: E402  (benchmarks/ is on sys.path)

MARK_START, MARK_END = markers("bench_interpret")
TARGET_MEDIAN_M, TARGET_DIP_DEG, PAPER_MEDIAN_DEG = 0.10, 2.0, 3.65
MIN_DRAWN_PX = 30.0  # shorter visible stretches are not drawn
JITTER_PX = 1.5  # a hand-drawn line: each vertex off by this much (σ, pixels)


def _dense(line: np.ndarray, per_m: float = 50.0) -> np.ndarray:
    """A polyline resampled every 2 cm (for point-to-line distances)."""
    out = [line[:1]]
    for a, b in zip(line[:-1], line[1:]):
        n = max(1, int(math.ceil(np.linalg.norm(b - a) * per_m)))
        out.append(a + (b - a) * (np.arange(1, n + 1) / n)[:, None])
    return np.concatenate(out)


def drawn_lines(scene: Scene, intr, pose, truth_lines: dict) -> list[tuple[Interpretation, int]]:
    """What a geologist draws: visible stretches of the true traces, in pixels.

    Returns (interpretation, index of the true line) pairs.
    """
    out = []
    for k, feat in enumerate(truth_lines["features"]):
        xyz = _dense(np.asarray(feat["geometry"]["coordinates"], np.float64), per_m=2.0)
        px = pose.project(intr, xyz)
        inside = np.isfinite(px).all(axis=1)
        inside &= (px[:, 0] >= 0) & (px[:, 1] >= 0)
        inside &= (px[:, 0] <= intr.width - 1) & (px[:, 1] <= intr.height - 1)
        if inside.sum() < 2:
            continue
        # Visible: the true camera's ray through the point first meets the surface there.
        origin, dirs = pose.rays(intr, px[inside])
        hits = scene.cast_rays(origin, dirs)
        rng = np.linalg.norm(xyz[inside] - origin, axis=1)
        vis = np.zeros(len(xyz), bool)
        vis[np.where(inside)[0]] = hits.hit & (np.abs(hits.distance - rng) < 0.02 + 0.002 * rng)
        # Runs of visible points are drawn as separate lines.
        edges = np.flatnonzero(np.diff(np.concatenate([[0], vis.astype(int), [0]])))
        for a, b in zip(edges[::2], edges[1::2]):
            seg = px[a:b]
            if len(seg) >= 2 and np.linalg.norm(np.diff(seg, axis=0), axis=1).sum() >= MIN_DRAWN_PX:
                props = feat["properties"]
                # A bed boundary is drawn as the base of the bed above it.
                label = "fault" if props["label"] == "fault" else props.get("above", "sandstone")
                out.append((Interpretation("LineString", seg, {"label": label, "truth": k}), k))
    return out


def _normal_angle(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(math.acos(min(1.0, abs(float(a @ b)))))


def evaluate(scene, intr, pose, drawn, true_dense, source, geology) -> dict:
    t0 = time.perf_counter()
    features = project_interpretations(scene, intr, pose, [d for d, _ in drawn], source=source)
    elapsed = time.perf_counter() - t0
    dist, ranges, parts = [], [], []
    bed = normal_from_dip(geology["bedding"]["dip_deg"], geology["bedding"]["dip_direction_deg"])
    fault = normal_from_dip(geology["fault"]["dip_deg"], geology["fault"]["dip_direction_deg"])
    orient = {"bed_boundary": [], "fault": []}
    n_traces = {"bed_boundary": 0, "fault": 0}
    covered, drawn_len = 0.0, 0.0
    for f, (_, k) in zip(features, drawn):
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
        m = f.measure()
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
    }


def run(sizes: list[str], photos_limit: int | None) -> dict:
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
            photo = load_photo(pt.photo)
            prior = prior_for_photo(photo, scene)
            t1 = time.perf_counter()
            reg = register(scene, photo.image, prior, photo_name=name)
            reg_s = time.perf_counter() - t1
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
                "n_drawn": len(drawn), "est": est, "true": floor, "hand": hand,
            })
            print(f"{size} {name}: {reg.status} ({reg.grade}), rot err "
                  f"{rows[-1]['rot_err_deg']:.3f}°, pos err {rows[-1]['pos_err_m']:.3f} m; "
                  f"{len(drawn)} lines, median dist {np.median(est['dist']):.3f} m "
                  f"(true pose {np.median(floor['dist']):.3f} m), projection {est['seconds']:.3f} s")
        out["scenes"].append({"size": size, "n_triangles": scene.n_faces, "load_s": load_s,
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
        "Gaussian of σ = 1.5 px (vertices are ~5–10 px apart).",
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
    lines += [
        "",
        "; ".join(fisher_lines) + ".",
        "",
        f"Targets: median distance ≤ {TARGET_MEDIAN_M * 100:.0f} cm at ~100 m range; median "
        f"bedding dip error ≤ {TARGET_DIP_DEG:.0f}° (Morago et al. report a {PAPER_MEDIAN_DEG}° "
        "median against a compass-clinometer). Traces whose plane was rejected (nearly straight, "
        "planarity < 0.75, or within 10° of the outcrop face) count in \"traces\" but not in "
        "\"planes\"; their plunge/trend is still measured.",
        "",
        f"Reproduce: `.venv/bin/python benchmarks/bench_interpret.py --report docs/benchmarks.md` "
        f"(deterministic scenes; Python {platform.python_version()}, NumPy {np.__version__}).",
        MARK_END,
    ]
    return "\n".join(lines)




def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="+", default=["small", "large"],
                        choices=["small", "large"])
    parser.add_argument("--photos", type=int, help="at most this many photos per scene")
    parser.add_argument("--report", type=Path, help="markdown file to update")
    parser.add_argument("--json", type=Path, help="also write the summary figures")
    args = parser.parse_args()
    result = run(args.sizes, args.photos)
    section = report(result)
    print(section)
    if args.report:
        write_section(args.report, section, MARK_START, MARK_END)
    if args.json:
        summary = {sc["size"]: {w: {k: v for k, v in _summary(sc["rows"], w).items() if k != "fisher"}
                                for w in ("est", "hand", "true")} for sc in result["scenes"]}
        with atomic_write(args.json) as fh:
            json.dump(summary, fh, indent=2)


if __name__ == "__main__":
    main()

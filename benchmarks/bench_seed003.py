"""Seed 003's own registration path on the generated terrestrial scans (issue 16).

For each photo of a tier of a benchmark scene, :func:`register_seed003`
(reflectivity + wireframe views, SIFT + oriented multi-scale HOG, six-point
DLT, iterated) is run against the scene's simulated scan
(``<scene>/lidar-s1/scan.laz``, made by ``bench_lidar_scan.py``) from the
photo's sensor prior, and scored against the check points of
``IMG_*.truth.json``: a *success* is a ``registered`` result whose median
check-point error (projected through the camera the result reports, its
estimated focal length included, px at 1632 px width) is below 4 px, as in
``bench_register.py``.

Beside each registration, the diagnosis of why it fails where it does: the
HOG matches of one round rendered from the **prior** and one rendered from
the **true camera** (what the views can match at best), each match counted
*correct* when its render point's 3D point, projected by the true camera,
falls within 4 px (at 1632 px width) of its photo point — per view pair.
``--images DIR`` writes, per photo, the photo's and the render's views side
by side with the matches of the true-camera round drawn (green correct, red
wrong).

    .venv/bin/python benchmarks/bench_seed003.py                       # seed 1, same light
    .venv/bin/python benchmarks/bench_seed003.py --photos 1 --images /tmp/s003

The figures in ``docs/benchmarks.md`` (section ``bench_seed003``)::

    .venv/bin/python benchmarks/bench_seed003.py \
        --scan benchmarks/_cache/large-seed1-n4-g3-b2/lidar-s2/scan.laz \
        --rows benchmarks/_cache/bench_seed003_rows_s2.json
    .venv/bin/python benchmarks/bench_seed003.py --mesh --no-masks --upright \
        --rows benchmarks/_cache/bench_seed003_rows_mesh_nomask.json
    .venv/bin/python benchmarks/bench_seed003.py --photos 2 --compare-pipeline \
        --scan benchmarks/_cache/large-seed1-n4-g3-b2/lidar-s2/scan.laz
    .venv/bin/python benchmarks/bench_seed003.py --from-rows \
        benchmarks/_cache/bench_seed003_rows_s2.json \
        --notes benchmarks/_cache/bench_seed003_notes.md --report docs/benchmarks.md

(``--compare-pipeline``: the default cloud pipeline's keypoint trials with and
without ``RegistrationParams.lidar_views``; ``--mesh``: the scene's textured
mesh in place of the scan; ``--no-masks``: keypoints anywhere.) Every run
calls ``tune_allocator()`` first, as the product does.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _report import markers, write_section  # noqa: E402

from napari_imgreg import Scene  # noqa: E402
from napari_imgreg.scene import size_text  # noqa: E402
from napari_imgreg._allocator import tune_allocator  # noqa: E402
from napari_imgreg._atomic import atomic_write  # noqa: E402
from napari_imgreg.io.photos import load_photo  # noqa: E402
from napari_imgreg.prior import prior_for_photo  # noqa: E402
from napari_imgreg.registration.lidar_views import (  # noqa: E402
    LidarViewParams,
    photo_views,
    render_views,
)
from napari_imgreg.registration.seed003 import (  # noqa: E402
    Seed003Params,
    register_seed003,
    scene_planes,
    seed003_matches,
)
from napari_imgreg.sample import load_truth  # noqa: E402

HERE = Path(__file__).resolve().parent
DEFAULT_SCENE = HERE / "_cache" / "large-seed1-n4-g3-b2"
MARK_START, MARK_END = markers("bench_seed003")
REFERENCE_WIDTH = 1632
SUCCESS_PX = 4.0


def _cp(pose, camera, truth) -> np.ndarray:
    """Check-point errors through ``camera`` (the one a result reports), px at 1632 px."""
    err = np.linalg.norm(pose.project(camera, truth.check_xyz) - truth.check_pixels, axis=1)
    return np.where(np.isfinite(err), err, 1e6) * REFERENCE_WIDTH / camera.width


def _correct(m, truth) -> np.ndarray:
    """Per match: its 3D point lands within 4 px (1632 px) of its photo point in the truth."""
    c = m.correspondences
    proj = truth.pose.project(truth.intrinsics, np.nan_to_num(c.xyz, nan=0.0))
    err = np.linalg.norm(proj - c.photo_points, axis=1) * REFERENCE_WIDTH / truth.intrinsics.width
    return np.isfinite(c.xyz).all(axis=1) & (err < SUCCESS_PX)


def diagnose(scene, photo, camera, pose, truth, params) -> dict:
    m = seed003_matches(scene, photo, camera, pose, params)
    ok = _correct(m, truth)
    c = m.correspondences
    out = {"points_photo": m.counts["points_photo"], "points_render": m.counts["points_render"]}
    for name in params.pairs:
        sel = m.source == name
        out[name] = {"matches": int(sel.sum()), "correct": int((ok & sel).sum()),
                     "checked": int((c.feature_inlier & sel).sum()),
                     "checked_correct": int((c.feature_inlier & ok & sel).sum()),
                     "lifted": int((c.lifted & sel).sum())}
    return out, m, ok


def match_image(scene, photo, m, ok, params, path: Path) -> None:
    """Photo views (top) beside render views (bottom), matches drawn."""
    import cv2

    r = m.rendered
    small = cv2.resize(photo, (r.shape[1], r.shape[0]), interpolation=cv2.INTER_AREA)
    p_imgs, p_mask = photo_views(small, params.views, None, params.pairs)
    r_imgs, r_mask, _ = render_views(r, scene_planes(scene, params.views, params.seed),
                                     params.views, params.pairs)
    rows = []
    scale = r.shape[1] / photo.shape[1]
    c = m.correspondences
    for name in params.pairs:
        a = cv2.cvtColor(p_imgs[name], cv2.COLOR_GRAY2BGR)
        b = cv2.cvtColor(r_imgs[name], cv2.COLOR_GRAY2BGR)
        a[~p_mask] //= 3
        b[~r_mask] //= 3
        pair = np.hstack([a, b])
        sel = np.flatnonzero(m.source == name)
        for i in sel:
            pa = (c.photo_points[i] + 0.5) * scale - 0.5
            pb = (c.render_points[i] + 0.5) * scale - 0.5 + np.array([a.shape[1], 0])
            colour = (0, 200, 0) if ok[i] else (0, 0, 220)
            cv2.line(pair, tuple(int(v) for v in pa), tuple(int(v) for v in pb), colour, 1,
                     cv2.LINE_AA)
        cv2.putText(pair, f"{name}: {int(ok[sel].sum())}/{len(sel)} correct", (8, 24),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.7, (255, 255, 0), 2)
        rows.append(pair)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.vstack(rows))



def evaluate(scene, photo_path: Path, params: Seed003Params, images: Path | None) -> dict:
    truth = load_truth(photo_path)
    photo = load_photo(photo_path)
    prior = prior_for_photo(photo, scene)
    t0 = time.perf_counter()
    reg = register_seed003(scene, photo.image, prior, params, photo_name=photo_path.name)
    seconds = time.perf_counter() - t0
    cp = _cp(reg.pose, reg.intrinsics, truth)
    cp_prior = _cp(prior.pose, prior.intrinsics, truth)
    cp_med = float(np.median(cp))
    registered = reg.status == "registered"
    claims = registered or reg.grade in ("good", "excellent")
    at_prior, _, _ = diagnose(scene, photo.image, prior.intrinsics, prior.pose, truth, params)
    at_truth, m, ok = diagnose(scene, photo.image, truth.intrinsics, truth.pose, truth, params)
    if images is not None:
        match_image(scene, photo.image, m, ok, params, images / f"{photo_path.stem}_truth_matches.png")
    return {
        "photo": photo_path.name,
        "status": reg.status, "grade": reg.grade, "Q": round(reg.q, 3),
        "success": bool(registered and cp_med < SUCCESS_PX),
        "false_verdict": bool(claims and cp_med >= SUCCESS_PX),
        "cp_median_px": round(cp_med, 2),
        "cp_prior_px": round(float(np.median(cp_prior)), 1),
        "focal_error": round(reg.intrinsics.fx / truth.intrinsics.fx - 1.0, 4),
        "estimated": list(reg.intrinsics.estimated),
        "inliers_3d": reg.metrics.get("inliers_3d"),
        "residual_flow_px": reg.metrics.get("residual_flow_px"),
        "solver": reg.metrics.get("seed003_solver"),
        "rounds": reg.trials[0].rounds,
        "seconds": round(seconds, 2),
        "timings_s": {k: round(v, 2) for k, v in reg.timings_s.items()},
        "uncertainty_px": (None if reg.uncertainty is None
                           else reg.uncertainty.to_dict()["reprojection_px"]),
        "hints": reg.hints,
        "matches_at_prior": at_prior,
        "matches_at_truth": at_truth,
    }


def _lidar_params(on: bool):
    """The default pipeline's cloud settings, keypoint trials only (no search,
    no robust stages: what the lidar views would add to), with the lidar views
    on or off."""
    import dataclasses

    from napari_imgreg.registration.params import RegistrationParams

    base = RegistrationParams.for_cloud()
    fields = {f.name: getattr(base, f.name) for f in dataclasses.fields(base)}
    fields.update(search_prior=False, sun_relight=False, edge_align=False, dense_refine=False,
                  area_match=False)
    fields.update(lidar_views=on)
    return RegistrationParams(**fields)


def compare_pipeline(scene, photo_path: Path) -> list[dict]:
    """The keypoint trials of the default cloud pipeline with and without the lidar views."""
    from napari_imgreg.registration.pipeline import register

    truth = load_truth(photo_path)
    photo = load_photo(photo_path)
    prior = prior_for_photo(photo, scene)
    out = []
    for on in (False, True):
        t0 = time.perf_counter()
        reg = register(scene, photo.image, prior, _lidar_params(on), photo_path.name)
        cp = float(np.median(_cp(reg.pose, reg.intrinsics, truth)))
        lv = [t.metrics.get("lidar_view_matches") for t in reg.trials]
        out.append({"photo": photo_path.name, "lidar_views": on, "status": reg.status,
                    "grade": reg.grade, "cp_median_px": round(cp, 2),
                    "success": bool(reg.registered and cp < SUCCESS_PX),
                    "inliers_3d": reg.metrics.get("inliers_3d"),
                    "lidar_view_matches": lv, "trials": len(reg.trials),
                    "seconds": round(time.perf_counter() - t0, 1)})
        print(json.dumps(out[-1]), flush=True)
    return out


def report(rows: list[dict], meta: dict) -> str:
    n = len(rows)
    succ = sum(r["success"] for r in rows)
    false = sum(r["false_verdict"] for r in rows)
    lines = [MARK_START, "## Seed 003's own path on the generated scans (`bench_seed003.py`)", "",
             f"Scene `{meta['scene']}`, scan `{meta['scan']}` ({meta['n_points']:,} points), tier "
             f"`{meta['tier']}`, {n} photos; `register_seed003` from the sensor prior "
             f"(pairs {', '.join(meta['pairs'])}, match width {meta['match_width']} px). "
             f"{meta['machine']}.", "",
             f"Success {succ}/{n}, false verdicts {false}/{n}.", "",
             "| photo | status | grade | check-point px (prior) | focal error | 3D inliers | "
             "correct / matches at the prior (refl., wire.) | at the true camera (refl., wire.) "
             "| s |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        def cm(d):
            return ", ".join(f"{d[k]['correct']}/{d[k]['matches']}" for k in meta["pairs"])
        # The focal length is estimated only when a camera was solved.
        focal = f"{100 * r['focal_error']:+.1f} %" if r["estimated"] else "–"
        lines.append(f"| {r['photo']} | {r['status']} | {r['grade']} | {r['cp_median_px']:.1f} "
                     f"({r['cp_prior_px']:.0f}) | {focal} | "
                     f"{r['inliers_3d']} | {cm(r['matches_at_prior'])} | "
                     f"{cm(r['matches_at_truth'])} | {r['seconds']:.0f} |")
    at_truth = sum(r["matches_at_truth"][k]["correct"] for r in rows for k in meta["pairs"])
    all_truth = sum(r["matches_at_truth"][k]["matches"] for r in rows for k in meta["pairs"])
    lines += ["", "A match is correct when its render point's 3D point, projected by the true "
              "camera, lies within 4 px (1632 px width) of its photo point.", "",
              f"Planes: {meta['planes']} ({100 * meta['planes_on_points']:.0f} % of the points), "
              f"{meta['steep_planes']} of them steeper than 45° (the rest is ground and talus): "
              f"{meta['planes_s']:.0f} s.",
              f"From the true camera {at_truth} of {all_truth} matches are correct."]
    if meta.get("notes"):
        lines += ["", meta["notes"]]
    lines.append(MARK_END)
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", type=Path, default=DEFAULT_SCENE)
    ap.add_argument("--scan", type=Path, default=None, help="default <scene>/lidar-s1/scan.laz")
    ap.add_argument("--tier", default="same_light")
    ap.add_argument("--photos", type=int, default=4)
    ap.add_argument("--pairs", default="reflectivity,wireframe")
    ap.add_argument("--match-width", type=int, default=768)
    ap.add_argument("--rounds", type=int, default=Seed003Params().max_rounds)
    ap.add_argument("--geometric-check", default="fundamental")
    ap.add_argument("--upright", action="store_true", help="HOG at orientation 0")
    ap.add_argument("--no-masks", action="store_true",
                    help="keypoints anywhere (no LSD mask in the photo, no plane mask in the render)")
    ap.add_argument("--mesh", action="store_true",
                    help="register against the scene's textured mesh (outcrop.obj) instead of a scan")
    ap.add_argument("--images", type=Path, default=None)
    ap.add_argument("--rows", type=Path, default=None)
    ap.add_argument("--report", type=Path, default=None)
    ap.add_argument("--from-rows", type=Path, default=None,
                    help="write the report from a --rows file instead of running")
    ap.add_argument("--compare-pipeline", action="store_true",
                    help="the default cloud pipeline's keypoint trials with and without the "
                         "lidar views (RegistrationParams.lidar_views) instead")
    ap.add_argument("--notes", type=Path, default=None,
                    help="a paragraph (markdown file) added to the report's section")
    args = ap.parse_args(argv)
    if args.from_rows:
        doc = json.loads(args.from_rows.read_text())
        if args.notes:
            doc["meta"]["notes"] = args.notes.read_text().strip()
        text = report(doc["rows"], doc["meta"])
        print(text)
        if args.report:
            write_section(args.report, text, MARK_START, MARK_END)
        return 0
    tune_allocator()
    args.scene = args.scene.resolve()
    scan = (args.scan or args.scene / ("outcrop.obj" if args.mesh else "lidar-s1/scan.laz")).resolve()
    t0 = time.perf_counter()
    scene = Scene.load(scan, georef=args.scene / "georef.json", dem=args.scene / "dem.tif")
    scene.build_engine()
    load_s = time.perf_counter() - t0
    params = Seed003Params(views=LidarViewParams(upright=args.upright,
                                                 use_lsd_mask=not args.no_masks,
                                                 use_plane_mask=not args.no_masks),
                           pairs=tuple(args.pairs.split(",")), match_width=args.match_width,
                           max_rounds=args.rounds, geometric_check=args.geometric_check)
    t0 = time.perf_counter()
    planes = scene_planes(scene, params.views, params.seed)
    planes_s = time.perf_counter() - t0
    print(f"loaded {size_text(scene)} in {load_s:.1f} s; {len(planes)} planes "
          f"({(planes.labels >= 0).mean():.0%} of the points) in {planes_s:.1f} s", flush=True)
    photos = sorted((args.scene / args.tier).glob("IMG_*.jpg"))[: args.photos]
    if args.compare_pipeline:
        rows = [r for path in photos for r in compare_pipeline(scene, path)]
        if args.rows:
            with atomic_write(args.rows, encoding="utf-8") as fh:
                json.dump({"rows": rows}, fh, indent=1)
        return 0
    rows = []
    for path in photos:
        row = evaluate(scene, path, params, args.images)
        rows.append(row)
        print(json.dumps({k: v for k, v in row.items() if k != "hints"}), flush=True)
    meta = {"scene": args.scene.name, "scan": str(scan.relative_to(args.scene)),
            "n_points": getattr(scene, "n_points", None) or scene.n_faces, "tier": args.tier, "pairs": list(params.pairs),
            "match_width": params.match_width, "planes": len(planes),
            "planes_s": round(planes_s, 1),
            "planes_on_points": round(float((planes.labels >= 0).mean()), 3),
            "steep_planes": int((np.abs(planes.normals[:, 2]) < np.cos(np.radians(45))).sum()),
            "machine": f"{platform.machine()}, {__import__('os').cpu_count()} cores"}
    if args.rows:
        with atomic_write(args.rows, encoding="utf-8") as fh:
            json.dump({"meta": meta, "rows": rows}, fh, indent=1)
    text = report(rows, meta)
    print(text)
    if args.report:
        write_section(args.report, text, MARK_START, MARK_END)
    return 0


if __name__ == "__main__":
    sys.exit(main())

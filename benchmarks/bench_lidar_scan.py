"""Generated terrestrial laser scans of the benchmark scenes (issue 16): N, time, file size.

For each benchmark scene (the models ``bench_register.py`` generates and
caches under ``benchmarks/_cache/``), a two-station terrestrial scan of the
scene's **true surface** is simulated with :mod:`napari_imgreg.sample.scan`
(``ScanSpec()`` defaults: stations 55 m in front of the face, 50 m apart,
1.7 m tripods, 1 mrad step, intensity from per-rock-type reflectance ×
|cos incidence| × range falloff × 2 % noise, 5 mm range noise, no colour) and
written as ``scan.laz`` + ``scan.json`` beside the scene:

* ``rough``: the rough scene's true surface
  (``<scene>/rough-r2/model/true_vertices.npy``, the surface the rough tiers'
  photos are rendered from), scan in ``<scene>/rough-r2/lidar-s<SCAN_VERSION>/``;
* ``plain``: the plain model (the surface of the ``same_light`` /
  ``changed_light`` tiers' photos), scan in ``<scene>/lidar-s<SCAN_VERSION>/``.

``--surface rough,plain`` (default) makes both.

Each scan runs in a child process, so its wall time, CPU time and peak RSS are
its own; the LAZ is then read back (laspy + lazrs) and its read time, point
spacing and intensities per rock type reported. Scans already in the cache are
reported, not re-made (``--force`` re-makes them).

    .venv/bin/python benchmarks/bench_lidar_scan.py --report docs/benchmarks.md
    .venv/bin/python benchmarks/bench_lidar_scan.py --quick      # small scene, 5 mrad
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _report import markers, write_section  # noqa: E402  (benchmarks/ is on sys.path)

from napari_imgreg._atomic import atomic_path, atomic_write  # noqa: E402
from napari_imgreg.sample.scan import SCAN_VERSION, ScanSpec  # noqa: E402

HERE = Path(__file__).resolve().parent
DEFAULT_CACHE = HERE / "_cache"
MARK_START, MARK_END = markers("bench_lidar_scan")
#: Station 1's intensity panorama, beside each scan.
PANORAMA = "station1_intensity.png"
#: The first scene's panorama in the report.
REPORT_IMAGE = "images/bench_lidar_scan.png"
#: The issue's range of points per scene.
TARGET_POINTS = (3_000_000, 8_000_000)


# ------------------------------------------------------------- one scan
def _one(model_dir: Path, out_dir: Path, step_mrad: float) -> int:
    """Child process: make one scan, read it back, print the figures as JSON."""
    import laspy

    from napari_imgreg.sample.scan import scan_scene_folder

    t0, c0 = time.perf_counter(), time.process_time()
    laz = scan_scene_folder(model_dir, ScanSpec(step_mrad=step_mrad), out_dir)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    rss_make = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
    t0 = time.perf_counter()
    las = laspy.read(laz)
    read_s = time.perf_counter() - t0
    doc = json.loads(laz.with_suffix(".json").read_text())
    xyz = np.column_stack([las.x, las.y, las.z]) - np.asarray(doc["georef_origin"] or [0, 0, 0])
    st = np.asarray(las.point_source_id, np.int64) - 1
    centres = np.array([s["position"] for s in doc["stations"]])
    ranges = np.linalg.norm(xyz - centres[st], axis=1)
    _panorama(xyz[st == 0] - centres[0], np.asarray(las.intensity[st == 0]) / 65535.0,
              step_mrad * 1e-3, out_dir / PANORAMA)
    print(json.dumps({
        "wall_s": round(wall, 2), "cpu_s": round(cpu, 2), "peak_rss_gb": round(rss_make, 3),
        "read_s": round(read_s, 2), "n_read": int(len(las.points)),
        "range_m": [round(float(v), 2) for v in np.percentile(ranges, [5, 50, 95])],
        "intensity_p": [round(float(v), 4) for v in np.percentile(np.asarray(las.intensity) / 65535.0,
                                                                  [5, 50, 95])],
    }))
    return 0


def _panorama(v: np.ndarray, intensity: np.ndarray, step: float, path: Path) -> None:
    """Station 1's scan as the scanner sees it: intensity on its azimuth × elevation grid (PNG)."""
    from PIL import Image

    az = np.arctan2(v[:, 0], v[:, 1])
    el = np.arcsin(v[:, 2] / np.linalg.norm(v, axis=1))
    col = np.round((az - az.min()) / step).astype(int)
    row = np.round((el.max() - el) / step).astype(int)
    img = np.zeros((row.max() + 1, col.max() + 1), np.float32)
    img[row, col] = intensity
    lo, hi = np.percentile(intensity, [1.0, 99.5])
    Image.fromarray((np.clip((img - lo) / (hi - lo), 0, 1) * 255).astype(np.uint8)).save(path)


def scan_dir(scene_dir: Path, surface: str, step_mrad: float) -> tuple[Path, Path]:
    """(model folder to scan, folder the scan goes to) for one benchmark scene."""
    from bench_register import rough_folder  # the rough scene, generated once

    tag = f"lidar-s{SCAN_VERSION}" + ("" if step_mrad == 1.0 else f"-{step_mrad:g}mrad")
    if surface == "rough":
        rough = rough_folder(scene_dir)
        return rough / "model", rough / tag
    return scene_dir, scene_dir / tag


def run_scene(model_dir: Path, out_dir: Path, step_mrad: float, force: bool) -> dict:
    """Make (or find cached) one scan; its figures."""
    bench = out_dir / "bench.json"
    if not force and bench.is_file() and (out_dir / "scan.json").is_file():
        rec = json.loads(bench.read_text())
        made_with = json.loads((out_dir / "scan.json").read_text()).get("spec")
        if rec.get("scan_version") == SCAN_VERSION and made_with == ScanSpec(step_mrad=step_mrad).to_dict():
            rec["cached"] = True
            return rec
    print(f"scanning {model_dir} -> {out_dir} ...", flush=True)
    load = os.getloadavg()
    proc = subprocess.run(
        [sys.executable, __file__, "--one", str(model_dir), str(out_dir), "--step-mrad", str(step_mrad)],
        capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        sys.stderr.write(proc.stderr)
        raise SystemExit(f"scan of {model_dir} failed")
    figures = json.loads(proc.stdout.strip().splitlines()[-1])
    doc = json.loads((out_dir / "scan.json").read_text())
    rec = {
        "scan_version": SCAN_VERSION, "step_mrad": step_mrad, "model": str(model_dir),
        "n_points": doc["n_points"], "stations": doc["stations"], "grid": doc["grid"],
        "laz_bytes": (out_dir / "scan.laz").stat().st_size,
        "timings_s": doc.get("timings_s", {}), "intensity_by_surface": doc.get("intensity_by_surface"),
        "surface": doc.get("surface"), "cover": doc.get("cover"),
        "load_average": [round(v, 1) for v in load], "out_dir": str(out_dir), **figures,
    }
    with atomic_write(bench) as fh:
        json.dump(rec, fh, indent=1)
    print(f"  {rec['n_points']:,} points, {rec['wall_s']:.0f} s, "
          f"{rec['laz_bytes'] / 1e6:.1f} MB", flush=True)
    return rec


# --------------------------------------------------------------- report
def report(rows: list[dict], meta: dict) -> str:
    spec = ScanSpec(step_mrad=meta["step_mrad"])
    lines = [
        MARK_START,
        "## Generated terrestrial laser scans (issue 16, benchmark data)",
        "",
        f"{len(rows)} scan(s) of {meta['what']}; scanned surfaces: {meta['surface_words']}. "
        f"{spec.n_stations} stations {spec.standoff_m:g} m in front of the face, "
        f"{spec.station_spacing_m:g} m apart, {spec.tripod_height_m:g} m tripods; "
        f"{spec.step_mrad:g} mrad step over azimuth ±{spec.azimuth_half_width_deg:g}° and elevation "
        f"{spec.elevation_range_deg[0]:g}° to {spec.elevation_range_deg[1]:g}°; intensity = "
        f"reflectance (sandstone {spec.reflectance['sandstone']:g}, mudstone "
        f"{spec.reflectance['mudstone']:g}, scree {spec.reflectance['scree']:g}, vegetation "
        f"{spec.reflectance['vegetation']:g}; beds ±{spec.bed_reflectance_variation:.0%}) × within-bed "
        f"texture (log-normal, {spec.texture_amplitude:.0%} log-std, value-noise octaves of "
        f"{', '.join(f'{v:g}' for v in spec.texture_scales_m)} m, correlation "
        f"{spec.texture_albedo_correlation:g} with the visible albedo's pattern within the bed) × "
        f"|cos incidence| × "
        f"min(1, ({spec.falloff_reference_m:g} m / R)^{spec.falloff_exponent:g}) × "
        f"(1 + {spec.intensity_noise:g}·N(0,1)); range noise {spec.range_noise_m * 1000:g} mm; no colour. "
        "LAS 1.4 point format 6, 1 mm scale, projected CRS coordinates with the CRS record of "
        "`georef.json`, LAZ by lazrs.",
        "",
        "| scene | points (per station) | target 3–8 M | hit rays | generation (wall / CPU) | "
        "of it: load, cover, cast | peak RSS | scan.laz | read back | range p5/p50/p95 | "
        "spacing at p50 | intensity: sandstone / mudstone (near normal) / cover (all) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        per = " + ".join(f"{s['points'] / 1e6:.2f}" for s in r["stations"])
        rays = sum(s["rays"] for s in r["stations"])
        ok = "✅" if TARGET_POINTS[0] <= r["n_points"] <= TARGET_POINTS[1] else "❌"
        t = r.get("timings_s", {})
        by = r.get("intensity_by_surface") or {}

        def med(k: str, which: str = "median_near_normal", by: dict = by) -> str:
            v = (by.get(k) or {}).get(which)
            return "–" if v is None else f"{v:.3f}"

        p5, p50, p95 = r["range_m"]
        lines.append(
            f"| {r['scene']} | {r['n_points'] / 1e6:.2f} M ({per}) | {ok} | "
            f"{r['n_points'] / rays:.0%} of {rays / 1e6:.2f} M | {r['wall_s']:.1f} s / {r['cpu_s']:.1f} s | "
            f"{t.get('load', 0):.1f}, {t.get('cover', 0):.1f}, {t.get('simulate', 0):.1f} s | "
            f"{r['peak_rss_gb']:.2f} GB | {r['laz_bytes'] / 1e6:.1f} MB ({r['laz_bytes'] / r['n_points']:.1f} B/pt) | "
            f"{r['read_s']:.1f} s | {p5:.0f} / {p50:.0f} / {p95:.0f} m | "
            f"{r['step_mrad'] * p50:.0f} mm | {med('sandstone')} / {med('mudstone')} / {med('cover', 'median')} |")
    loads = [tuple(r.get("load_average", ())) for r in rows]
    lines += [
        "",
        f"- The write (LAZ compression, JSON) is the rest of the wall time after load, cover and cast. "
        f"Times on {meta['machine']}; load average at the start of each scan: "
        f"{'; '.join(', '.join(f'{v:g}' for v in la) for la in loads)}. "
        "Each scan ran in its own process (peak RSS is the scan's).",
        "- *cover*: the generator's rock mask rebuilt from `scene.json`'s spec and seed "
        "(bare rock reflects by its bed's rock type, from `geology.json`); scree on the talus, "
        "vegetation elsewhere. *intensity*: medians, the rock types' at |cos incidence| > 0.9 "
        "(where they compare directly: their ratio is the reflectances' when the beds average out), the "
        "cover's over all its points (mostly grazing ground).",
        "- The photos' own RGB is never used: the texture shares only a stated part of its "
        "variance with the albedo's *within-bed* log luminance (dark stains, seeps and lichen "
        "are dark at the laser's wavelength too), the rest is the scanner's own field; scan.json "
        "beside each scan records the stations, grid, noise, intensity and texture model and N.",
        "",
        f"Reproduce: `{meta['command']}` (scans are cached beside the scenes: {meta['where']}).",
    ]
    if meta.get("image"):
        lines += ["", f"![station 1's scan: intensity on its azimuth × elevation grid]({meta['image']})",
                  "", f"*{meta['image_caption']}*"]
    lines += [
        MARK_END,
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--size", choices=("small", "large"), default="large")
    parser.add_argument("--scenes", type=int, default=2, help="scene seeds (default 2)")
    parser.add_argument("--first-seed", type=int, default=1)
    parser.add_argument("--photos", type=int, default=4,
                        help="cameras per scene of the cached benchmark scenes (names their folder)")
    parser.add_argument("--surface", default="rough,plain",
                        help="comma-separated: rough (the rough tiers' true surface), plain (the model)")
    parser.add_argument("--step-mrad", type=float, default=1.0)
    parser.add_argument("--cache", type=Path, default=DEFAULT_CACHE)
    parser.add_argument("--force", action="store_true", help="re-make cached scans")
    parser.add_argument("--quick", action="store_true",
                        help="smoke run: the package's small sample scene, plain surface, 5 mrad")
    parser.add_argument("--report", type=Path, help="markdown file whose section to rewrite")
    parser.add_argument("--one", nargs=2, type=Path, metavar=("MODEL_DIR", "OUT_DIR"),
                        help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.one:
        return _one(args.one[0], args.one[1], args.step_mrad)

    rows = []
    if args.quick:
        from napari_imgreg.sample import sample_scene

        step = 5.0 if args.step_mrad == 1.0 else args.step_mrad
        folder = sample_scene("small")
        rec = run_scene(folder, args.cache / f"quick-small-lidar-s{SCAN_VERSION}-{step:g}mrad", step,
                        args.force)
        rows.append({**rec, "scene": "small seed 0 (quick)"})
        meta = {"what": "the small sample scene, quick run", "surface_words": "the model",
                "step_mrad": step, "where": str(args.cache)}
    else:
        from bench_register import scene_folder  # the benchmark's scenes, generated once

        step = args.step_mrad
        surfaces = [w.strip() for w in args.surface.split(",") if w.strip()]
        if not surfaces or set(surfaces) - {"rough", "plain"}:
            parser.error(f"--surface takes rough and/or plain, not {args.surface!r}")
        for seed in range(args.first_seed, args.first_seed + args.scenes):
            scene_dir = scene_folder(args.cache, args.size, seed, args.photos)
            for surface in surfaces:
                model_dir, out_dir = scan_dir(scene_dir, surface, step)
                rec = run_scene(model_dir, out_dir, step, args.force)
                rows.append({**rec, "scene": f"{args.size} seed {seed}, {surface}"})
        seeds = f"seed {args.first_seed}" if args.scenes == 1 else \
            f"seeds {args.first_seed}–{args.first_seed + args.scenes - 1}"
        meta = {"what": f"the {args.size} benchmark scenes ({seeds}"
                        + (", 1,198,152 triangles)" if args.size == "large" else ")"),
                "surface_words": " and ".join(
                    {"rough": "*rough*, the rough scene's true surface (`rough-r2/model/true_vertices.npy`: "
                              "beds proud, gullies, roughness — what the rough tiers' photos show)",
                     "plain": "*plain*, the model (the same_light/changed_light tiers' photos' surface)"}[w]
                    for w in surfaces),
                "step_mrad": step,
                "where": f"`{args.cache.name}/<scene>/[rough-r2/]lidar-s{SCAN_VERSION}/`"}
    cmd = ".venv/bin/python benchmarks/bench_lidar_scan.py"
    if args.quick:
        cmd += " --quick"
    else:
        if args.size != "large":
            cmd += f" --size {args.size}"
        if args.scenes != 2 or args.first_seed != 1:
            cmd += f" --scenes {args.scenes} --first-seed {args.first_seed}"
        if args.photos != 4:
            cmd += f" --photos {args.photos}"
        if args.surface != "rough,plain":
            cmd += f" --surface {args.surface}"
        if step != 1.0:
            cmd += f" --step-mrad {step:g}"
    meta["command"] = cmd + (f" --report {args.report}" if args.report else "")
    meta["machine"] = f"{os.cpu_count()} cores, Python {platform.python_version()}"
    for r in rows:
        print(f"{r['scene']}: {r['n_points']:,} points, {r['wall_s']:.1f} s wall ({r['cpu_s']:.1f} s CPU), "
              f"{r['laz_bytes'] / 1e6:.1f} MB, peak RSS {r['peak_rss_gb']:.2f} GB"
              + (" (cached)" if r.get("cached") else ""))
    if args.report and not args.quick:
        from PIL import Image

        pano = Path(rows[0]["out_dir"]) / PANORAMA
        if pano.is_file():
            img = Image.open(pano)
            scale = min(1.0, 1400 / img.width)
            img = img.resize((int(img.width * scale), int(img.height * scale)), Image.Resampling.BOX)
            target = args.report.parent / REPORT_IMAGE
            target.parent.mkdir(parents=True, exist_ok=True)
            with atomic_path(target) as tmp:
                img.save(tmp, format="PNG")
            meta["image"] = REPORT_IMAGE
            meta["image_caption"] = (f"{rows[0]['scene']}, station 1: intensity of the "
                                     f"{rows[0]['stations'][0]['points']:,} returns on the scan grid "
                                     f"(black: no return), scaled to {scale:.2f}×")
    section = report(rows, meta)
    if args.report:
        write_section(args.report, section, MARK_START, MARK_END)
        print(f"wrote the bench_lidar_scan section of {args.report}")
    else:
        print(section)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

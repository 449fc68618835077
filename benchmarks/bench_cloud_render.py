"""Point-cloud scene benchmark: normals, first and interactive splat renders,
ray queries and peak memory at 5 M and 50 M points (issue 16).

The cloud is a generated terrestrial scan of a rough rock wall (30 m wide,
8 m high, relief of ±0.3 m plus 5 mm range noise), swept by one station
15 m in front of it at a constant angular step, in scan order, with an
intensity of alternating sandstone/mudstone beds × cos(incidence) × a range
falloff. Each size runs in its own process so that its peak RSS is its own.
The section of ``docs/benchmarks.md`` between the ``bench_cloud_render``
markers is rewritten (atomically).

    python benchmarks/bench_cloud_render.py --sizes 5e6 50e6 --report docs/benchmarks.md

The engine comparison rows time the alternatives that were tried, on the
same cloud and camera: vectorised NumPy (projection, then a z-buffer by
``np.minimum.at``, one pixel per point, no splats) against the numba
kernels.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from _report import markers, write_section

from napari_imgreg.camera import Intrinsics, Pose
from napari_imgreg.cloud import CloudScene
from napari_imgreg.render_points import splat_cloud

MARK_START, MARK_END = markers("bench_cloud_render")
TARGETS = {"render_5M": 0.5}
PHOTO = Intrinsics(1632, 1224, 1400.0, 1400.0, 815.5, 611.5)
MATCH_WIDTH = 768
STATION = np.array([0.0, -15.0, 1.6])


def _peak_rss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2


def _wall(x: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Relief of the wall (metres toward the scanner) at (x, z)."""
    return (0.18 * np.sin(0.9 * x + 0.3 * z) + 0.08 * np.sin(3.1 * x - 1.7 * z)
            + 0.03 * np.sin(11.0 * x + 7.0 * z))


def generate_scan(n_points: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A scan of ~n_points points of the wall from :data:`STATION`, in scan order.

    Returns
    -------
    xyz : (N, 3) float64, metres
    intensity : (N,) float32 in [0, 1]
    """
    rng = np.random.default_rng(seed)
    az_half = np.arctan2(15.0, 15.0)
    el_lo, el_hi = np.arctan2(-1.6, 15.0), np.arctan2(8.0 - 1.6, 15.0)
    n_el = int(np.sqrt(n_points * (el_hi - el_lo) / (2 * az_half)))
    n_az = int(n_points / n_el)
    xyz = np.empty((n_az * n_el, 3))
    intensity = np.empty(n_az * n_el, np.float32)
    az = np.linspace(-az_half, az_half, n_az)
    el = np.linspace(el_lo, el_hi, n_el)
    block = max(1, 2_000_000 // n_el)
    for lo in range(0, n_az, block):  # column by column, as the scanner turns
        A, E = np.meshgrid(az[lo:lo + block], el, indexing="ij")
        d = np.stack([np.sin(A) * np.cos(E), np.cos(A) * np.cos(E), np.sin(E)], -1).reshape(-1, 3)
        t = -STATION[1] / d[:, 1]
        p = STATION + d * t[:, None]
        for _ in range(2):  # the ray meets the relief: two fixed-point steps
            t = (-STATION[1] - _wall(p[:, 0], p[:, 2])) / d[:, 1]
            p = STATION + d * t[:, None]
        t += rng.normal(0.0, 0.005, len(t))  # 5 mm range noise
        p = STATION + d * t[:, None]
        rows = slice(lo * n_el, lo * n_el + len(p))
        xyz[rows] = p
        bed = np.where(np.sin(2 * np.pi * (p[:, 2] + 0.05 * p[:, 0]) / 1.3) > 0, 0.8, 0.45)
        intensity[rows] = np.clip(bed * np.abs(d[:, 1]) * (15.0 / t) ** 0.5
                                  * (1 + rng.normal(0, 0.02, len(t))), 0, 1)
    return xyz, intensity


def _numpy_engine(xyz32: np.ndarray, intr: Intrinsics, pose: Pose) -> tuple[float, float]:
    """The vectorised-NumPy alternative: projection, then a one-pixel z-buffer."""
    t0 = time.perf_counter()
    p = xyz32 @ pose.R.T.astype(np.float32)
    p += pose.t.astype(np.float32)
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = intr.fx * p[:, 0] / z + intr.cx
        v = intr.fy * p[:, 1] / z + intr.cy
    ok = (z > 0.01) & (u > -0.5) & (u < intr.width - 0.5) & (v > -0.5) & (v < intr.height - 0.5)
    idx = np.flatnonzero(ok)
    t1 = time.perf_counter()
    pix = np.rint(v[idx]).astype(np.int64) * intr.width + np.rint(u[idx]).astype(np.int64)
    zbuf = np.full(intr.width * intr.height, np.inf, np.float32)
    np.minimum.at(zbuf, pix, z[idx])
    win = z[idx] == zbuf[pix]
    ids = np.full(intr.width * intr.height, -1, np.int64)
    ids[pix[win]] = idx[win]
    return t1 - t0, time.perf_counter() - t1


def run_one(n_points: float, runs: int) -> dict:
    out: dict = {"requested": n_points, "load_before": os.getloadavg()[0]}
    t0 = time.perf_counter()
    xyz, intensity = generate_scan(n_points)
    out["generate_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    scene = CloudScene(xyz, intensity=intensity, name="wall", viewpoints=STATION[None])
    out["construct_s"] = time.perf_counter() - t0
    del xyz, intensity
    out["n_points"] = scene.n_points
    out["build_s"] = scene.build_engine()
    out["normals_s"] = scene.timings_s["normals"]
    out["compile_s"] = scene.timings_s["compile"]
    pose = Pose.from_attitude(0.0, 0.0, 0.0, np.array([1.0, -13.0, 2.5]))
    t0 = time.perf_counter()
    first = splat_cloud(scene, PHOTO, pose)
    out["first_render_s"] = time.perf_counter() - t0
    out["coverage"] = float(first["mask"].mean())
    out["first_timings"] = first["timings_s"]
    del first
    scale = MATCH_WIDTH / PHOTO.width
    for key, s in (("render", 1.0), ("render_match", scale)):
        times, cpus, parts = [], [], []
        for k in range(runs):
            # Interactive: the pose moves a little between renders.
            p = Pose.from_attitude(0.3 * k, 0.2 * k, 0.0, np.array([1.0 + 0.05 * k, -13.0, 2.5]))
            t0, c0 = time.perf_counter(), time.process_time()
            r = splat_cloud(scene, PHOTO, p, scale=s)
            times.append(time.perf_counter() - t0)
            cpus.append(time.process_time() - c0)
            parts.append(r["timings_s"])
            del r
        out[key + "_s"] = statistics.median(times)
        out[key + "_all"] = times
        out[key + "_cpu_s"] = statistics.median(cpus)
        out[key + "_parts"] = {k: statistics.median(pp[k] for pp in parts) for k in parts[0]}
    # Ray queries: a drawn line's samples (virtual camera) and a few rays.
    origin, d = pose.rays(PHOTO, np.stack([np.linspace(200, 1400, 1000),
                                           np.linspace(300, 900, 1000)], 1))
    t0 = time.perf_counter()
    hits = scene.cast_rays(origin, d)
    out["rays_1000_s"] = time.perf_counter() - t0
    out["rays_1000_hit"] = float(hits.hit.mean())
    t0 = time.perf_counter()
    scene.cast_rays(origin, d[:4])
    out["rays_4_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    out["terrain_z"] = scene.terrain_height(1.0, -1.0)
    out["terrain_s"] = time.perf_counter() - t0
    if scene.n_points <= 10_000_000:
        proj, zb = [], []
        for _ in range(runs):
            a, b = _numpy_engine(scene.xyz32, PHOTO, pose)
            proj.append(a)
            zb.append(b)
        out["numpy_project_s"] = statistics.median(proj)
        out["numpy_zbuffer_s"] = statistics.median(zb)
    out["peak_rss_gb"] = _peak_rss_gb()
    out["load_after"] = os.getloadavg()[0]
    return out


def report(results: list[dict], runs: int) -> str:
    lines = [MARK_START, "## Point-cloud scenes: splat rendering (issue 16)", ""]
    lines.append(
        f"Generated terrestrial scan of a rough 30 × 8 m wall from one station 15 m away, in "
        f"scan order, intensity from the beds × cos(incidence) × range falloff, 5 mm range "
        f"noise; camera {PHOTO.width}×{PHOTO.height} (f = {PHOTO.fx:.0f} px) 13 m from the "
        f"wall; {os.cpu_count()} cores shared with other work (every run under `nice -n 19`), "
        f"Python {platform.python_version()}. Medians of {runs} renders from slightly moved "
        "poses. Times are wall clock; \"CPU time\" sums both threads, so on two idle cores a "
        "render's wall time is about half of it (the load average column says how busy the "
        "machine was: above 2, the threads waited for the cores). Engine: numba kernels (surfel z-buffer, blended colour, 3 hole-filling passes, "
        "outputs) on Python threads.")
    header = ("| points | normals + spacing (once) | kernels (once) | first render | "
              f"render {PHOTO.width}×{PHOTO.height} | its CPU time | target | render at "
              f"{MATCH_WIDTH} px (CPU) | 1000 rays | 4 rays | peak RSS | load average |")
    lines += ["", header, "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        target = ""
        if r["n_points"] <= 6e6:
            target = "≤ 0.5 s " + ("✅" if r["render_s"] <= TARGETS["render_5M"] else "❌")
        lines.append(
            f"| {r['n_points'] / 1e6:.1f} M | {r['normals_s']:.1f} s | {r['compile_s']:.2f} s | "
            f"{r['first_render_s']:.3f} s | {r['render_s']:.3f} s | {r['render_cpu_s']:.3f} s | "
            f"{target} | {r['render_match_s']:.3f} s ({r['render_match_cpu_s']:.3f} s) | "
            f"{r['rays_1000_s']:.3f} s | {r['rays_4_s']:.3f} s | {r['peak_rss_gb']:.2f} GB | "
            f"{r['load_before']:.1f} → {r['load_after']:.1f} |")
    lines += ["", "Where the time of a full-resolution render goes (median, s):", "",
              "| points | project | z-buffer splats | colour blend | hole filling | outputs |",
              "|---|---|---|---|---|---|"]
    for r in results:
        p = r["render_parts"]
        lines.append(f"| {r['n_points'] / 1e6:.1f} M | {p['project']:.3f} | {p['splat']:.3f} | "
                     f"{p['blend']:.3f} | {p['fill']:.3f} | {p['finish']:.3f} |")
    numpy_rows = [r for r in results if "numpy_project_s" in r]
    if numpy_rows:
        header = ("| points | NumPy projection | NumPy z-buffer (`np.minimum.at`, 1 px per "
                  "point, no splats, no filling) | numba projection | numba surfel z-buffer |")
        lines += ["", "Engines tried, same cloud and camera (s, median):", "", header,
                  "|---|---|---|---|---|"]
        for r in numpy_rows:
            p = r["render_parts"]
            lines.append(f"| {r['n_points'] / 1e6:.1f} M | {r['numpy_project_s']:.3f} | "
                         f"{r['numpy_zbuffer_s']:.3f} | {p['project']:.3f} | {p['splat']:.3f} |")
        met = all(r["render_s"] <= TARGETS["render_5M"] for r in numpy_rows)
        lines += ["", "GL points through EGL (llvmpipe) were not tried"
                  + (": the numba kernels meet the target without a GL stack on a headless "
                     "machine." if met else ".")]
    coverage = ", ".join(f"{r['n_points'] / 1e6:.1f} M {r['coverage']:.0%}" for r in results)
    hit = ", ".join(f"{r['rays_1000_hit']:.0%}" for r in results)
    renders = "; ".join(f"{r['n_points'] / 1e6:.1f} M "
                        + ", ".join(f"{t:.3f}" for t in r["render_all"]) for r in results)
    lines += ["", (f"Coverage of the frame: {coverage}; 1000 rays from the camera hit: {hit}. "
                   "Kernels (once) is numba loading its on-disk cache; compiling them in a "
                   "fresh install takes ~7 s of CPU, once."),
              "", f"All full-resolution renders (s): {renders}.",
              "", ("Reproduce: `nice -n 19 .venv/bin/python benchmarks/bench_cloud_render.py "
                   "--sizes 5e6 50e6 --report docs/benchmarks.md`."), MARK_END]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", nargs="+", type=float, default=[5e6, 50e6])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--report", type=Path)
    ap.add_argument("--one", type=float, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.one:
        print(json.dumps(run_one(args.one, args.runs)))
        return
    results = []
    for n in args.sizes:
        proc = subprocess.run([sys.executable, __file__, "--one", str(n), "--runs", str(args.runs)],
                              capture_output=True, text=True, check=False)
        if proc.returncode != 0:
            sys.exit(f"{n:g} points: {proc.stderr[-2000:]}")
        results.append(json.loads(proc.stdout.strip().splitlines()[-1]))
        r = results[-1]
        print(f"{r['n_points']:,} points: normals {r['normals_s']:.1f} s, first render "
              f"{r['first_render_s']:.3f} s, render {r['render_s']:.3f} s, at {MATCH_WIDTH} px "
              f"{r['render_match_s']:.3f} s, peak RSS {r['peak_rss_gb']:.2f} GB", flush=True)
    text = report(results, args.runs)
    print(text)
    if args.report:
        write_section(args.report, text, MARK_START, MARK_END)


if __name__ == "__main__":
    main()

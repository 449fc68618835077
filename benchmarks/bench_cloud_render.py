"""Point-cloud scene benchmark: load, first and interactive splat renders,
ray queries and peak memory at 5 M and 50 M points (issue 16).

The cloud is a generated terrestrial scan of a rough rock wall (30 m wide,
8 m high, relief of ±0.3 m plus 5 mm range noise), swept by one station
15 m in front of it at a constant angular step, in scan order, with an
intensity of alternating sandstone/mudstone beds × cos(incidence) × a range
falloff. It is written once as LAZ (``benchmarks/_cache/cloud_render``) and
its normals computed once (the ``.imgreg-normals.npz`` beside it, as for a
user's file); each size then runs in its own process, which loads the file
as the tool does (every point, ``max_points=None``), so that its peak RSS
is its own. The section of ``docs/benchmarks.md`` between the
``bench_cloud_render`` markers is rewritten (atomically).

    nice -n 19 .venv/bin/python benchmarks/bench_cloud_render.py --sizes 5e6 50e6 --report docs/benchmarks.md

Renders are timed interleaved, several rounds, medians: ``before`` (the
kernels as they were before this work, loaded from git history by ``_splat_before.py``),
``full`` (the current kernels, every point) and ``auto`` (the default: the
level of detail above ``LodParams.min_points``, else the same as ``full``),
so that other load on the machine affects each alike. The engine comparison
rows time the vectorised-NumPy alternative (projection, then a z-buffer by
``np.minimum.at``, one pixel per point, no splats) on the same cloud and camera.
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

from napari_imgreg._allocator import tune_allocator
from napari_imgreg.camera import Intrinsics, Pose
from napari_imgreg.cloud import CloudScene
from napari_imgreg.render_points import splat_cloud

MARK_START, MARK_END = markers("bench_cloud_render")
CACHE = Path(__file__).resolve().parent / "_cache" / "cloud_render"
VARIANTS = ("before", "full", "auto")
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


def scan_path(n_points: float) -> Path:
    return CACHE / f"wall_{int(n_points)}.laz"


def prepare(n_points: float) -> dict:
    """Write the generated scan as LAZ and compute its normals cache, once.

    Returns the figures of that one-off work (kept in ``wall_N.json``)."""
    from napari_imgreg._atomic import atomic_write
    from napari_imgreg.io.pointclouds import PointCloud, write_point_cloud

    path = scan_path(n_points)
    meta_path = path.with_suffix(".json")
    meta = json.loads(meta_path.read_text()) if meta_path.exists() else {}
    if not path.exists():
        t0 = time.perf_counter()
        xyz, intensity = generate_scan(n_points)
        path.parent.mkdir(parents=True, exist_ok=True)
        write_point_cloud(path, PointCloud(xyz, intensity))
        meta = {"generate_write_s": time.perf_counter() - t0}
        del xyz, intensity
    scene = None
    if "normals_s" not in meta or not path.with_name(path.name + ".imgreg-normals.npz").exists():
        scene = CloudScene.load(path, max_points=None)
        t0, c0 = time.perf_counter(), time.process_time()
        _ = scene.normals  # computed and written beside the file
        meta.update(normals_s=time.perf_counter() - t0, normals_cpu_s=time.process_time() - c0,
                    normals_load=os.getloadavg()[0])
        lod_cache = path.with_name(path.name + ".imgreg-lod.npz")
        if lod_cache.exists():
            lod_cache.unlink()  # of other normals: built again below
    lod_cache = path.with_name(path.name + ".imgreg-lod.npz")
    if "lod_build_s" not in meta or (meta["lod_build_s"] and not lod_cache.exists()):
        scene = scene or CloudScene.load(path, max_points=None)
        t0 = time.perf_counter()
        built = scene.level_of_detail is not None  # built and written beside the file
        meta["lod_build_s"] = time.perf_counter() - t0 if built else 0.0  # 0: below min_points
        del scene
    with atomic_write(meta_path) as fh:
        json.dump(meta, fh)
    return meta


def _pose(k: int) -> Pose:
    """Interactive: the pose moves a little between renders."""
    return Pose.from_attitude(0.3 * k, 0.2 * k, 0.0, np.array([1.0 + 0.05 * k, -13.0, 2.5]))


def _same(a: dict, b: dict) -> dict:
    """How two renders of one pose differ."""
    both = a["mask"] & b["mask"]
    dz = np.abs(a["depth"] - b["depth"])[both]
    grey = np.abs(a["rgb"][..., 0].astype(np.int16) - b["rgb"][..., 0])[both]
    return {"identical": bool(np.array_equal(a["depth"], b["depth"], equal_nan=True)
                              and np.array_equal(a["face_id"], b["face_id"])
                              and np.array_equal(a["rgb"], b["rgb"])),
            "coverage": [float(a["mask"].mean()), float(b["mask"].mean())],
            "depth_over_1cm": float((dz > 0.01).mean()) if dz.size else 0.0,
            "depth_median_mm": float(np.median(dz) * 1e3) if dz.size else 0.0,
            "grey_mean_diff": float(grey.mean()) if grey.size else 0.0}


def run_one(n_points: float, runs: int) -> dict:
    tune_allocator()
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import _splat_before

    before = _splat_before.load()
    if before is None:
        raise SystemExit("bench_cloud_render: needs the repository's history (git show "
                         f"{_splat_before.BEFORE_COMMIT}) for the old kernels")

    meta = prepare(n_points)
    out: dict = {"requested": n_points, "load_before": os.getloadavg()[0], **meta}
    path = scan_path(n_points)
    t0, c0 = time.perf_counter(), time.process_time()
    scene = CloudScene.load(path, max_points=None)
    out["read_s"] = time.perf_counter() - t0
    out["build_s"] = scene.build_engine()
    out["load_s"] = time.perf_counter() - t0
    out["load_cpu_s"] = time.process_time() - c0
    out["lod_s"] = scene.timings_s.get("lod", 0.0)
    out["compile_s"] = scene.timings_s["compile"]
    out["n_points"] = scene.n_points
    out["rss_loaded_gb"] = _peak_rss_gb()
    pose = _pose(0)
    t0 = time.perf_counter()
    first = splat_cloud(scene, PHOTO, pose)
    out["first_render_s"] = time.perf_counter() - t0
    out["coverage"] = float(first["mask"].mean())
    out["first_timings"] = first["timings_s"]
    lod = scene.level_of_detail
    if lod is not None:
        from napari_imgreg.render_points import _field_of_view

        blocks, level, _ = lod.choose(pose.R, pose.t, _field_of_view(PHOTO), PHOTO.fx, 0.75,
                                      0.01, scene.params.lod.max_radius_px)
        out["points_drawn"] = int(lod.counts[blocks, level].sum())
        out["levels_drawn"] = np.bincount(level, weights=lod.counts[blocks, level],
                                          minlength=lod.n_levels).astype(int).tolist()
        out["blocks"] = [len(blocks), lod.n_blocks]
    else:
        out["points_drawn"] = scene.n_points
    render = {"before": lambda p, s: before.splat_cloud(scene, PHOTO, p, scale=s),
              "full": lambda p, s: splat_cloud(scene, PHOTO, p, scale=s, detail="full"),
              "auto": lambda p, s: splat_cloud(scene, PHOTO, p, scale=s, detail="auto")}
    ref = {v: render[v](pose, 1.0) for v in VARIANTS}  # also compiles the frozen kernels
    out["full_vs_before"] = _same(ref["full"], ref["before"])
    out["auto_vs_full"] = _same(ref["auto"], ref["full"])
    del first, ref
    scale = MATCH_WIDTH / PHOTO.width
    for key, s, variants in (("render", 1.0, VARIANTS), ("render_match", scale, ("full", "auto"))):
        times = {v: [] for v in variants}
        cpus = {v: [] for v in variants}
        parts = {v: [] for v in variants}
        for k in range(runs):
            p = _pose(k + 1)
            for v in variants[k % len(variants):] + variants[:k % len(variants)]:
                t0, c0 = time.perf_counter(), time.process_time()
                r = render[v](p, s)
                times[v].append(time.perf_counter() - t0)
                cpus[v].append(time.process_time() - c0)
                parts[v].append(r["timings_s"])
                del r
        for v in variants:
            out[f"{key}_{v}_s"] = statistics.median(times[v])
            out[f"{key}_{v}_all"] = times[v]
            out[f"{key}_{v}_cpu_s"] = statistics.median(cpus[v])
            out[f"{key}_{v}_parts"] = {k: statistics.median(pp.get(k, 0.0) for pp in parts[v])
                                       for k in parts[v][0]}
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


def _m(r: dict) -> str:
    return f"{r['n_points'] / 1e6:.1f} M"


def _lod_build(r: dict) -> str:
    if not r.get("lod_build_s"):
        return "— (below 10 M)"
    return f"{r['lod_build_s']:.1f} s (from its cache: {r['lod_s']:.1f} s)"


def report(results: list[dict], runs: int) -> str:
    lines = [MARK_START, "## Point-cloud scenes: splat rendering (issue 16)", ""]
    lines.append(
        f"Generated terrestrial scan of a rough 30 × 8 m wall from one station 15 m away, in "
        f"scan order, intensity from the beds × cos(incidence) × range falloff, 5 mm range "
        f"noise, written as LAZ and loaded whole (`CloudScene.load(path, max_points=None)`); "
        f"camera {PHOTO.width}×{PHOTO.height} (f = {PHOTO.fx:.0f} px) 13 m from the "
        f"wall; {os.cpu_count()} cores shared with other work (every run under `nice -n 19`), "
        f"Python {platform.python_version()}. Renders from slightly moved poses, {runs} rounds, "
        "the variants interleaved in each round (their order rotating), medians. Times are wall "
        "clock; \"CPU\" sums both threads, so on two idle cores a render's wall time is about "
        "half of it (the load average says how busy the machine was: above 2, the threads "
        "waited for the cores). `auto` is what `render()` draws: the level of detail "
        "(`LodParams`) for a cloud of 10 M points or more, every point below; `full` every "
        "point (`detail=\"full\"`, the z-buffer registration can ask for); `before` the "
        "kernels as they were before this work (commit d4da268's `render_points.py`, loaded by `benchmarks/_splat_before.py`).")
    header = ("| points | read LAZ | normals + spacing (once) | level of detail (once) | load "
              "(read, cached normals, level of detail, kernels) | first render | interactive "
              f"render {PHOTO.width}×{PHOTO.height} (`auto`) | its CPU | target | `full` "
              "(CPU) | `before` (CPU) | peak RSS | load average |")
    lines += ["", header, "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        target = ""
        if r["n_points"] <= 6e6:
            ok = r["render_auto_s"] <= TARGETS["render_5M"]
            target = "≤ 0.5 s " + ("✅" if ok else "❌")
        lines.append(
            f"| {_m(r)} | {r['read_s']:.1f} s | {r['normals_s']:.0f} s | "
            f"{_lod_build(r)} | "
            f"{r['load_s']:.1f} s | {r['first_render_s']:.3f} s | {r['render_auto_s']:.3f} s | "
            f"{r['render_auto_cpu_s']:.3f} s | {target} | {r['render_full_s']:.3f} s "
            f"({r['render_full_cpu_s']:.3f} s) | {r['render_before_s']:.3f} s "
            f"({r['render_before_cpu_s']:.3f} s) | {r['peak_rss_gb']:.2f} GB | "
            f"{r['load_before']:.1f} → {r['load_after']:.1f} |")
    lines += ["", f"At the match width ({MATCH_WIDTH} px), and ray queries:", "",
              "| points | `auto` (CPU) | `full` (CPU) | 1000 rays | 4 rays |", "|---|---|---|---|---|"]
    for r in results:
        lines.append(f"| {_m(r)} | {r['render_match_auto_s']:.3f} s "
                     f"({r['render_match_auto_cpu_s']:.3f} s) | {r['render_match_full_s']:.3f} s "
                     f"({r['render_match_full_cpu_s']:.3f} s) | {r['rays_1000_s']:.3f} s | "
                     f"{r['rays_4_s']:.3f} s |")
    lines += ["", "Where the time of a full-resolution render goes (median, s):", "",
              ("| points | variant | level-of-detail choice | project | z-buffer splats | colour "
               "blend | hole filling | outputs |"), "|---|---|---|---|---|---|---|---|"]
    for r in results:
        for v in VARIANTS:
            p = r[f"render_{v}_parts"]
            lines.append(f"| {_m(r)} | `{v}` | {p.get('select', 0.0):.3f} | {p['project']:.3f} | "
                         f"{p['splat']:.3f} | {p['blend']:.3f} | {p['fill']:.3f} | "
                         f"{p['finish']:.3f} |")
    lines += ["", ("What the level of detail draws, and how its image differs from every "
                   "point's (first pose):"), "",
              ("| points | blocks in view | points drawn | by level (0 = full) | `full` = "
               "`before` | coverage `auto` / `full` | pixels whose depth moved > 1 cm | median "
               "depth change | mean grey change |"), "|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        a, f = r["auto_vs_full"], r["full_vs_before"]
        blocks = f"{r['blocks'][0]:,} of {r['blocks'][1]:,}" if "blocks" in r else "— (below 10 M)"
        drawn = list(r.get("levels_drawn", []))
        while drawn and not drawn[-1]:
            drawn.pop()  # the coarser levels not drawn
        levels = ", ".join(f"{x / 1e6:.2f} M" for x in drawn) or "—"
        same = "identical" if f["identical"] else (
            f"differ: {f['depth_over_1cm']:.2%} of pixels > 1 cm, grey {f['grey_mean_diff']:.2f}")
        lines.append(f"| {_m(r)} | {blocks} | {r['points_drawn'] / 1e6:.2f} M | {levels} | "
                     f"{same} | {a['coverage'][0]:.1%} / {a['coverage'][1]:.1%} | "
                     f"{a['depth_over_1cm']:.2%} | {a['depth_median_mm']:.2f} mm | "
                     f"{a['grey_mean_diff']:.2f} |")
    numpy_rows = [r for r in results if "numpy_project_s" in r]
    if numpy_rows:
        header = ("| points | NumPy projection | NumPy z-buffer (`np.minimum.at`, 1 px per "
                  "point, no splats, no filling) | numba projection | numba surfel z-buffer |")
        lines += ["", "Engines tried, same cloud and camera (s, median):", "", header,
                  "|---|---|---|---|---|"]
        for r in numpy_rows:
            p = r["render_full_parts"]
            lines.append(f"| {_m(r)} | {r['numpy_project_s']:.3f} | "
                         f"{r['numpy_zbuffer_s']:.3f} | {p['project']:.3f} | {p['splat']:.3f} |")
        lines += ["", "GL points through EGL (llvmpipe) were not tried."]
    renders = "; ".join(f"{_m(r)} `{v}` " + ", ".join(f"{t:.3f}" for t in r[f"render_{v}_all"])
                        for r in results for v in VARIANTS)
    lines += ["", ("Coverage of the frame: "
                   + ", ".join(f"{_m(r)} {r['coverage']:.0%}" for r in results)
                   + "; 1000 rays from the camera hit: "
                   + ", ".join(f"{r['rays_1000_hit']:.0%}" for r in results)
                   + ". Normals + spacing is a one-off per file (cached beside it), timed at "
                   "load average " + ", ".join(f"{r.get('normals_load', float('nan')):.1f}"
                                                for r in results)
                   + "; kernels are loaded from numba's on-disk cache (compiling them in a "
                   "fresh install takes ~7 s of CPU, once)."),
              "", f"All full-resolution renders (s): {renders}.",
              "", ("Reproduce: `nice -n 19 .venv/bin/python benchmarks/bench_cloud_render.py "
                   "--sizes 5e6 50e6 --report docs/benchmarks.md`."), MARK_END]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    tune_allocator()
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", nargs="+", type=float, default=[5e6, 50e6])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--report", type=Path)
    ap.add_argument("--prepare", action="store_true",
                    help="only write the scans and their normals caches")
    ap.add_argument("--one", type=float, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.one:
        print(json.dumps(run_one(args.one, args.runs)))
        return
    if args.prepare:
        for n in args.sizes:
            print(f"{n:g}: {prepare(n)}", flush=True)
        return
    results = []
    for n in args.sizes:
        proc = subprocess.run([sys.executable, __file__, "--one", str(n), "--runs", str(args.runs)],
                              capture_output=True, text=True, check=False)
        if proc.returncode != 0:
            sys.exit(f"{n:g} points: {proc.stderr[-2000:]}")
        results.append(json.loads(proc.stdout.strip().splitlines()[-1]))
        r = results[-1]
        print(f"{r['n_points']:,} points: load {r['load_s']:.1f} s, first render "
              f"{r['first_render_s']:.3f} s, render auto {r['render_auto_s']:.3f} s, full "
              f"{r['render_full_s']:.3f} s, before {r['render_before_s']:.3f} s, peak RSS "
              f"{r['peak_rss_gb']:.2f} GB", flush=True)
    from napari_imgreg._atomic import atomic_write

    with atomic_write(CACHE / "results.json") as fh:  # the raw figures
        json.dump(results, fh, indent=1)
    text = report(results, args.runs)
    print(text)
    if args.report:
        write_section(args.report, text, MARK_START, MARK_END)


if __name__ == "__main__":
    main()

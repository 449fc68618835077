"""Render benchmark: scene load, BVH build, full render, feature lifting, peak memory.

On the generated 1.2 M-triangle sample outcrop at the paper's camera
resolution (1632 × 1224). Medians of ``--runs`` repetitions; the report
section of ``docs/benchmarks.md`` between the ``bench_render`` markers is
rewritten (atomically).

    python benchmarks/bench_render.py --report docs/benchmarks.md

Reference (Kehl et al., Table II, NVIDIA Shield K1 tablet, ~1.2 M triangles):
re-rendering 10.757 s, ray casting of features 103.351 s.
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

from napari_imgreg import Intrinsics, Pose, Scene, render
from napari_imgreg._atomic import atomic_write
from napari_imgreg.sample import sample_scene

PAPER_RENDER_S = 10.757
PAPER_RAYCAST_S = 103.351
TARGETS = {"load": 3.0, "build": 2.0, "render": 0.5, "peak_rss_gb": 2.0}
from _report import markers, write_section  # noqa: E402  (benchmarks/ is on sys.path)

MARK_START, MARK_END = markers("bench_render")


def _peak_rss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2  # KiB -> GiB


def _median_time(fn, runs: int) -> tuple[float, list[float]]:
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), times


def _bilinear_lookup(xyz: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Bilinear look-up of (N, 2) pixel positions (x, y) in an (H, W, 3) map."""
    x, y = pixels[:, 0], pixels[:, 1]
    x0 = np.clip(np.floor(x).astype(int), 0, xyz.shape[1] - 2)
    y0 = np.clip(np.floor(y).astype(int), 0, xyz.shape[0] - 2)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    return (
        xyz[y0, x0] * (1 - fx) * (1 - fy)
        + xyz[y0, x0 + 1] * fx * (1 - fy)
        + xyz[y0 + 1, x0] * (1 - fx) * fy
        + xyz[y0 + 1, x0 + 1] * fx * fy
    )


def run(folder: Path, runs: int) -> dict:
    mesh_path = folder / "outcrop.obj"
    truths = sorted(folder.glob("IMG_*.truth.json"))
    if not truths:
        sys.exit(f"{folder}: no IMG_*.truth.json ground truth files")

    parse_s, parse_all = _median_time(lambda: Scene.load(mesh_path, cache=False), runs)
    Scene.load(mesh_path)  # make sure the parsed-mesh cache holds this scene
    load_s, load_all = _median_time(lambda: Scene.load(mesh_path), runs)
    scene = Scene.load(mesh_path)

    def build() -> None:
        Scene(scene.vertices, scene.faces, scene.uv, scene.texture).build_engine()

    build_s, build_all = _median_time(build, runs)
    scene.build_engine()

    cameras = []
    for path in truths:
        truth = json.loads(path.read_text())
        cameras.append((Intrinsics.from_dict(truth["camera"]), Pose.from_dict(truth["pose"])))
    intr, pose = cameras[0]
    render(scene, intr, pose)  # warm caches (ray directions, per-face arrays)

    render_times, coverages = [], []
    for k in range(runs):
        intr_k, pose_k = cameras[k % len(cameras)]
        r = render(scene, intr_k, pose_k)
        render_times.append(r.timings_s["total"])
        coverages.append(r.coverage)
    render_s = statistics.median(render_times)
    preview_s, _ = _median_time(lambda: render(scene, intr, pose, scale=0.25), runs)

    # Lifting 10 000 features: a look-up in the render's xyz map, versus
    # casting one ray per feature (what the 2018 tablet did).
    result = render(scene, intr, pose)
    rng = np.random.default_rng(0)
    pixels = np.column_stack(
        [rng.uniform(0, intr.width - 1, 10_000), rng.uniform(0, intr.height - 1, 10_000)]
    )
    lift_s, _ = _median_time(lambda: _bilinear_lookup(result.xyz, pixels), runs)

    def cast_features() -> None:
        origin, dirs = pose.rays(intr, pixels)
        scene.cast_rays(origin, dirs)

    cast_s, _ = _median_time(cast_features, runs)

    peak_first = _workflow_peak(folder, cache=False)
    peak_cached = _workflow_peak(folder, cache=True)
    return {
        "scene": str(folder),
        "parse_s": parse_s,
        "parse_all_s": parse_all,
        "peak_rss_first_gb": peak_first,
        "triangles": scene.n_faces,
        "texture": list(scene.texture.shape[:2]) if scene.has_texture else None,
        "resolution": [intr.width, intr.height],
        "runs": runs,
        "load_s": load_s,
        "build_s": build_s,
        "render_s": render_s,
        "render_all_s": render_times,
        "render_coverage": statistics.median(coverages),
        "preview_quarter_s": preview_s,
        "lift_10k_lookup_s": lift_s,
        "cast_10k_rays_s": cast_s,
        "peak_rss_gb": peak_cached,
        "peak_rss_benchmark_gb": _peak_rss_gb(),
        "load_all_s": load_all,
        "build_all_s": build_all,
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
    }


def _workflow_peak(folder: Path, cache: bool) -> float:
    """Peak RSS (GB) of a fresh process that loads, builds, renders and lifts once."""
    out = subprocess.run(
        [sys.executable, __file__, "--workflow", str(folder)] + ([] if cache else ["--no-cache"]),
        capture_output=True, text=True, check=True,
    )
    return float(out.stdout.strip().splitlines()[-1])


def workflow(folder: Path, cache: bool) -> None:
    """One user's pass: open the scene, build the engine, render a photo's view, lift."""
    scene = Scene.load(folder / "outcrop.obj", cache=cache)
    scene.build_engine()
    truth = json.loads(sorted(folder.glob("IMG_*.truth.json"))[0].read_text())
    intr, pose = Intrinsics.from_dict(truth["camera"]), Pose.from_dict(truth["pose"])
    result = render(scene, intr, pose)
    result.lift(np.array([[100.0, 200.0], [800.0, 600.0]]))
    print(_peak_rss_gb())


def report(m: dict) -> str:
    def ok(key: str, value: float) -> str:
        return "✅" if value <= TARGETS[key] else "❌"

    w, h = m["resolution"]
    lines = [
        MARK_START,
        "## Rendering (issue: foundation)",
        "",
        f"Generated outcrop, {m['triangles']:,} triangles, texture "
        f"{m['texture'][1]}×{m['texture'][0]}, camera {w}×{h} "
        f"({w * h / 1e6:.1f} M rays), {m['cpus']} cores, Python {m['python']}. "
        f"Medians of {m['runs']} runs; the surface fills {m['render_coverage']:.0%} of the "
        "frame (the rest is sky, whose rays are cheap).",
        "",
        "| stage | median | target | | 2018 tablet (Table II) |",
        "|---|---|---|---|---|",
        f"| scene load, first open (trimesh parses OBJ + MTL + JPEG) | {m['parse_s']:.2f} s | | | |",
        f"| scene load, unchanged files (parsed-mesh cache) | {m['load_s']:.2f} s | ≤ 3 s | "
        f"{ok('load', m['load_s'])} | |",
        f"| BVH build (Embree) | {m['build_s']:.2f} s | ≤ 2 s | {ok('build', m['build_s'])} | |",
        f"| full render, rgb + xyz + depth + normal | {m['render_s']:.3f} s | ≤ 0.5 s | "
        f"{ok('render', m['render_s'])} | {PAPER_RENDER_S} s "
        f"(**{PAPER_RENDER_S / m['render_s']:.0f}× slower**) |",
        f"| quarter-resolution preview render | {m['preview_quarter_s']:.3f} s | | | |",
        f"| lift 10 000 features to 3D (xyz look-up) | {m['lift_10k_lookup_s'] * 1000:.1f} ms | | | "
        f"{PAPER_RAYCAST_S} s ray casting (**{PAPER_RAYCAST_S / m['lift_10k_lookup_s']:,.0f}× "
        "slower**) |",
        f"| cast 10 000 feature rays instead | {m['cast_10k_rays_s'] * 1000:.1f} ms | | | |",
        f"| peak RSS: open (cached), build, render, lift | {m['peak_rss_gb']:.2f} GB | ≤ 2 GB | "
        f"{ok('peak_rss_gb', m['peak_rss_gb'])} | 2 GB device |",
        f"| peak RSS: the same, first open (OBJ parse) | {m['peak_rss_first_gb']:.2f} GB | | | |",
        "",
        "Reproduce: `make bench` (or `.venv/bin/python benchmarks/bench_render.py "
        "--report docs/benchmarks.md`); the large scene is generated once and cached.",
        "",
        "The first open of a mesh is parsed by trimesh (pure-Python OBJ parsing "
        "dominates); napari-imgreg then keeps a binary copy keyed by the files' "
        "paths, sizes and times (`~/.cache/napari-imgreg/meshes`), so every later "
        "open of the unchanged model reads arrays.",
        "",
        "All runs (s): first open " + ", ".join(f"{t:.2f}" for t in m["parse_all_s"])
        + "; cached open " + ", ".join(f"{t:.2f}" for t in m["load_all_s"])
        + "; build " + ", ".join(f"{t:.2f}" for t in m["build_all_s"])
        + "; render " + ", ".join(f"{t:.3f}" for t in m["render_all_s"]) + ".",
        MARK_END,
    ]
    return "\n".join(lines)




def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", type=Path, help="scene folder (default: generated large sample)")
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--report", type=Path, help="markdown file to update")
    parser.add_argument("--json", type=Path, help="also write the raw figures")
    parser.add_argument("--workflow", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--no-cache", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.workflow:
        workflow(args.workflow, cache=not args.no_cache)
        return
    folder = args.scene or sample_scene("large")
    m = run(folder, args.runs)
    section = report(m)
    print(section)
    if args.report:
        write_section(args.report, section, MARK_START, MARK_END)
    if args.json:
        with atomic_write(args.json) as fh:
            json.dump(m, fh, indent=2)


if __name__ == "__main__":
    main()

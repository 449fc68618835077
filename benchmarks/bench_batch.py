"""Benchmark ``napari-imgreg batch`` on Dask: a generated campaign, corrupt
photos, a worker killed mid-run, a resumed run, and throughput against the
number of workers.

What it does (each ``batch`` a subprocess, as a user runs it):

1. Generates (once, cached in ``benchmarks/_cache/``) the small sample
   outcrop with ``--photos`` photos from as many viewpoints, and copies it
   with ``--corrupt`` photos broken (truncated, empty, not an image).
2. **Fault run**: ``batch --workers 2 --threads-per-worker 1`` over it; when
   a third of the photos are done it SIGKILLs one worker process (a child of
   the batch process, chosen as it is registering). Checks: one result per
   good photo, the corrupt ones reported as ``bad_input``, nothing lost
   (every result whole, summary complete), and the killed photo retried.
3. **Resume**: the same with ``--skip-existing``: every done photo skipped.
4. **Throughput**: ``--threads-per-worker 1`` with each of ``--workers`` (1, 2,
   4 by default) on the clean copy, and the defaults (no option): photos per
   minute, end to end (cluster start, scene loads and all), and the speed-up
   over one worker.

Small check (a few minutes)::

    nice .venv/bin/python benchmarks/bench_batch.py --photos 12 --workers 1 2

Full run for docs/benchmarks.md (on a quiet 2-core machine about 25 min,
plus about 5 min to generate the campaign the first time)::

    .venv/bin/python benchmarks/bench_batch.py --photos 100 --workers 1 2 4 \\
        --report docs/benchmarks.md
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from _report import markers, write_section  # benchmarks/ is on sys.path

from napari_imgreg.registration.batch import available_cores, default_workers
from napari_imgreg.sample import generate_outcrop
from napari_imgreg.sample.outcrop import OutcropSpec

MARK_START, MARK_END = markers("bench_batch")
CACHE = Path(__file__).parent / "_cache"
ROOT = Path(__file__).resolve().parents[1]
#: The scene's model files, copied with the photos.
MODEL_FILES = ("outcrop.obj", "outcrop.mtl", "outcrop_texture.jpg", "dem.tif", "georef.json")


# ------------------------------------------------------------- campaign
def campaign(n_photos: int, seed: int) -> Path:
    """The small sample outcrop with ``n_photos`` photos (generated once)."""
    folder = CACHE / f"batch_campaign_{n_photos}_s{seed}"
    if (folder / "scene.json").is_file():
        return folder
    t0 = time.perf_counter()
    print(f"generating a {n_photos}-photo campaign into {folder} ...", flush=True)
    tmp = folder.with_name(folder.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    generate_outcrop(tmp, "small", seed=seed,
                     spec=replace(OutcropSpec.for_size("small"), n_photos=n_photos))
    tmp.rename(folder)
    print(f"  generated in {time.perf_counter() - t0:.0f} s", flush=True)
    return folder


def scene_copy(source: Path, dest: Path, corrupt: int) -> tuple[Path, list[str]]:
    """A scene folder of the model and photos (records beside them), ``corrupt``
    photos broken in three ways; returns it and the broken photos' names."""
    shutil.rmtree(dest, ignore_errors=True)
    dest.mkdir(parents=True)
    for name in MODEL_FILES:
        shutil.copy2(source / name, dest / name)
    photos = sorted(source.glob("IMG_*.jpg"))
    for photo in photos:
        for path in (photo, photo.with_suffix(".json")):
            shutil.copy2(path, dest / path.name)
    broken = []
    step = max(1, len(photos) // max(1, corrupt))
    for k in range(corrupt):
        target = dest / photos[(k * step + step // 2) % len(photos)].name
        data = target.read_bytes()
        target.write_bytes((data[: len(data) // 5], b"", b"this is not a JPEG\n")[k % 3])
        broken.append(target.name)
    return dest, broken


# ------------------------------------------------------------------ runs
def batch_command(scene: Path, out: Path, *options: str) -> list[str]:
    return [sys.executable, "-m", "napari_imgreg", "batch", str(scene), "--out", str(out),
            *options]


def run_batch(scene: Path, out: Path, *options: str, kill_after: int | None = None,
              log: Path | None = None) -> dict:
    """Run ``batch``; with ``kill_after``, SIGKILL one worker process once that
    many results exist. Returns the wall time, exit code, summary and kill."""
    shutil.rmtree(out, ignore_errors=True) if "--skip-existing" not in options else None
    log = log or out.with_suffix(".log")
    t0 = time.perf_counter()
    with open(log, "w") as fh:
        proc = subprocess.Popen(batch_command(scene, out, *options), stdout=fh,
                                stderr=subprocess.STDOUT, cwd=ROOT,
                                env={**os.environ, "PYTHONPATH": str(ROOT / "src")})
        killed = None
        while proc.poll() is None:
            if kill_after is not None and killed is None and out.is_dir() \
                    and len(list(out.glob("*.result.json"))) >= kill_after:
                workers = worker_processes(proc.pid)
                if workers:
                    victim = workers[0]
                    os.kill(victim, signal.SIGKILL)
                    killed = {"pid": victim, "after_results": len(list(out.glob("*.result.json"))),
                              "at_s": round(time.perf_counter() - t0, 1)}
                    print(f"  killed worker process {victim} after {killed['after_results']} "
                          f"results", flush=True)
            time.sleep(0.2)
    wall = time.perf_counter() - t0
    summary = json.loads((out / "summary.json").read_text()) if (out / "summary.json").is_file() \
        else {}
    return {"wall_s": wall, "code": proc.returncode, "summary": summary, "killed": killed,
            "log": log}


def worker_processes(parent: int) -> list[int]:
    """Dask worker processes of a local cluster: the batch's children started by
    multiprocessing's spawn (not its resource tracker)."""
    out = []
    for child in _children(parent):
        try:
            cmdline = Path(f"/proc/{child}/cmdline").read_bytes().replace(b"\0", b" ")
        except OSError:
            continue
        if b"multiprocessing" in cmdline and b"resource_tracker" not in cmdline:
            out.append(child)
    return out


def _children(pid: int) -> list[int]:
    """Child processes of ``pid`` (from /proc/*/stat: Linux)."""
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return sorted(out)


def check_fault_run(run: dict, n_photos: int, broken: list[str], out: Path) -> dict:
    """The must-show checks of the fault run; returns what was found."""
    summary = run["summary"]
    rows = summary.get("photos", [])
    by_status: dict[str, list[str]] = {}
    for row in rows:
        by_status.setdefault(row["status"], []).append(row["photo"])
    results = sorted(out.glob("*.result.json"))
    whole = 0
    for path in results:
        try:
            json.loads(path.read_text())
            whole += 1
        except ValueError:
            pass
    good = n_photos - len(broken)
    found = {
        "rows": len(rows),
        "results": len(results),
        "results_whole": whole,
        "registered": len(by_status.get("registered", [])),
        "failed": len(by_status.get("failed", [])),
        "bad_input": sorted(by_status.get("bad_input", [])),
        "error": sorted(by_status.get("error", [])),
        "complete": bool(summary.get("complete")),
        "temporary_files": len(list(out.glob(".*"))),
    }
    found["ok"] = (found["rows"] == n_photos and found["results"] == good == whole
                   and found["bad_input"] == sorted(broken) and not found["error"]
                   and found["complete"] and run["killed"] is not None)
    return found


def throughput_runs(scene: Path, work: Path, workers: list[int], n_photos: int) -> list[dict]:
    rows = []
    configs = [(f"--workers {n} --threads-per-worker 1",
                ["--workers", str(n), "--threads-per-worker", "1"]) for n in workers]
    n_default = default_workers(1, n_photos)
    configs.append((f"defaults ({n_default} worker(s) × 1 thread)", []))
    for label, options in configs:
        print(f"throughput: {label} ...", flush=True)
        run = run_batch(scene, work / f"tp_{len(rows)}", *options)
        counts = run["summary"].get("counts", {})
        per_photo = [r["seconds"] for r in run["summary"].get("photos", []) if r.get("seconds")]
        rows.append({"label": label, "wall_s": run["wall_s"], "code": run["code"],
                     "registered": counts.get("registered", 0),
                     "failed": counts.get("failed", 0),
                     "photos_per_min": 60.0 * n_photos / run["wall_s"],
                     "photo_s_median": sorted(per_photo)[len(per_photo) // 2] if per_photo
                     else None, "photo_s_sum": sum(per_photo),
                     # Other work on the machine shows here (the runs are meant alone).
                     "load_after": os.getloadavg()[0]})
        print(f"  {rows[-1]['wall_s']:.0f} s, {rows[-1]['photos_per_min']:.1f} photos/min",
              flush=True)
    base = rows[0]["photos_per_min"]
    for row in rows:
        row["speedup"] = row["photos_per_min"] / base
    return rows


# ---------------------------------------------------------------- report
def report(args, n_photos, broken, fault, fault_found, resume, tp) -> str:
    lines = [MARK_START, "## bench_batch: `batch` on Dask distributed", ""]
    lines.append(
        f"A generated campaign: the small sample outcrop (127 k triangles) with {n_photos} "
        f"photos from as many viewpoints, {len(broken)} of them corrupt "
        f"({', '.join(broken)}: truncated, empty, not an image). Each `batch` is a "
        f"subprocess, timed end to end (cluster start and one scene load per worker "
        f"included). Machine: {available_cores()} core(s), Python "
        f"{platform.python_version()}; load average (1 min) {args.load_before:.1f} before "
        f"the first run"
        # The load after a run includes that run's own workers (shown per row),
        # so only the load before the first run tells of other work.
        + (" (above the core count: other work shared the cores and the throughput "
           "figures are not clean)." if args.load_before > available_cores() else "."))
    lines += ["", "**Fault run** (`--workers 2 --threads-per-worker 1`, one worker process "
              "SIGKILLed by the benchmark mid-run):", ""]
    k = fault["killed"] or {}
    lines += [
        "| check | found |", "|---|---|",
        f"| worker killed | pid {k.get('pid')} after {k.get('after_results')} results, "
        f"at {k.get('at_s')} s |",
        f"| results (one per good photo, each whole JSON) | {fault_found['results']} "
        f"({fault_found['results_whole']} whole) of {n_photos - len(broken)} |",
        f"| registered / failed its quality bar | {fault_found['registered']} / "
        f"{fault_found['failed']} |",
        f"| reported bad input | {len(fault_found['bad_input'])}: "
        f"{', '.join(fault_found['bad_input'])} |",
        f"| photos lost with the worker (status error) | {len(fault_found['error'])} |",
        f"| summary complete, temporary files left | {fault_found['complete']}, "
        f"{fault_found['temporary_files']} |",
        f"| exit code (2: bad input among the photos) | {fault['code']} |",
        f"| wall time | {fault['wall_s']:.0f} s |",
        f"| **all checks** | **{'pass' if fault_found['ok'] else 'FAIL'}** |",
    ]
    counts = resume["summary"].get("counts", {})
    lines += ["", f"**Rerun with `--skip-existing`**: {counts.get('skipped', 0)} skipped "
              f"(of {n_photos - len(broken)} done), {counts.get('bad_input', 0)} bad input "
              f"reported again, {counts.get('registered', 0) - counts.get('skipped', 0)} "
              f"registered again, {resume['wall_s']:.0f} s.", ""]
    lines += ["**Throughput** (clean copy, all photos good):", "",
              "| configuration | wall time | photos / min | speed-up over 1 worker "
              "| median s / photo | sum of photo s | registered | load average at the end |",
              "|---|---|---|---|---|---|---|---|"]
    for row in tp:
        median = "" if row["photo_s_median"] is None else f"{row['photo_s_median']:.1f}"
        lines.append(f"| {row['label']} | {row['wall_s']:.0f} s | {row['photos_per_min']:.1f} "
                     f"| {row['speedup']:.2f}× | {median} | {row.get('photo_s_sum', 0):.0f} s "
                     f"| {row['registered']} | {row.get('load_after', float('nan')):.1f} |")
    two = next((r for r in tp if r["label"].startswith("--workers 2 ")), None)
    if two is not None:
        verdict = "met" if two["speedup"] >= 1.7 else "NOT met"
        lines += ["", f"Two workers against one, one thread each: {two['speedup']:.2f}× "
                  f"(target ≥ 1.7× on 2 cores: {verdict})."]
    lines += ["", f"Reproduce: `{args.command}`", MARK_END]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--photos", type=int, default=100, help="photos in the campaign")
    parser.add_argument("--corrupt", type=int, default=3, help="of them made corrupt")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2, 4],
                        help="worker counts of the throughput runs (first is the baseline)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--work", type=Path, default=CACHE / "bench_batch_runs",
                        help="folder for the scene copies and results")
    parser.add_argument("--report", type=Path, help="markdown file to update")
    args = parser.parse_args(argv)
    args.command = "python benchmarks/bench_batch.py " + " ".join(
        a for a in (argv if argv is not None else sys.argv[1:]))

    args.load_before = os.getloadavg()[0]
    source = campaign(args.photos, args.seed)
    args.work.mkdir(parents=True, exist_ok=True)
    # Throughput first: it is the figure that needs a quiet machine.
    clean, _ = scene_copy(source, args.work / "scene_clean", 0)
    tp = throughput_runs(clean, args.work, args.workers, args.photos)
    scene, broken = scene_copy(source, args.work / "scene_corrupt", args.corrupt)
    print(f"fault run: {args.photos} photos, {len(broken)} corrupt, kill a worker ...",
          flush=True)
    out = args.work / "fault"
    fault = run_batch(scene, out, "--workers", "2", "--threads-per-worker", "1",
                      kill_after=max(1, args.photos // 3))
    found = check_fault_run(fault, args.photos, broken, out)
    print(f"  {json.dumps(found)}", flush=True)
    resume = run_batch(scene, out, "--workers", "2", "--threads-per-worker", "1",
                       "--skip-existing", log=out.with_name("resume.log"))
    counts = resume["summary"].get("counts", {})
    found["resume_ok"] = (counts.get("skipped") == found["results"]
                          and counts.get("bad_input") == len(broken))
    found["ok"] = found["ok"] and found["resume_ok"]
    print(f"  resume: {counts} in {resume['wall_s']:.0f} s", flush=True)
    section = report(args, args.photos, broken, fault, found, resume, tp)
    print(section)
    if args.report:
        write_section(args.report, section, MARK_START, MARK_END)
    return 0 if found["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())

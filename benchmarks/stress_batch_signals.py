"""Stress ``napari-imgreg batch`` on a local Dask cluster with SIGTERM and SIGINT
sent at chosen moments; check what each run leaves.

Each trial starts ``batch`` (its own session, as a job scheduler or a terminal
runs it), waits for a moment of the run, sends the signal and checks: the exit
code (143 after SIGTERM, 130 after SIGINT), that stderr is the one line
``terminated (SIGTERM)`` / ``interrupted`` and nothing else (no ``terminate
called without an active exception``, no traceback), and the summary (valid
JSON, ``interrupted: true`` with the right ``signal``, every result it lists
whole and every result in the folder listed, no ``batch.lock`` left).

Moments (``--phases``):

- ``startup``: the scene is loaded, the local cluster is starting;
- ``worker_scene``: the first photos were submitted, the workers load the scene;
- ``mid``: photos are registering;
- ``stall``: mid-photo, and then the command's process is stopped for 1.2 s
  about Dask's 4 s close timeout (SIGSTOP/SIGCONT), as a loaded machine
  delays it: the worker then reaches its own exit first. Before the worker
  plugin ``_NoFinalizingMidPhoto`` this printed ``terminate called without an
  active exception`` in 10 of 12 trials;
- ``final``: just after the last photo was reported (summary, cluster close).

Example (about 15 minutes on a 2-core machine; the campaign is generated once
into ``benchmarks/_cache/`` as ``bench_batch.py`` does)::

    nice .venv/bin/python benchmarks/stress_batch_signals.py --trials 30

Exit code 1 when any trial went wrong; one JSON line per trial on stdout.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from bench_batch import campaign, scene_copy  # benchmarks/ is on sys.path

ROOT = Path(__file__).resolve().parents[1]
#: Moment -> (what the stdout line starts with, random delay after it, s).
PHASES = {
    "startup": (lambda line, n: line.startswith("scene "), (0.0, 2.5)),
    "worker_scene": (lambda line, n: line.startswith("registering"), (0.0, 2.0)),
    "mid": (lambda line, n: line.startswith("["), (0.0, 4.0)),
    "stall": (lambda line, n: line.startswith("["), (0.5, 2.5)),
    "final": (lambda line, n: line.startswith(f"[{n}/{n}]"), (0.0, 0.8)),
}
#: Cluster shapes the trials cycle through.
SHAPES = (["--workers", "2"], ["--workers", "1"], ["--workers", "2", "--threads-per-worker", "2"])


def summary_problems(out: Path, signal_name: str) -> list[str]:
    """What is wrong with RESULTS_DIR after an interrupt (empty: nothing)."""
    try:
        summary = json.loads((out / "summary.json").read_text())
    except (OSError, ValueError) as exc:
        return [f"summary.json: {exc}"]
    problems = []
    if summary.get("complete") or summary.get("interrupted") is not True:
        problems.append(f"complete={summary.get('complete')} "
                        f"interrupted={summary.get('interrupted')}")
    if summary.get("signal") != signal_name:
        problems.append(f"signal={summary.get('signal')}")
    listed = {row["result"] for row in summary["photos"] if row.get("result")}
    for name in sorted(listed):
        try:
            json.loads((out / name).read_text())
        except (OSError, ValueError) as exc:
            problems.append(f"{name}: {exc}")
    on_disk = {p.name for p in out.glob("*.result.json")}
    if listed != on_disk:
        problems.append(f"listed but missing {sorted(listed - on_disk)}, "
                        f"there but not listed {sorted(on_disk - listed)}")
    if (out / "batch.lock").exists():
        problems.append("batch.lock left")
    return problems


def trial(scene: Path, out: Path, phase: str, options: list[str], signal_name: str,
          to_group: bool, n_photos: int) -> dict:
    """One run of ``batch``, interrupted at ``phase``; returns what was found."""
    shutil.rmtree(out, ignore_errors=True)
    err_path = out.with_suffix(".stderr")
    with open(err_path, "w") as err:
        proc = subprocess.Popen(
            [sys.executable, "-m", "napari_imgreg", "batch", str(scene), "--out", str(out),
             *options], stdout=subprocess.PIPE, stderr=err, text=True, cwd=ROOT,
            env={**os.environ, "PYTHONPATH": str(ROOT / "src")}, start_new_session=True,
            # A background job of a script starts with SIGINT ignored, and so would batch.
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)
    reader.start()
    reached, (low, high) = PHASES[phase]
    t0 = time.monotonic()
    while proc.poll() is None and time.monotonic() - t0 < 600:
        if any(reached(line, n_photos) for line in list(lines)):
            time.sleep(random.uniform(low, high))
            break
        time.sleep(0.02)
    if proc.poll() is not None:
        return {"phase": phase, "options": options, "signal": signal_name, "sent": False,
                "code": proc.returncode, "problems": []}
    sent_at = time.monotonic()
    (os.killpg if to_group else os.kill)(proc.pid, getattr(signal, signal_name))
    if phase == "stall":  # the command late for Dask's 4 s close timeout
        time.sleep(3.6)
        os.kill(proc.pid, signal.SIGSTOP)
        time.sleep(1.2)
        os.kill(proc.pid, signal.SIGCONT)
    try:
        code = proc.wait(timeout=120)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        code = "hung"
    exit_s = time.monotonic() - sent_at
    # Worker processes that outlive the command still write to its stderr.
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and subprocess.run(
            ["pgrep", "-s", str(proc.pid)], capture_output=True).returncode == 0:
        time.sleep(0.1)
    stderr = err_path.read_text()
    expected = (143, "terminated (SIGTERM)") if signal_name == "SIGTERM" else (130, "interrupted")
    problems = summary_problems(out, signal_name)
    if code != expected[0]:
        problems.append(f"exit code {code}")
    if stderr.strip() != expected[1]:
        problems.append(f"stderr: {stderr[-400:]!r}")
    return {"phase": phase, "options": options, "signal": signal_name, "group": to_group,
            "sent": True, "code": code, "exit_s": round(exit_s, 2), "problems": problems}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trials", type=int, default=30)
    parser.add_argument("--photos", type=int, default=16, help="photos of the campaign")
    parser.add_argument("--phases", nargs="+", default=list(PHASES), choices=list(PHASES))
    parser.add_argument("--signals", nargs="+", default=["SIGTERM"],
                        choices=["SIGTERM", "SIGINT"])
    parser.add_argument("--seed", type=int, default=0, help="of the random delays")
    args = parser.parse_args()
    random.seed(args.seed)
    work = Path(tempfile.mkdtemp(prefix="imgreg-signals-"))
    scene, _ = scene_copy(campaign(args.photos, seed=0), work / "scene", corrupt=0)
    plan = itertools.islice(itertools.cycle(itertools.product(
        args.phases, SHAPES, args.signals)), args.trials)
    failed = 0
    for k, (phase, options, signal_name) in enumerate(plan):
        # SIGINT as a terminal sends it (the whole group) every other time.
        found = trial(scene, work / f"out{k}", phase, list(options), signal_name,
                      to_group=signal_name == "SIGINT" and k % 2 == 0, n_photos=args.photos)
        failed += bool(found["problems"])
        print(json.dumps(found), flush=True)
    print(f"{args.trials} trials, {failed} with problems; runs kept in {work}", flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())

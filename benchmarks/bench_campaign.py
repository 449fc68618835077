"""Benchmark a campaign of many photos kept as a workspace: the command line,
the Python API and the workbench, at 20, 100 and 300 photos.

What it does, per campaign size N:

1. A scene folder of the small sample outcrop (127 k triangles) with N photos:
   the ``--source``-photo campaign of ``bench_batch`` (generated once, cached in
   ``benchmarks/_cache/``), its photos copied round-robin under new names, each
   with its own sensor record.
2. **Command line** (each a subprocess, timed end to end, Python's start and
   imports included: the first row says how long those take alone):
   ``workspace create``; ``workspace add`` of one more photo; ``workspace
   register`` of one photo with the registration's own seconds taken off (the
   bookkeeping: opening, recording, saving); ``workspace lines``; ``workspace info``.
3. Between 2's steps, through the Python API (not timed): a third of the photos
   get a registration (one real one, made once on the first photo, recorded
   on the others with their true poses), a tenth of them (registered ones)
   their drawn lines, which are then projected.
4. **Python API**: open (with the model read, and with the model given),
   switch the current photo, save after one edit (a nudge, a drawing), save as
   a new folder, and the folder's size on disk.
5. **Workbench** (a real napari window; needs a display, e.g. ``xvfb-run``):
   opening the workspace (until the window is idle again), switching photo in
   the photos table, rebuilding the table, recording one photo's registration
   (as Register all does), a nudge, *Save workspace as*, and opening another
   workspace over it. A 10 ms QTimer heartbeat records the gaps of the GUI
   thread: the longest is each step's stall.

Full run for docs/benchmarks.md (about 15 minutes on 2 cores, plus about a
minute to generate the source campaign the first time)::

    xvfb-run -a -s "-screen 0 1600x1000x24" .venv/bin/python benchmarks/bench_campaign.py \\
        --report docs/benchmarks.md

``--before FILE.json`` puts the figures of an earlier run (``--json``) beside
this run's in the report: run the script with ``PYTHONPATH`` pointing at the
older code's ``src`` to measure it (``git archive COMMIT src | tar -x -C DIR``).
``--report-only`` writes the report of the figures in ``--json`` without measuring.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import shutil
import statistics
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _report import markers, write_section  # benchmarks/ is on sys.path
from bench_batch import CACHE, MODEL_FILES, campaign

import napari_imgreg

MARK_START, MARK_END = markers("bench_campaign")
ROOT = Path(__file__).resolve().parents[1]
#: The ``src`` folder of the napari_imgreg measured (this checkout's, or PYTHONPATH's).
SRC = Path(napari_imgreg.__file__).resolve().parents[1]
#: Targets (seconds): a geologist's patience.
TARGETS = {"open_s": 3.0, "open_stall_s": 0.5, "switch_stall_s": 0.3, "save_s": 1.0}
#: Every how many photos one is registered, and (among those) drawn on.
REGISTERED_EVERY = 3
DRAWN_EVERY = 10


# -------------------------------------------------------------- campaign
def scene_of(source: Path, n_photos: int, dest: Path) -> Path:
    """A scene folder with the model and ``n_photos`` photos copied round-robin
    from ``source`` (``IMG_0001.jpg`` …), each with its own sensor record."""
    if (dest / f"IMG_{n_photos:04d}.json").is_file():
        return dest
    shutil.rmtree(dest, ignore_errors=True)
    dest.mkdir(parents=True)
    for name in MODEL_FILES:
        os.link(source / name, dest / name)
    photos = sorted(source.glob("IMG_*.jpg"))
    for k in range(n_photos):
        src = photos[k % len(photos)]
        shutil.copyfile(src, dest / f"IMG_{k + 1:04d}.jpg")
        shutil.copyfile(src.with_suffix(".json"), dest / f"IMG_{k + 1:04d}.json")
    return dest


def source_photo(source: Path, name: str) -> Path:
    """The source photo a scene photo (``IMG_0042.jpg``) was copied from."""
    photos = sorted(source.glob("IMG_*.jpg"))
    return photos[(int(Path(name).stem.split("_")[1]) - 1) % len(photos)]


def fill_workspace(folder: Path, source: Path) -> dict:
    """Give the workspace its registrations, drawings and projection (not timed)."""
    from napari_imgreg.camera import Pose
    from napari_imgreg.interpret import files as interpret_files
    from napari_imgreg.workspace import Workspace

    ws = Workspace.open(folder)
    try:
        ws.select_photo(0)
        reg = ws.register(auto=False)  # one real registration: its trials and matches
        for k, ps in enumerate(ws.photos):
            if k == 0 or k % REGISTERED_EVERY:
                continue
            truth = json.loads(source_photo(source, ps.name).with_suffix(".truth.json")
                               .read_text())
            pose = Pose.from_dict(truth["pose"])
            ws.record_registration(
                replace(reg, photo=ps.name, pose=pose, prior=ps.prior, intrinsics=ps.intrinsics),
                "Auto", ps, pose_if_not_current=True)
            if k % (REGISTERED_EVERY * DRAWN_EVERY) == REGISTERED_EVERY:
                lines = source_photo(source, ps.name).with_suffix(".lines.geojson")
                ws.set_interpretations(interpret_files.read_interpretations(lines), ps=ps)
        features = ws.project_interpretations()
        return {"registered": sum(ps.registration is not None for ps in ws.photos),
                "drawn": sum(bool(ps.interpretations) for ps in ws.photos),
                "features": len(features)}
    finally:
        ws.detach()


# ------------------------------------------------------------------ CLI
def cli(*args: str) -> tuple[float, str]:
    """Run ``napari-imgreg ARGS`` as a user does; returns its wall time and output."""
    env = {**os.environ, "PYTHONPATH": str(SRC)}
    t0 = time.perf_counter()
    out = subprocess.run([sys.executable, "-m", "napari_imgreg", *args], cwd=ROOT, env=env,
                         capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if out.returncode not in (0, 1):
        raise RuntimeError(f"napari-imgreg {' '.join(args)}: exit {out.returncode}\n"
                           f"{out.stdout}\n{out.stderr}")
    return wall, out.stdout + out.stderr


def folder_size(folder: Path) -> int:
    """Bytes of the files under ``folder``."""
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


def measure_cli(n_photos: int, scene: Path, work: Path, source: Path) -> dict:
    ws_folder = work / f"campaign_{n_photos}.imgreg"
    shutil.rmtree(ws_folder, ignore_errors=True)
    m: dict = {}
    m["create_s"], _ = cli("workspace", "create", str(ws_folder), str(scene))
    m["fill"] = fill_workspace(ws_folder, source)
    extra = work / "extra"
    extra.mkdir(exist_ok=True)
    for suffix in (".jpg", ".json"):
        shutil.copyfile(scene / f"IMG_0001{suffix}", extra / f"IMG_X{n_photos:04d}{suffix}")
    m["add_s"], _ = cli("workspace", "add", str(ws_folder), str(extra / f"IMG_X{n_photos:04d}.jpg"))
    wall, out = cli("workspace", "register", str(ws_folder), "--photo", "IMG_0002.jpg",
                    "--redo", "--once")
    found = re.search(r"trial\(s\), ([0-9.]+) s", out)
    m["register_wall_s"] = wall
    m["register_photo_s"] = float(found.group(1)) if found else float("nan")
    m["register_overhead_s"] = wall - m["register_photo_s"]
    lines = source_photo(source, "IMG_0004.jpg").with_suffix(".lines.geojson")
    m["lines_s"], _ = cli("workspace", "lines", str(ws_folder), "IMG_0004.jpg", str(lines))
    m["info_s"], out = cli("workspace", "info", str(ws_folder))
    m["info_lines"] = out.count("\n")
    m["size_bytes"] = folder_size(ws_folder)
    m["folder"] = str(ws_folder)
    return m


# ------------------------------------------------------------ Python API
def measure_api(folder: Path, work: Path) -> dict:
    from napari_imgreg.interpret.project import Interpretation
    from napari_imgreg.workspace import Workspace, read_scene

    m: dict = {}
    t0 = time.perf_counter()
    ws = Workspace.open(folder)
    m["open_s"] = time.perf_counter() - t0
    scene, terrain, files = ws.scene, ws.terrain, dict(ws.scene_files)
    ws.detach()
    del ws
    t0 = time.perf_counter()
    scene, terrain = read_scene(files["mesh"], files.get("dem") or None,
                                files.get("georef") or None)
    m["model_read_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    ws = Workspace.open(folder, scene=scene, terrain=terrain)
    m["open_model_given_s"] = time.perf_counter() - t0
    n = len(ws.photos)
    switches = []
    for k in range(12):
        index = (k * 37 + 5) % n
        t0 = time.perf_counter()
        ws.select_photo(index)
        switches.append(time.perf_counter() - t0)
    m["switch_s"] = _stats(switches)
    nudges = []
    for k in range(8):
        t0 = time.perf_counter()
        ws.nudge("turn right 0.1", d_trend=0.1 if k % 2 else -0.1)
        nudges.append(time.perf_counter() - t0)
    m["nudge_save_s"] = _stats(nudges)
    line = Interpretation("LineString", np.array([[100.0, 100.0], [300.0, 120.0]]),
                          {"label": "bed"})
    t0 = time.perf_counter()
    ws.add_interpretation(line)
    m["draw_save_s"] = time.perf_counter() - t0
    target = work / f"{folder.stem}_saved_as.imgreg"
    shutil.rmtree(target, ignore_errors=True)
    t0 = time.perf_counter()
    ws.save(target)
    m["save_as_s"] = time.perf_counter() - t0
    ws.detach()
    shutil.rmtree(target, ignore_errors=True)
    return m


def _stats(values: list[float]) -> dict:
    return {"median": statistics.median(values), "max": max(values), "n": len(values)}


# ------------------------------------------------------------- workbench
def measure_gui(folders: dict[int, Path], work: Path) -> dict[int, dict]:
    """The workbench's steps on each workspace (see the module docstring)."""
    import napari
    from qtpy.QtCore import QTimer
    from qtpy.QtWidgets import QApplication

    from napari_imgreg.widgets.campaign import CampaignView
    from napari_imgreg.widgets.workbench import Workbench

    app = QApplication.instance() or QApplication([])
    beats: list[float] = []
    heartbeat = QTimer()
    heartbeat.setInterval(10)
    heartbeat.timeout.connect(lambda: beats.append(time.perf_counter()))
    heartbeat.start()

    def pump(seconds: float) -> None:
        end = time.perf_counter() + seconds
        while time.perf_counter() < end:
            app.processEvents()
            time.sleep(0.001)

    def wait(cond, timeout: float = 300.0) -> float:
        end = time.perf_counter() + timeout
        while not cond():
            app.processEvents()
            time.sleep(0.001)
            if time.perf_counter() > end:
                raise TimeoutError
        return time.perf_counter()

    def stall(t0: float, t1: float) -> float:
        """The longest the GUI thread did not answer between t0 and t1, seconds."""
        points = [t0] + [b for b in beats if t0 < b < t1] + [t1]
        return max(b - a for a, b in zip(points, points[1:]))

    def step(action, done=lambda: True, settle: bool = True) -> dict:
        """Run ``action`` on the GUI thread; time until ``done`` and idle, and its stall."""
        t0 = time.perf_counter()
        action()
        t_done = wait(done)
        if settle:
            wait(lambda: not ctrl.busy)
        # The window answers again: the next heartbeat after the step.
        n_before = len(beats)
        t_end = wait(lambda: len(beats) > n_before)
        return {"s": t_done - t0, "idle_s": t_end - t0, "stall_s": stall(t0, t_end)}

    results: dict[int, dict] = {}
    for n_photos, folder in folders.items():
        viewer = napari.Viewer(title="bench_campaign", show=True)
        viewer.window._qt_window.resize(1600, 1000)
        wb = Workbench.add_to_viewer(viewer)
        ctrl = wb.controller
        view = CampaignView(viewer)
        viewer.window.add_dock_widget(view, name="Campaign view", area="left")
        pump(1.0)
        table = wb.photos_table
        wb.show_tab("Photos")
        m: dict = {}

        def open_step(path: Path) -> dict:
            """Open ``path`` in the workbench, until its photos fill the table."""
            resolved = path.resolve()
            return step(lambda: ctrl.open_workspace(path),
                        lambda: (ctrl.workspace.folder == resolved
                                 and table.table.rowCount() == len(ctrl.photos)
                                 and not ctrl.busy))

        m["open"] = open_step(folder)
        pump(0.5)
        n = len(ctrl.photos)
        switches = []
        for k in range(6):
            index = (k * 37 + 11) % n
            row = table.row_of(index)
            switches.append(step(lambda: table.table.selectRow(row),
                                 lambda: ctrl.workspace.current_index == index))
        m["switch"] = switches
        refreshes = [step(table.refresh, settle=False) for _ in range(3)]
        m["table_refresh"] = refreshes
        ws = ctrl.workspace
        registered = next(ps for ps in ws.photos if ps.registration is not None)
        other = next(ps for ps in ws.photos
                     if ps is not ws.current and ps.registration is None)
        m["record_registration"] = step(lambda: ws.record_registration(
            replace(registered.registration, photo=other.name), "Auto", other,
            pose_if_not_current=True))
        m["nudge"] = step(lambda: ctrl.nudge("turn right 0.1", d_trend=0.1))
        target = work / f"gui_{n_photos}_saved_as.imgreg"
        shutil.rmtree(target, ignore_errors=True)
        # Written in a worker behind its dialog: done when the folder is complete.
        m["save_as"] = step(lambda: ctrl.save_workspace(target), lambda: not ctrl.saving)
        # Another workspace over this one (the photos visited have layers to replace).
        again = work / f"gui_{n_photos}_copy.imgreg"
        shutil.rmtree(again, ignore_errors=True)
        ctrl.workspace.detach()
        shutil.copytree(folder, again)
        m["open_over"] = open_step(again)
        pump(0.3)
        ctrl.workspace.detach()
        viewer.close()
        pump(0.5)
        shutil.rmtree(target, ignore_errors=True)
        shutil.rmtree(again, ignore_errors=True)
        results[n_photos] = m
        print(f"  GUI {n_photos}: open {m['open']['idle_s']:.2f} s "
              f"(stall {m['open']['stall_s']:.2f} s)", flush=True)
    heartbeat.stop()
    return results


# ---------------------------------------------------------------- report
def _s(x: float | None) -> str:
    return "–" if x is None else (f"{x:.2f}" if x < 10 else f"{x:.0f}")


def _worst(steps: list[dict], key: str) -> float:
    return max(s[key] for s in steps)


def rows_of(r: dict) -> list[tuple[str, str, float, float | None]]:
    """(what, kind, seconds, target) of one run's figures for one campaign size."""
    c, a, g = r["cli"], r["api"], r.get("gui")
    rows = [
        ("CLI: Python start and imports alone (`--version`)", "cli", r["startup_s"], None),
        ("CLI: `workspace create` (scene and every photo)", "cli", c["create_s"], None),
        ("CLI: `workspace add` one photo", "cli", c["add_s"], None),
        ("CLI: `workspace register` one photo, its registration taken off", "cli",
         c["register_overhead_s"], None),
        ("CLI: `workspace lines` on one photo", "cli", c["lines_s"], None),
        ("CLI: `workspace info` (the listing)", "cli", c["info_s"], None),
        ("API: `Workspace.open` (model read included)", "api", a["open_s"], TARGETS["open_s"]),
        ("API: `Workspace.open`, model given (the photos' part)", "api",
         a["open_model_given_s"], None),
        ("API: switch photo (`select_photo`), worst of 12", "api", a["switch_s"]["max"],
         TARGETS["switch_stall_s"]),
        ("API: save after a nudge (autosave), worst of 8", "api", a["nudge_save_s"]["max"],
         TARGETS["save_s"]),
        ("API: save after a drawn line (autosave)", "api", a["draw_save_s"], TARGETS["save_s"]),
        ("API: save as a new folder (every photo)", "api", a["save_as_s"], TARGETS["save_s"]),
    ]
    if g:
        rows += [
            ("GUI: open the workspace, until idle", "gui", g["open"]["idle_s"],
             TARGETS["open_s"]),
            ("GUI: open, longest stall", "gui", g["open"]["stall_s"], TARGETS["open_stall_s"]),
            ("GUI: switch photo in the table, until idle (worst of 6)", "gui",
             _worst(g["switch"], "idle_s"), None),
            ("GUI: switch photo, longest stall", "gui", _worst(g["switch"], "stall_s"),
             TARGETS["switch_stall_s"]),
            ("GUI: photos table rebuilt, longest stall (worst of 3)", "gui",
             _worst(g["table_refresh"], "stall_s"), TARGETS["switch_stall_s"]),
            ("GUI: one photo's registration recorded (Register all's step), longest stall",
             "gui", g["record_registration"]["stall_s"], TARGETS["switch_stall_s"]),
            ("GUI: nudge (autosave), longest stall", "gui", g["nudge"]["stall_s"],
             TARGETS["switch_stall_s"]),
            ("GUI: Save workspace as, longest stall", "gui", g["save_as"]["stall_s"],
             TARGETS["save_s"]),
            ("GUI: open another workspace over it, until idle", "gui",
             g["open_over"]["idle_s"], TARGETS["open_s"]),
            ("GUI: open over it, longest stall", "gui", g["open_over"]["stall_s"],
             TARGETS["open_stall_s"]),
        ]
    return rows


def report(args, runs: dict, before: dict | None) -> str:
    sizes = sorted(runs, key=int)
    lines = [MARK_START, "## bench_campaign: a campaign of many photos as a workspace", ""]
    first = runs[sizes[0]]["cli"]["fill"]
    lines.append(
        f"The small sample outcrop (127 k triangles) with N photos: the {args.source} photos of "
        "`bench_batch`'s generated campaign copied under new names, each with its own sensor "
        f"record. One photo in {REGISTERED_EVERY} has a registration (one real registration "
        "recorded with each photo's true pose; its trials and matches saved with it), one in "
        f"{REGISTERED_EVERY * DRAWN_EVERY} its drawn lines (~70 features), projected "
        f"(at N = {sizes[0]}: {first['registered']} registered, {first['drawn']} drawn, "
        f"{first['features']} features). Command-line rows are subprocesses timed end to end; "
        "GUI rows a real napari "
        f"{runs[sizes[0]].get('napari', '')} window under Xvfb (software OpenGL) with the "
        "workbench and the campaign view docked, a 10 ms QTimer heartbeat measuring the "
        "GUI thread's longest stall. Machine: "
        f"{os.cpu_count()} cores, Python {platform.python_version()}; load average (1 min) "
        f"before the run {args.load_before:.1f}"
        + (f" (before: {before['load_before']:.1f})" if before and "load_before" in before else "")
        + ": another job shared the two cores throughout, so single figures move by tens of "
        "per cent from run to run (the command-line rows but `create` are mostly Python's "
        "start and the model's read: their before → after changes are the load's); what "
        "grows with N is the code's.")
    lines.append("")
    head = "| step | " + " | ".join(f"N = {n}" for n in sizes) + " | target |"
    if before:
        lines.append(f"Seconds, before → after (before: {before.get('label', 'earlier run')}; "
                     f"after: {args.label}). ❌: over its target (the after figure).")
    else:
        lines.append(f"Seconds ({args.label}). ❌: over its target.")
    lines += ["", head, "|---|" + "---|" * len(sizes) + "---|"]
    table = {n: rows_of(runs[n]) for n in sizes}
    before_rows = {n: {row[0]: row[2] for row in rows_of(before["runs"][n])}
                   for n in sizes if before and n in before.get("runs", {})}
    for k, (what, _kind, _x, target) in enumerate(table[sizes[0]]):
        cells = []
        for n in sizes:
            value = table[n][k][2]
            mark = " ❌" if target is not None and value > target else ""
            old = before_rows.get(n, {}).get(what)
            cells.append((f"{_s(old)} → " if old is not None else "") + _s(value) + mark)
        lines.append(f"| {what} | " + " | ".join(cells) + f" | {_s(target) if target else ''} |")
    lines += ["", "| on disk | " + " | ".join(
        f"{runs[n]['cli']['size_bytes'] / 1e6:.1f} MB" for n in sizes) + " |",
        "|---|" + "---|" * len(sizes)]
    lines += ["", "Reproduce (the before figures: the same with `PYTHONPATH` at the older "
              "code's `src` and `--json before.json`): `xvfb-run -a -s \"-screen 0 "
              "1600x1000x24\" python benchmarks/bench_campaign.py --json after.json --before "
              "before.json --report docs/benchmarks.md`", MARK_END]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--photos", type=int, nargs="+", default=[20, 100, 300],
                        help="campaign sizes")
    parser.add_argument("--source", type=int, default=20,
                        help="photos generated (the others are copies of them)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-gui", action="store_true", help="skip the workbench steps")
    parser.add_argument("--work", type=Path, default=CACHE / "bench_campaign_runs")
    parser.add_argument("--label", default=f"napari_imgreg from {SRC}",
                        help="what code this run measures (said in the report)")
    parser.add_argument("--json", type=Path, help="write the figures here")
    parser.add_argument("--before", type=Path, help="figures of an earlier run (its --json)")
    parser.add_argument("--report", type=Path, help="markdown file to update")
    parser.add_argument("--report-only", action="store_true",
                        help="measure nothing: write the report of the figures in --json")
    args = parser.parse_args(argv)
    args.command = "python benchmarks/bench_campaign.py " + " ".join(
        argv if argv is not None else sys.argv[1:])
    before = json.loads(args.before.read_text()) if args.before else None
    if args.report_only:
        saved = json.loads(args.json.read_text())
        args.label, args.load_before, args.command = (saved["label"], saved["load_before"],
                                                      saved["command"])
        section = report(args, saved["runs"], before)
        print(section)
        if args.report:
            write_section(args.report, section, MARK_START, MARK_END)
        return 0
    args.load_before = os.getloadavg()[0]
    source = campaign(args.source, args.seed)
    args.work.mkdir(parents=True, exist_ok=True)
    startup_s, _ = cli("--version")
    runs: dict = {}
    for n in args.photos:
        print(f"campaign of {n} photos ...", flush=True)
        scene = scene_of(source, n, CACHE / f"campaign_scene_{n}_s{args.seed}")
        c = measure_cli(n, scene, args.work, source)
        print(f"  CLI: create {c['create_s']:.1f} s, info {c['info_s']:.1f} s", flush=True)
        a = measure_api(Path(c["folder"]), args.work)
        print(f"  API: open {a['open_s']:.2f} s, save as {a['save_as_s']:.2f} s", flush=True)
        runs[str(n)] = {"cli": c, "api": a, "startup_s": startup_s}
    if not args.no_gui:
        import napari

        gui = measure_gui({int(n): Path(r["cli"]["folder"]) for n, r in runs.items()},
                          args.work)
        for n, g in gui.items():
            runs[str(n)]["gui"] = g
            runs[str(n)]["napari"] = napari.__version__
    if args.json:
        args.json.write_text(json.dumps({"label": args.label, "load_before": args.load_before,
                                         "command": args.command, "runs": runs}, indent=1))
    section = report(args, runs, before)
    print(section)
    if args.report:
        write_section(args.report, section, MARK_START, MARK_END)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Interaction speed of the registration workbench, measured in a real napari window.

Two targets on the sample outcrop with a 1632 × 1224 photo (the paper's
camera; the sample photo upsampled, its sensor record scaled):

* a pose nudge shows the new reduced-resolution render within 0.3 s;
* a filter slider move shows the filtered photo within 0.1 s.

Each latency runs from the button click / slider move (the Qt signal, as a
user's click makes it) to the layer holding the new image, and to the next
paint of the napari canvas after it. The report section of
``docs/benchmarks.md`` between the ``bench_interaction`` markers is rewritten
(atomically, other sections kept). Needs a display::

    xvfb-run -a -s "-screen 0 1600x1000x24" .venv/bin/python \\
        benchmarks/bench_interaction.py --report docs/benchmarks.md
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

MARK_START, MARK_END = "<!-- bench_interaction:start -->", "<!-- bench_interaction:end -->"
TARGETS = {"nudge": 0.3, "filter": 0.1}
WIDTH, HEIGHT = 1632, 1224


def _photo_1632(folder: Path, out: Path) -> Path:
    """The sample's first photo at 1632 × 1224 with its sensor record beside it."""
    import cv2

    src = folder / "IMG_0001.jpg"
    img = cv2.imread(str(src))
    big = cv2.resize(img, (WIDTH, HEIGHT), interpolation=cv2.INTER_CUBIC)
    dst = out / "IMG_1632.jpg"
    cv2.imwrite(str(dst), big, [cv2.IMWRITE_JPEG_QUALITY, 92])
    shutil.copy(folder / "IMG_0001.json", out / "IMG_1632.json")  # 1024×768 camera: scaled on load
    return dst


def _stats(values: list[float]) -> dict:
    v = sorted(values)
    p90 = v[min(len(v) - 1, int(round(0.9 * (len(v) - 1))))]
    return {"median": statistics.median(v), "p90": p90, "max": v[-1], "n": len(v), "all": values}


def measure(n_nudges: int = 20, n_slider: int = 20) -> dict:
    import napari
    from qtpy.QtWidgets import QApplication

    from napari_imgreg.sample import sample_scene
    from napari_imgreg.widgets.workbench import Workbench

    app = QApplication.instance() or QApplication([])

    def pump(seconds: float) -> None:
        end = time.perf_counter() + seconds
        while time.perf_counter() < end:
            app.processEvents()
            time.sleep(0.002)

    def wait(cond, timeout: float = 120.0) -> float:
        end = time.perf_counter() + timeout
        while not cond():
            app.processEvents()
            time.sleep(0.0005)
            if time.perf_counter() > end:
                raise TimeoutError
        return time.perf_counter()

    folder = sample_scene("small")
    tmp = Path(tempfile.mkdtemp(prefix="bench-interaction-"))
    photo = _photo_1632(folder, tmp)
    viewer = napari.Viewer(title="bench_interaction", show=True)
    viewer.window._qt_window.resize(1600, 1000)
    wb = Workbench.add_to_viewer(viewer)
    ctrl = wb.controller
    ctrl.open_scene(folder / "outcrop.obj", dem=folder / "dem.tif", photos=[photo])
    wait(lambda: ctrl.current is not None and not ctrl.busy)
    pump(1.0)
    assert ctrl.current.size == (WIDTH, HEIGHT)

    painted: list[float] = []
    try:
        canvas = viewer.window._qt_viewer.canvas._scene_canvas  # private: benchmark only
        canvas.events.draw.connect(lambda event: painted.append(time.perf_counter()))
    except AttributeError:  # pragma: no cover - another napari
        canvas = None

    shown: list[tuple[str, float]] = []
    ctrl.render_shown.connect(lambda kind: shown.append((kind, time.perf_counter())))
    ctrl.filters_shown.connect(lambda which: shown.append((which, time.perf_counter())))

    def paint_after(t: float, timeout: float = 2.0) -> float | None:
        if canvas is None:
            return None
        try:
            return wait(lambda: any(p >= t for p in painted), timeout)
        except TimeoutError:
            return None

    # -- pose nudges, one at a time (the full render of the last one done)
    wb.show_tab("Pose")
    pump(0.5)
    buttons = [wb.pose_panel.nudge_buttons[k] for k in ("turn right", "turn left")]
    nudge_shown, nudge_painted, full_shown = [], [], []
    for k in range(n_nudges + 1):
        ctrl.latency.clear()
        shown.clear()
        painted.clear()
        pose_before = ctrl.current.pose
        t0 = time.perf_counter()
        buttons[k % 2].click()
        assert ctrl.current.pose is not pose_before
        t1 = wait(lambda: any(kind == "preview" for kind, _ in shown), 10)
        t1 = next(t for kind, t in shown if kind == "preview")
        t2 = paint_after(t1)
        t3 = wait(lambda: any(kind == "full" for kind, _ in shown), 10)
        wait(lambda: not ctrl.busy)
        if k == 0:
            continue  # the first edit warms caches
        nudge_shown.append(t1 - t0)
        if t2 is not None:
            nudge_painted.append(t2 - t0)
        full_shown.append(t3 - t0)
        pump(0.05)

    # -- rapid nudges: a click every 80 ms (a held arrow key)
    rapid = []
    for k in range(12):
        shown.clear()
        t0 = time.perf_counter()
        buttons[0].click()
        try:
            t1 = wait(lambda: any(kind == "preview" for kind, _ in shown), 5)
            rapid.append(t1 - t0)
        except TimeoutError:
            pass
        pump(max(0.0, 0.08 - (time.perf_counter() - t0)))
    wait(lambda: not ctrl.busy)

    # -- filter sliders with the preview on, 1632 × 1224
    wb.show_tab("Filters")
    fp = wb.filters_panel
    fp.preview_check.setChecked(True)
    wait(lambda: not ctrl.busy)
    pump(0.5)

    def slide(widget, values) -> tuple[list[float], list[float]]:
        out_shown, out_painted = [], []
        for k, value in enumerate(values):
            shown.clear()
            painted.clear()
            t0 = time.perf_counter()
            widget.setValue(value)  # what a slider drag emits
            t1 = wait(lambda: any(w == "photo" for w, _ in shown), 10)
            t1 = next(t for w, t in shown if w == "photo")
            t2 = paint_after(t1)
            wait(lambda: not ctrl.busy)
            if k == 0:
                continue
            out_shown.append(t1 - t0)
            if t2 is not None:
                out_painted.append(t2 - t0)
            pump(0.05)
        return out_shown, out_painted

    gammas = list(np.linspace(0.8, 2.0, n_slider + 1))
    gamma_shown, gamma_painted = slide(fp.photo_editor.widgets["gamma"], gammas)
    fp.photo_editor.wallis_check.setChecked(True)
    wait(lambda: not ctrl.busy)
    wallis_shown, wallis_painted = slide(fp.photo_editor.widgets["wallis_target_std"],
                                         list(np.linspace(30.0, 80.0, n_slider + 1)))
    assert ctrl.layers.get("photo_filtered").data.shape == (768, 1024)  # at the match width

    viewer.close()
    shutil.rmtree(tmp, ignore_errors=True)
    out = {
        "nudge_shown": _stats(nudge_shown),
        "nudge_painted": _stats(nudge_painted) if nudge_painted else None,
        "full_shown": _stats(full_shown),
        "rapid_shown": _stats(rapid) if rapid else None,
        "gamma_shown": _stats(gamma_shown),
        "gamma_painted": _stats(gamma_painted) if gamma_painted else None,
        "wallis_shown": _stats(wallis_shown),
        "wallis_painted": _stats(wallis_painted) if wallis_painted else None,
    }
    return out


def _ms(x: float) -> str:
    return f"{1000 * x:.0f} ms"


def report(m: dict) -> str:
    import cv2
    import napari
    import vispy

    def row(label, key, target=None):
        s = m.get(key)
        if s is None:
            return f"| {label} | – | – | – | |"
        ok = ""
        if target is not None:
            ok = "✅" if s["median"] <= target else "❌"
        return f"| {label} | {_ms(s['median'])} | {_ms(s['p90'])} | {_ms(s['max'])} | {ok} |"

    gl = os.environ.get("DISPLAY", "")
    lines = [
        MARK_START,
        "## Interaction speed of the workbench (issue 4)",
        "",
        f"Sample outcrop (126,990 triangles), photo {WIDTH}×{HEIGHT} (the paper's camera), "
        f"real napari {napari.__version__} window under Xvfb with Mesa's software OpenGL "
        f"(DISPLAY {gl or 'none'}), {os.cpu_count()} cores, Python {platform.python_version()}, "
        f"OpenCV {cv2.__version__}, vispy {vispy.__version__}. Latency from the click (or slider "
        "move) to the layer holding the new image (*shown*) and to the next paint of the canvas "
        f"(*painted*); {m['nudge_shown']['n']} nudges and {m['gamma_shown']['n']} slider moves "
        "per row after one warm-up, each after the previous one had settled.",
        "",
        "| interaction | median | 90th pct. | max | target |",
        "|---|---|---|---|---|",
        row("pose nudge → reduced render (400 px wide) shown", "nudge_shown", TARGETS["nudge"]),
        row("pose nudge → reduced render painted", "nudge_painted", TARGETS["nudge"]),
        row("pose nudge → full-resolution render shown (after the 350 ms pause)", "full_shown"),
        row("held nudges, a click every 80 ms → reduced render shown", "rapid_shown"),
        row("gamma slider → filtered photo shown", "gamma_shown", TARGETS["filter"]),
        row("gamma slider → filtered photo painted", "gamma_painted", TARGETS["filter"]),
        row("Wallis slider (window 41) → filtered photo shown", "wallis_shown",
            TARGETS["filter"]),
        row("Wallis slider → filtered photo painted", "wallis_painted", TARGETS["filter"]),
        "",
        "Targets: ≤ 0.3 s for a nudge's reduced render, ≤ 0.1 s for a filter preview on "
        f"{WIDTH}×{HEIGHT}. The preview shows what the detector reads: the photo reduced to the "
        "match width (1024 px, as the registration does), filtered, laid over the photo at its "
        "size. Renders, filters and registrations run in napari thread workers; the "
        "full-resolution render follows 350 ms after the last edit. Software OpenGL under Xvfb "
        "competes with the workers for the cores, so a desktop with a GPU paints faster; on this "
        "shared two-core machine the medians move by about ±20 % from run to run.",
        "",
        "Reproduce: `xvfb-run -a -s \"-screen 0 1600x1000x24\" .venv/bin/python "
        "benchmarks/bench_interaction.py --report docs/benchmarks.md`.",
        "",
        "All runs (ms): " + "; ".join(
            f"{k}: " + ", ".join(f"{1000 * v:.0f}" for v in s["all"])
            for k, s in m.items() if s is not None),
        MARK_END,
    ]
    return "\n".join(lines)


def write_report(path: Path, section: str) -> None:
    """Replace (or append) this benchmark's section, keeping the others; atomic."""
    from napari_imgreg._atomic import atomic_write

    text = path.read_text(encoding="utf-8") if path.exists() else "# Benchmarks\n"
    if MARK_START in text and MARK_END in text:
        before, rest = text.split(MARK_START, 1)
        after = rest.split(MARK_END, 1)[1]
        text = before + section + after
    else:
        text = text.rstrip("\n") + "\n\n" + section + "\n"
    with atomic_write(path, encoding="utf-8") as fh:
        fh.write(text)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--report", type=Path, help="markdown file to update")
    parser.add_argument("--nudges", type=int, default=20)
    parser.add_argument("--slides", type=int, default=20)
    args = parser.parse_args(argv)
    m = measure(args.nudges, args.slides)
    section = report(m)
    print(section)
    if args.report:
        write_report(args.report, section)
        print(f"updated {args.report}")
    ok = (m["nudge_shown"]["median"] <= TARGETS["nudge"]
          and m["gamma_shown"]["median"] <= TARGETS["filter"])
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

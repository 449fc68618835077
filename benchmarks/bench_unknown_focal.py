"""Unknown focal length benchmark (issue 16, item 4): the registration
benchmark's photos registered with and without their focal length.

The scenes and photos are those of ``bench_register.py`` (its generator and
cache, reused by import). Each photo is registered by the full automatic
pipeline (``RegistrationParams()``) twice in the same process:

* ``known``: as the benchmark does, the sensor record's camera (focal length
  in millimetres and the sensor size) and the photo's EXIF as written;
* ``unknown``: the same photo with the record's camera cut down to
  ``{"width", "height"}`` and the EXIF's focal-length tags removed
  (``FocalLength``, ``FocalLengthIn35mmFilm``, ``FocalPlane*``), so the
  prior assumes a 65° view and the registration estimates the focal length
  (``PoseParams.solver`` "auto": P4Pf and the joint refinement);
* ``unknown_dlt`` (asked for by name): as ``unknown`` with the pose solver
  set to seed 003's six-point DLT (``"solver": "dlt"``), which also
  estimates the principal point.

Success and false verdicts are ``bench_register.py``'s (status
``registered`` and median check-point error below 4 px at 1632 px width),
except that the check points are projected with the camera the result
reports: an estimated focal length is part of the answer. The focal error is
``fx / fx_true − 1`` of the registered results.

``rough_changed_light`` (asked for by name): the rough tier of issue 13 (a
low sun on relief the model does not resolve), registered to the rough
scene's own model.

Targets (issue 16): with width/height-only records, success ≥ 90 % of the
known-intrinsics rate and median focal error ≤ 1 %.

    .venv/bin/python benchmarks/bench_unknown_focal.py --scenes 2 --photos 4 \\
        --tiers same_light,changed_light --report docs/benchmarks.md
    .venv/bin/python benchmarks/bench_unknown_focal.py --quick      # smoke run
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import bench_register as br  # noqa: E402  (the benchmark's scenes, generator and cache)
from _report import markers, write_section  # noqa: E402

from napari_imgreg import Scene  # noqa: E402
from napari_imgreg.camera import Intrinsics  # noqa: E402
from napari_imgreg.io.photos import load_photo  # noqa: E402
from napari_imgreg.prior import prior_for_photo  # noqa: E402
from napari_imgreg.registration.params import RegistrationParams  # noqa: E402
from napari_imgreg.registration.pipeline import register  # noqa: E402
from napari_imgreg.sample import load_truth  # noqa: E402

NAME = "bench_unknown_focal"
MODES = ("known", "unknown", "unknown_dlt", "exif", "exif_fixed")
DEFAULT_MODES = ("known", "unknown")
TIERS = ("same_light", "changed_light", "rough_changed_light")
#: Photos of the rough true surface (issue 13), registered to the rough scene's
#: smoothed, survey-lit model (``bench_register.rough_folder``); asked for by name.
ROUGH_TIERS = ("rough_changed_light",)
#: EXIF tags from which a focal length in pixels can be had.
FOCAL_TAGS = ("FocalLength", "FocalLengthIn35mmFilm", "FocalPlaneXResolution",
              "FocalPlaneYResolution", "FocalPlaneResolutionUnit")
TARGETS = {"success_ratio": 0.9, "median_focal_error": 0.01}
#: ``--start-hfov``: the start's field of view instead of the package's
#: assumption (65°), to see how far a start the estimation recovers from
#: (the generator's cameras all have a 66.8° view, 3.4 % from 65°).
START_HFOV_DEG: float | None = None


def prior_of(photo, scene, mode: str, tmp: Path):
    """The photo's prior: as recorded (``known``), without any focal length
    (``unknown``, ``unknown_dlt``), or with the EXIF's nominal one only (a
    record of width and height; the generator writes ``FocalLengthIn35mmFilm``
    26 mm, 1.0 % short of its lens): ``exif`` as the package reads it (the
    start of an estimated focal length), ``exif_fixed`` taken as known (the
    package before it refined EXIF focal lengths)."""
    if mode == "known":
        return prior_for_photo(photo, scene)
    if mode in ("exif", "exif_fixed"):
        record = json.loads(photo.sidecar.read_text())
        cam = record["camera"]
        record["camera"] = {"width": cam["width"], "height": cam["height"]}
        path = tmp / photo.sidecar.name
        path.write_text(json.dumps(record))
        prior = prior_for_photo(photo, scene, record_path=path)
        assert "focal length from EXIF" in prior.assumptions, prior.assumptions
        if mode == "exif_fixed":
            prior.intrinsics = replace(prior.intrinsics, estimated=())
        return prior
    record = json.loads(photo.sidecar.read_text())
    cam = record.get("camera") or {}
    record["camera"] = {"width": cam["width"], "height": cam["height"]} if "width" in cam else None
    if record["camera"] is None:
        del record["camera"]
    path = tmp / photo.sidecar.name
    path.write_text(json.dumps(record))
    bare = copy.copy(photo)  # the same pixels, without the focal length's EXIF tags
    bare.exif = {k: v for k, v in (photo.exif or {}).items() if k not in FOCAL_TAGS}
    prior = prior_for_photo(bare, scene, record_path=path)
    assert not prior.intrinsics.focal_known, prior.assumptions
    if START_HFOV_DEG is not None:
        start = Intrinsics.from_fov(prior.intrinsics.width, prior.intrinsics.height,
                                    START_HFOV_DEG)
        prior.intrinsics = replace(start, estimated=("fx", "fy"))
    return prior


def _run_tiers(scene: Scene, tiers: list[str], folders: dict, seed: int, modes, tmp: Path,
               rows: list[dict], rows_path: Path) -> None:
    """Register every photo of ``tiers`` to ``scene`` in every mode, appending to
    ``rows`` and writing them after each (a stopped run keeps its rows)."""
    for tier in tiers:
        for photo_path in sorted(folders[tier].glob("IMG_*.jpg")):
            for mode in modes:
                row = {"tier": tier, "scene_seed": seed, "photo": photo_path.name,
                       **evaluate(scene, photo_path, mode, tmp)}
                rows.append(row)
                rows_path.write_text(json.dumps(rows, indent=1))
                print(f"{tier:13s} seed {seed} {photo_path.name} {mode:11s} "
                      f"{row['status']:10s} {row['grade']:9s} cp {row['cp_median_px']:8.2f} px "
                      f"focal {100 * row['focal_error']:+6.2f} % (start "
                      f"{100 * row['start_focal_error']:+5.1f} %) {row['seconds']:5.1f} s"
                      + (" SUCCESS" if row["success"] else "")
                      + (" FALSE-VERDICT" if row["false_verdict"] else ""), flush=True)


def params_of(mode: str) -> RegistrationParams:
    params = RegistrationParams()
    if mode == "unknown_dlt":
        params.pose = replace(params.pose, solver="dlt")
    return params


def evaluate(scene: Scene, photo_path: Path, mode: str, tmp: Path) -> dict:
    truth = load_truth(photo_path)
    photo = load_photo(photo_path)
    prior = prior_of(photo, scene, mode, tmp)
    t0 = time.perf_counter()
    reg = register(scene, photo.image, prior, params_of(mode), photo_path.name)
    seconds = time.perf_counter() - t0
    cam = reg.intrinsics
    # The check points through the camera the result reports (its focal
    # length included), at 1632 px width.
    proj = reg.pose.project(cam, truth.check_xyz)
    cp = np.linalg.norm(proj - truth.check_pixels, axis=1) * br.REFERENCE_WIDTH / cam.width
    cp_med = float(np.median(np.where(np.isfinite(cp), cp, 1e6)))
    registered = reg.status == "registered"
    claims = registered or reg.grade in ("good", "excellent")
    true_fx = truth.intrinsics.fx
    return {
        "mode": mode,
        "status": reg.status,
        "grade": reg.grade,
        "success": bool(registered and cp_med < br.SUCCESS_PX),
        "false_verdict": bool(claims and cp_med >= br.SUCCESS_PX),
        "cp_median_px": round(cp_med, 3),
        "rotation_error_deg": round(reg.pose.rotation_error_deg(truth.pose), 4),
        "position_error_m": round(float(np.linalg.norm(reg.pose.center - truth.pose.center)), 4),
        "fx": round(cam.fx, 3),
        "fx_true": round(true_fx, 3),
        "focal_error": round(cam.fx / true_fx - 1.0, 6),
        "start_focal_error": round(prior.intrinsics.fx / true_fx - 1.0, 6),
        "estimated": list(cam.estimated),
        "cx_error_px": round(cam.cx - truth.intrinsics.cx, 3),
        "cy_error_px": round(cam.cy - truth.intrinsics.cy, 3),
        "uncertainty_px": (None if reg.uncertainty is None
                           else reg.uncertainty.to_dict()["reprojection_px"]),
        "n_trials": len(reg.trials),
        "seconds": round(seconds, 3),
        "hints": reg.hints,
    }


def _median(values) -> float | None:
    v = [x for x in values if x is not None and np.isfinite(x)]
    return float(statistics.median(v)) if v else None


def _pct(values, q) -> float | None:
    v = [x for x in values if x is not None and np.isfinite(x)]
    return float(np.percentile(v, q)) if v else None


def _f(v, fmt="{:.2f}") -> str:
    return "–" if v is None else fmt.format(v)


def summarize(rows: list[dict], tiers, modes) -> dict:
    out = {}
    for tier in list(tiers) + ["all"]:
        for mode in modes:
            sel = [r for r in rows if r["mode"] == mode and (tier == "all" or r["tier"] == tier)]
            if not sel:
                continue
            reg = [r for r in sel if r["status"] == "registered"]
            out[(tier, mode)] = {
                "n": len(sel),
                "success": sum(r["success"] for r in sel),
                "false_verdicts": sum(r["false_verdict"] for r in sel),
                "cp_median": _median([r["cp_median_px"] for r in reg]),
                "rot_median": _median([r["rotation_error_deg"] for r in reg]),
                "pos_median": _median([r["position_error_m"] for r in reg]),
                "focal_median": _median([abs(r["focal_error"]) for r in reg]),
                "focal_p90": _pct([abs(r["focal_error"]) for r in reg], 90),
                "start_focal_median": _median([abs(r["start_focal_error"]) for r in sel]),
                "seconds": _median([r["seconds"] for r in sel]),
            }
    return out


def report(summary: dict, tiers, modes, meta: dict) -> str:
    start, end = markers(NAME)
    lines = [start, "## Unknown focal length (issue 16, item 4)", "",
             f"The registration benchmark's photos ({meta['scenes']}), each registered by the "
             "full automatic pipeline with its recorded camera (`known`) and with a record "
             "giving the camera's `width` and `height` only and no focal length in the EXIF "
             "(`unknown`: a 65° view assumed as the start, the focal length estimated by "
             "P4Pf and the joint refinement of pose and focal length; `unknown_dlt`: the "
             "six-point DLT instead, principal point estimated too). Success: `registered` "
             "and median check-point error < 4 px at 1632 px width, the check points "
             "projected with the camera the result reports; focal error |fx / fx_true − 1| "
             "over the registered photos. The generator's cameras all have the same lens "
             "(a 66.8° view), 3.4 % from the 65° start; `--start-hfov` starts from another "
             "view.", "",
             "| tier | mode | success | false verdicts | check-point error, median (px) | "
             "rotation error (°) | position error (m) | focal error, median / 90th | "
             "start's focal error | time, median (s) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for (tier, mode), s in summary.items():
        label = "both tiers" if tier == "all" else tier
        focal = ("(read)" if mode == "known" else
                 f"{_f(s['focal_median'] and 100 * s['focal_median'], '{:.2f}')} % / "
                 f"{_f(s['focal_p90'] and 100 * s['focal_p90'], '{:.2f}')} %")
        start_err = ("–" if mode == "known" else
                     f"{_f(s['start_focal_median'] and 100 * s['start_focal_median'], '{:.1f}')} %")
        lines.append(
            f"| {label} | {mode} | {s['success']}/{s['n']} ({s['success'] / s['n']:.0%}) | "
            f"{s['false_verdicts']}/{s['n']} | {_f(s['cp_median'])} | "
            f"{_f(s['rot_median'], '{:.3f}')} | {_f(s['pos_median'], '{:.3f}')} | {focal} | "
            f"{start_err} | {_f(s['seconds'], '{:.1f}')} |")
    lines += ["", "Targets (issue 16):", ""]
    known = summary.get(("all", "known"))
    for mode in modes:
        if mode == "known" or ("all", mode) not in summary:
            continue
        s = summary[("all", mode)]
        if known and known["success"]:
            ratio = (s["success"] / s["n"]) / (known["success"] / known["n"])
            ok = ratio >= TARGETS["success_ratio"]
            lines.append(f"- {'✅' if ok else '❌'} `{mode}`: success ≥ 90 % of the known-"
                         f"intrinsics rate: {s['success']}/{s['n']} against {known['success']}/"
                         f"{known['n']} ({ratio:.0%}).")
        fm = s["focal_median"]
        ok = fm is not None and fm <= TARGETS["median_focal_error"]
        lines.append(f"- {'✅' if ok else '❌'} `{mode}`: median focal error ≤ 1 %: "
                     f"{_f(fm and 100 * fm, '{:.2f}')} % (90th percentile "
                     f"{_f(s['focal_p90'] and 100 * s['focal_p90'], '{:.2f}')} %); false verdicts "
                     f"{s['false_verdicts']}/{s['n']}.")
    lines += ["", f"Reproduce: `{meta['command']}` ({meta['cpus']} cores, Python "
                  f"{meta['python']}; load average {meta['load']} at the end; "
                  f"{meta['wall_min']:.0f} min). Per-photo rows: `{meta['rows']}`.", end]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true",
                        help="smoke run: 1 small scene, 3 photos, same light")
    parser.add_argument("--size", choices=("small", "large"), default=None)
    parser.add_argument("--scenes", type=int, default=None, help="scene seeds (default 2)")
    parser.add_argument("--first-seed", type=int, default=1)
    parser.add_argument("--photos", type=int, default=None, help="cameras per scene (default 4)")
    parser.add_argument("--tiers", default=",".join(TIERS))
    parser.add_argument("--modes", default=",".join(DEFAULT_MODES),
                        help=f"comma-separated, of {', '.join(MODES)}")
    parser.add_argument("--cache", type=Path, default=br.DEFAULT_CACHE)
    parser.add_argument("--report", type=Path, help="markdown file whose section to rewrite")
    parser.add_argument("--start-hfov", type=float, default=None,
                        help="start unknown cameras from this horizontal view (°) instead of 65°")
    parser.add_argument("--rows", type=Path, default=None,
                        help="per-photo rows (JSON); default in the cache folder")
    args = parser.parse_args(argv)
    global START_HFOV_DEG
    START_HFOV_DEG = args.start_hfov
    size = args.size or ("small" if args.quick else "large")
    n_scenes = args.scenes or (1 if args.quick else 2)
    n_photos = args.photos or (3 if args.quick else 4)
    tiers = [t for t in args.tiers.split(",") if t] if not args.quick else ["same_light"]
    modes = [m for m in args.modes.split(",") if m]
    for t in tiers:
        if t not in TIERS:
            parser.error(f"unknown tier {t!r} (of {', '.join(TIERS)})")
    for m in modes:
        if m not in MODES:
            parser.error(f"unknown mode {m!r} (of {', '.join(MODES)})")
    seeds = list(range(args.first_seed, args.first_seed + n_scenes))
    rows_path = args.rows or args.cache / f"{NAME}_rows{'_quick' if args.quick else ''}.json"
    rows_path = rows_path.resolve()
    t_start = time.perf_counter()
    rows: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="bench_focal_") as tmpdir:
        tmp = Path(tmpdir)
        for seed in seeds:
            d = br.scene_folder(args.cache, size, seed, n_photos)
            folders = {"same_light": d / "same_light"}
            if "changed_light" in tiers:
                folders["changed_light"] = br.changed_folder(d, br.CHANGED_STRENGTH)
            groups = []  # (model file, its tiers): the rough tiers have their own model
            plain = [t for t in tiers if t not in ROUGH_TIERS]
            if plain:
                manifest = json.loads((d / "scene.json").read_text())
                groups.append((d / manifest["files"]["mesh"], plain))
            rough = [t for t in tiers if t in ROUGH_TIERS]
            if rough:
                r = br.rough_folder(d)
                folders.update({t: r / t for t in rough})
                groups.append((r / "model" / "outcrop.obj", rough))
            for mesh, group in groups:
                scene = Scene.load(mesh)
                br._warm_up(scene, sorted(folders[group[0]].glob("IMG_*.jpg"))[0])
                _run_tiers(scene, group, folders, seed, modes, tmp, rows, rows_path)
                del scene
    summary = summarize(rows, tiers, modes)
    cmd = "python benchmarks/bench_unknown_focal.py" + (" --quick" if args.quick else "")
    if args.size:
        cmd += f" --size {args.size}"
    if args.scenes:
        cmd += f" --scenes {args.scenes}"
    if args.first_seed != 1:
        cmd += f" --first-seed {args.first_seed}"
    if args.photos:
        cmd += f" --photos {args.photos}"
    if not args.quick:
        cmd += " --tiers " + ",".join(tiers)
    if modes != list(DEFAULT_MODES):
        cmd += " --modes " + ",".join(modes)
    if args.start_hfov is not None:
        cmd += f" --start-hfov {args.start_hfov:g}"
    if args.rows:
        cmd += f" --rows {args.rows}"
    if args.report:
        cmd += f" --report {args.report}"
    meta = {
        "scenes": f"{size}, scene seeds {seeds[0]}–{seeds[-1]}, {n_photos} cameras each, "
                  f"tiers {', '.join(tiers)}",
        "command": ".venv/bin/" + cmd,
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
        "load": ", ".join(f"{x:.1f}" for x in os.getloadavg()),
        "wall_min": (time.perf_counter() - t_start) / 60,
        "rows": str(rows_path.relative_to(HERE.parent)) if HERE.parent in rows_path.parents
        else str(rows_path),
    }
    section = report(summary, tiers, modes, meta)
    print(section)
    if args.report:
        write_section(args.report, section, *markers(NAME))
    return 0


if __name__ == "__main__":
    sys.exit(main())

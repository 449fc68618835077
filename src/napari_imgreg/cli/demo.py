"""``napari-imgreg demo``: the main job on the bundled sample scene (contract §8).

Generates the sample outcrop once (cached), registers each sample photo from
its sensor prior and compares the registered pose with the sample's ground
truth; writes RESULT.json per photo, renders and side-by-side views into
``--out``. ``--gui`` instead opens napari with the sample in the workbench:
the one path of the command line that needs Qt, imported only then.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from ._common import EXIT_FAILED, EXIT_OK, load_scene, write_json
from ..io.photos import load_photo, save_image
from ..prior import prior_for_photo
from ..render import render
from ..registration.quality import outcome_words
from ..validate import check_writable

__all__ = ["add_parser", "run", "open_gui"]


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register the ``demo`` sub-command; its handler is :func:`run`."""
    p = subparsers.add_parser(
        "demo",
        help="run the main job on the bundled sample scene",
        description="Generate (once, cached) the sample outcrop, register each sample photo "
        "from its sensor prior and compare the pose with the sample's ground truth. Writes "
        "RESULT.json per photo and side-by-side views photo | render from the prior and "
        "photo | render from the registered pose. Exit 0 when every photo registered.",
    )
    p.add_argument("--out", default="demo_output", help="output folder (default demo_output)")
    p.add_argument("--gui", action="store_true", help="open napari with the sample loaded")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    """Run ``demo``: register the sample photos (or open the GUI with ``--gui``)."""
    from ..sample import load_truth, sample_scene
    from ..registration import pipeline

    if not args.gui:
        check_writable(args.out, folder=True)  # before the minutes of work
    t0 = time.perf_counter()
    folder = sample_scene("small")
    print(f"sample outcrop scene: {folder} ({time.perf_counter() - t0:.1f} s)")
    scene = load_scene(folder / "outcrop.obj", dem=folder / "dem.tif")
    t1 = time.perf_counter()
    scene.build_engine()
    print(
        f"loaded {scene.n_faces:,} triangles, texture "
        f"{scene.texture.shape[1]}×{scene.texture.shape[0]} in {t1 - t0:.1f} s; "
        f"ray engine built in {scene.timings_s['build']:.2f} s"
    )
    if args.gui:
        return open_gui(folder)
    out = Path(args.out)
    summary = []
    for photo_path in sorted(folder.glob("IMG_*.jpg")):
        photo = load_photo(photo_path)
        prior = prior_for_photo(photo, scene)
        stem = photo_path.stem
        # What the phone's sensors give: the model rendered from the prior.
        t = time.perf_counter()
        prior_view = render(scene, prior.intrinsics, prior.pose)
        render_s = time.perf_counter() - t
        save_image(out / f"{stem}_prior_render.png", prior_view.rgb)
        save_image(out / f"{stem}_photo_vs_prior.jpg",
                   np.concatenate([photo.image, prior_view.rgb], axis=1))
        # The main job: register the photo, then render from the registered pose.
        reg = pipeline.register(scene, photo.image, prior, photo_name=photo_path.name)
        result_path = out / f"{stem}.result.json"
        write_json(result_path, reg.to_dict())
        reg_view = render(scene, reg.intrinsics, reg.pose)
        save_image(out / f"{stem}_registered_render.png", reg_view.rgb)
        side_by_side = out / f"{stem}_photo_vs_registered.jpg"
        save_image(side_by_side, np.concatenate([photo.image, reg_view.rgb], axis=1))
        # How close it came: the sample's ground truth.
        truth = load_truth(photo_path).pose
        rot_err = reg.pose.rotation_error_deg(truth)
        pos_err = float(np.linalg.norm(reg.pose.center - truth.center))
        prior_rot_err = prior.pose.rotation_error_deg(truth)
        prior_pos_err = float(np.linalg.norm(prior.pose.center - truth.center))
        seconds = reg.timings_s["total"]
        print(
            f"  {photo_path.name}: {reg.status.upper()} — "
            f"{outcome_words(reg.status, reg.grade)} (Q = {reg.q:+.2f}) "
            f"in {seconds:.1f} s; off the true pose by {rot_err:.3f}° and {pos_err:.2f} m "
            f"(the prior: {prior_rot_err:.1f}° and {prior_pos_err:.1f} m)"
        )
        print(f"      -> {result_path}, {side_by_side}")
        summary.append(
            {"photo": photo_path.name, "render": f"{stem}_prior_render.png",
             "render_s": round(render_s, 3), "pose": prior.pose.to_dict(),
             "assumptions": prior.assumptions,
             "registration": {
                 "status": reg.status, "grade": reg.grade, "Q": reg.q,
                 "seconds": round(seconds, 3), "result": result_path.name,
                 "render": f"{stem}_registered_render.png", "pose": reg.pose.to_dict(),
                 "rotation_error_deg": rot_err, "position_error_m": pos_err,
                 "prior_rotation_error_deg": prior_rot_err,
                 "prior_position_error_m": prior_pos_err,
             }}
        )
    write_json(out / "demo.json", {"scene": str(folder), "photos": summary})
    regs = [s["registration"] for s in summary]
    n_ok = sum(r["status"] == "registered" for r in regs)
    worst = (
        f" (largest error {max(r['rotation_error_deg'] for r in regs):.3f}°, "
        f"{max(r['position_error_m'] for r in regs):.2f} m)" if regs else ""
    )
    print(
        f"registered {n_ok} of {len(regs)} sample photos{worst} in "
        f"{time.perf_counter() - t0:.1f} s; results, renders and side-by-side views "
        f"(photo | prior, photo | registered) in {out}/"
    )
    return EXIT_OK if n_ok == len(regs) else EXIT_FAILED


def open_gui(folder: Path) -> int:  # pragma: no cover - interactive
    """Open napari with the sample scene ``folder`` in the workbench; returns 0
    when the viewer is closed."""
    # The only import of the command line that needs Qt (an allowed exception
    # to the layer rules, see pyproject.toml): imported only for ``--gui``.
    from ..widgets.demo import open_demo

    open_demo(folder)
    return EXIT_OK

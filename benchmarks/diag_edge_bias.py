"""Which way the photo's edge at a contact is off the true contact (issue 14's ceiling).

For each photo of the small sample scene, every visible contact stretch is
drawn perfectly (the true trace projected with the true pose), moved across
itself to the photo's edge at the contact (``bench_snap.edge_at_contact``,
the tracers' ceiling), and the signed offsets are averaged: in x on steep
traces (faults), in y on flat ones (bed boundaries; negative = up in the
image), the latter split by which bed lies above (``sm``: sandstone over
mudstone, ``ms``: mudstone over sandstone).

    nice .venv/bin/python benchmarks/diag_edge_bias.py            # the photos
    nice .venv/bin/python benchmarks/diag_edge_bias.py --render 1 2 3

``--render S``: on the model's own colours rendered from the true pose at S
times the photo's resolution instead (offsets in photo pixels): an offset
that shrinks as S grows comes from how the image samples and smooths the
contact's neighbourhood, not from where the contact is drawn.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

from bench_interpret import _dense, drawn_lines  # noqa: E402
from bench_snap import edge_at_contact  # noqa: E402

from napari_imgreg import Scene, render  # noqa: E402
from napari_imgreg.interpret.snap import SnapParams, _luminance_derivatives  # noqa: E402
from napari_imgreg.io.photos import load_photo  # noqa: E402
from napari_imgreg.sample import load_truth, sample_scene  # noqa: E402


def offsets(scene, truth, name: str, scale: float | None) -> dict[str, float]:
    """Mean signed offsets (photo pixels) of one photo's contacts."""
    pt = truth.photos[name]
    if scale is None:
        image, s = load_photo(pt.photo).image, 1.0
    else:
        image, s = render(scene, pt.intrinsics, pt.pose, mode="color", scale=scale).rgb, scale
    gx, gy = _luminance_derivatives(image, SnapParams().smoothing_px)
    rows: dict[str, list[float]] = {"faults dx": [], "beds dy": [], "sm dy": [], "ms dy": []}
    for item, k in drawn_lines(scene, pt.intrinsics, pt.pose, truth.lines):
        at = (item.pixels + 0.5) * s - 0.5  # pixel centres stay at integers
        dense = _dense(at, 1.0)
        d = (edge_at_contact(gx, gy, at) - dense) / s
        tangent = np.gradient(dense, axis=0)
        tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-9)
        steep, flat = np.abs(tangent[:, 1]) > 0.7, np.abs(tangent[:, 0]) > 0.7
        rows["faults dx"] += d[steep, 0].tolist()
        rows["beds dy"] += d[flat, 1].tolist()
        props = truth.lines["features"][k]["properties"]
        if props.get("label") == "bed_boundary":
            key = props["above"][0] + props["below"][0]
            rows[f"{key} dy"] += d[flat, 1].tolist()
    return {key: float(np.mean(v)) if v else float("nan") for key, v in rows.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--render", type=float, nargs="*", metavar="S",
                    help="the model's colours rendered at these scales instead of the photos")
    args = ap.parse_args()
    folder = sample_scene("small")
    truth = load_truth(folder)
    scene = Scene.load(folder / "outcrop.obj", dem=folder / "dem.tif")
    scene.build_engine()
    for scale in args.render or [None]:
        source = "photo" if scale is None else f"model's colours ×{scale:g}"
        for name in sorted(truth.photos):
            o = offsets(scene, truth, name, scale)
            print(f"{source:>20} {name}: " + ", ".join(f"{k} {v:+.3f}" for k, v in o.items()))


if __name__ == "__main__":
    main()

"""Snapping onto the model's own colour edge (issue 14): the first try, superseded.

Shipped since as ``SnapParams.model_reach_px`` (``snap._follow_model``), which
reads the render with the tracer's own last step instead of :func:`refine_on`
here (the smoothed gradient's biased peak, one polarity direction for the
whole trace, every point moved): see ``bench_snap.py`` and the notes in
``docs/benchmarks.md``. Kept as the record of that first measurement.

Does refining a snapped trace onto the contact as the model's texture shows it,
rendered from the registered pose and projected back through the same pose,
take the registration's error out of the trace? Rows, median 3D distance to
the true trace (cm) and the ratio to the perfect drawing: the perfect drawing,
the photo's edge at the contact (bench_snap's ceiling), the render's edge at
the contact, the snapped trace, and the snapped trace moved onto the render's
edge within 1 or 2 px.

    nice .venv/bin/python benchmarks/diag_snap_on_model.py small
    SS=3 ... (the render supersampled 3×)   TRUE=1 ... (the true pose instead)
"""
import sys
from pathlib import Path

import numpy as np
sys.path.insert(0, str(Path(__file__).parent))
from scipy.spatial import cKDTree
from napari_imgreg import Scene, render
from napari_imgreg.interpret.project import Interpretation
from napari_imgreg.interpret.snap import SnapParams, _luminance_derivatives, snap_trace, _subpixel
from napari_imgreg.io.photos import load_photo
from napari_imgreg.sample import load_truth, sample_scene
from bench_interpret import _dense, _register, drawn_lines
from bench_snap import _distances, edge_at_contact, POSES, CLICK_JITTER_PX

def refine_on(gx, gy, px, reach):
    """Move each vertex of px across itself to the sub-pixel peak of the edge in (gx,gy),
    polarity as along the trace."""
    from scipy import ndimage
    d = _dense(px, 1.0)
    tang = np.gradient(d, axis=0); tang /= np.maximum(np.linalg.norm(tang, axis=1, keepdims=True), 1e-9)
    normal = np.stack([-tang[:, 1], tang[:, 0]], axis=1)
    along = (ndimage.map_coordinates(gx, [d[:, 1], d[:, 0]], order=1) * normal[:, 0]
             + ndimage.map_coordinates(gy, [d[:, 1], d[:, 0]], order=1) * normal[:, 1])
    n0 = normal[len(normal) // 2]
    sign = 1.0 if np.median(along) >= 0 else -1.0
    return _subpixel(np.clip(sign * (gx * n0[0] + gy * n0[1]), 0, None), d, reach=reach)

sizes = sys.argv[1:] or ["small"]
params = SnapParams()
for size in sizes:
    folder = sample_scene(size)
    truth = load_truth(folder)
    scene = Scene.load(folder / "outcrop.obj", dem=folder / "dem.tif")
    scene.build_engine()
    trees = [cKDTree(_dense(np.asarray(f["geometry"]["coordinates"], np.float64))) for f in truth.lines["features"]]
    acc = {k: [] for k in ("perfect", "photo_edge", "render_edge", "snap", "snap_ref1", "snap_ref2")}
    for name in sorted(truth.photos):
        pt = truth.photos[name]
        drawn = drawn_lines(scene, pt.intrinsics, pt.pose, truth.lines)
        image = load_photo(pt.photo).image
        reg, _ = _register(scene, name, pt, size, POSES)
        if __import__("os").environ.get("TRUE"): reg = pt
        import cv2
        SS = int(__import__("os").environ.get("SS", "1"))
        col = render(scene, reg.intrinsics, reg.pose, scale=SS, mode="color").rgb
        if SS > 1:
            col = cv2.resize(col, (reg.intrinsics.width, reg.intrinsics.height), interpolation=cv2.INTER_AREA)
        gx, gy = _luminance_derivatives(image, params.smoothing_px)
        rgx, rgy = _luminance_derivatives(col, params.smoothing_px)
        rng = np.random.default_rng(0)
        sets = {k: [] for k in acc}
        for item, k in drawn:
            sets["perfect"].append((item, k))
            sets["photo_edge"].append((Interpretation("LineString", edge_at_contact(gx, gy, item.pixels), item.properties), k))
            sets["render_edge"].append((Interpretation("LineString", refine_on(rgx, rgy, item.pixels, 1.5), item.properties), k))
            ends = item.pixels[[0, -1]] + rng.normal(0, CLICK_JITTER_PX, (2, 2))
            ends = np.clip(ends, 0, [image.shape[1] - 1, image.shape[0] - 1])
            px = snap_trace(image, ends, params)
            sets["snap"].append((Interpretation("LineString", px, item.properties), k))
            sets["snap_ref1"].append((Interpretation("LineString", refine_on(rgx, rgy, px, 1.0), item.properties), k))
            sets["snap_ref2"].append((Interpretation("LineString", refine_on(rgx, rgy, px, 2.0), item.properties), k))
        line = [name]
        for key, items in sets.items():
            d = _distances(scene, reg.intrinsics, reg.pose, items, trees)
            acc[key].append(d)
            line.append(f"{key} {np.median(d)*100:.2f}")
        print(size, " | ".join(line), flush=True)
    p = np.median(np.concatenate(acc["perfect"]))
    for key, ds in acc.items():
        d = np.concatenate(ds)
        print(f"{size} {key:12s} median {np.median(d)*100:.2f} cm  p95 {np.percentile(d,95)*100:.1f}  ratio {np.median(d)/p:.2f}")

"""Why snapped traces miss: per-contact pixel error against the perfect drawing.

For each visible true contact of the first photo(s) of a sample scene, snap a
trace from its two end points (each off by a hand's ±1.5 px, as
``bench_snap`` does) and measure, in pixels, how far the snapped polyline
lies from the perfect drawing (the true trace's own projection, true pose):
the median and tail over all points, the share of contacts followed on
another edge (median > 1 px), and the worst contacts. Issue 14's diagnosis
(docs/benchmarks.md, bench_snap) came from it::

    .venv/bin/python benchmarks/snap_diagnostics.py small 1
"""
import sys
from pathlib import Path
import numpy as np
sys.path.insert(0, str(Path(__file__).parent))
from scipy.spatial import cKDTree
from napari_imgreg import Scene
from napari_imgreg.interpret.snap import SnapParams, snap_trace
from napari_imgreg.io.photos import load_photo
from napari_imgreg.sample import load_truth, sample_scene
from bench_interpret import drawn_lines

def dense(px, step=0.25):
    out = [px[:1]]
    for a, b in zip(px[:-1], px[1:]):
        n = max(int(np.ceil(np.linalg.norm(b - a) / step)), 1)
        out.append(a + (b - a) * (np.arange(1, n + 1) / n)[:, None])
    return np.concatenate(out)

def run(size="small", photos=1, params=SnapParams(), verbose=False):
    folder = sample_scene(size); truth = load_truth(folder)
    scene = Scene.load(folder / "outcrop.obj", dem=folder / "dem.tif"); scene.build_engine()
    allerr, per = [], []
    for name in sorted(truth.photos)[:photos]:
        pt = truth.photos[name]
        drawn = drawn_lines(scene, pt.intrinsics, pt.pose, truth.lines)
        image = load_photo(pt.photo).image
        rng = np.random.default_rng(0)
        for item, k in drawn:
            ends = item.pixels[[0, -1]] + rng.normal(0, 1.5, (2, 2))
            ends = np.clip(ends, 0, [image.shape[1] - 1, image.shape[0] - 1])
            px = snap_trace(image, ends, params)
            tree = cKDTree(dense(item.pixels))
            d = tree.query(dense(px))[0]
            allerr.append(d); per.append((name, k, len(item.pixels), float(np.linalg.norm(item.pixels[-1]-item.pixels[0])), float(np.median(d)), float(np.percentile(d, 90))))
    e = np.concatenate(allerr)
    med = np.array([p[4] for p in per])
    print(f"pixel error: median {np.median(e):.3f} p75 {np.percentile(e,75):.2f} p90 {np.percentile(e,90):.2f}; contacts {len(per)}, median>1px: {np.mean(med>1):.0%}, p90>2px: {np.mean(np.array([p[5] for p in per])>2):.0%}; median over good contacts {np.median(np.concatenate([a for a,p in zip(allerr,per) if p[4]<=1])):.3f}")
    if verbose:
        for p in sorted(per, key=lambda p: -p[5])[:15]: print(p)
    return e, per

if __name__ == "__main__":
    run(sys.argv[1] if len(sys.argv) > 1 else "small", int(sys.argv[2]) if len(sys.argv) > 2 else 1, verbose=True)

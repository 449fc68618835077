"""What stands between the snapped traces and 1.2x the perfect drawing (issue 14).

Three readings of ``bench_snap``'s must-show ratio (median 3D distance of the
snapped traces over that of the perfect drawing, the photo's registered pose),
on the benchmark's photos and clicks (each end of each contact off by a
Gaussian 1.5 px; the clicks are drawn as in ``bench_snap`` but without its
waypoint draws, so they match its own up to the first stray):

``strays``
    The snapped traces as shipped; the traces that stray (median more than
    1.5 px from the perfect drawing) replaced by the perfect drawing; and each
    two-click trace traced with both polarities and the better one kept in
    hindsight. How much is left to win by not straying.
``offset``
    The reference of ``bench_snap``'s photo's-edge column (the perfect drawing
    moved onto the photo's steepest luminance step, ``refined_edge_at_contact``)
    started on the perfect drawing and 0.3 px to either side of it. How much a
    sub-pixel offset of one sign moves the ratio against the registration's
    own error.

    .venv/bin/python benchmarks/diag_snap_gap.py --sizes small large

Needs the registered poses cached by ``bench_snap.py`` (``_cache/interpret_poses.json``).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).parent))

import bench_snap as bs  # noqa: E402
from bench_interpret import _register, drawn_lines  # noqa: E402
from napari_imgreg.interpret import snap as S  # noqa: E402
from napari_imgreg.interpret.project import Interpretation  # noqa: E402
from napari_imgreg.io.photos import load_photo  # noqa: E402


def _both_polarities(image: np.ndarray, ends: np.ndarray, params: S.SnapParams):
    """The two-click trace with each polarity (as ``snap_trace`` builds it)."""
    h, w = image.shape[:2]
    pad = params.margin_px + params.snap_radius_px + int(4 * params.smoothing_px) + 4
    c0, r0 = (int(max(np.floor(ends[:, i].min()) - pad, 0)) for i in (0, 1))
    c1 = int(min(np.ceil(ends[:, 0].max()) + pad + 1, w))
    r1 = int(min(np.ceil(ends[:, 1].max()) + pad + 1, h))
    sub = image[r0:r1, c0:c1]
    a, b = ends - (c0, r0)
    gx, gy = S._luminance_derivatives(sub, params.smoothing_px)
    chroma = S._chroma_derivatives(sub)
    t = b - a
    normal = np.array([-t[1], t[0]]) / np.linalg.norm(t)
    colour = S._colour_step(*chroma, normal, np.stack([a, b])) if chroma is not None else None
    lum = S._gray(S._unit(sub))
    return [np.clip(S._refine_across(lum, S._oriented_piece(gx, gy, a, b, normal, sign, params,
                                                            colour), params) + (c0, r0),
                    0, [w - 1, h - 1]) for sign in (1.0, -1.0)]


def _shifted(px: np.ndarray, by_px: float) -> np.ndarray:
    pts = S._resample(px)
    t = np.gradient(ndimage.gaussian_filter1d(pts, 2.0, axis=0, mode="nearest"), axis=0)
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-9)
    return pts + by_px * np.stack([-t[:, 1], t[:, 0]], axis=1)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", nargs="+", default=["small", "large"], choices=["small", "large"])
    args = ap.parse_args()
    params = S.SnapParams()
    edge_params = replace(params, refine_reach_px=1.5, simplify_px=0.0)
    n_photo = 0
    print("| scene | snapped | strays replaced by the perfect drawing | polarity chosen in hindsight "
          "| off the contact: as shipped / hindsight | photo's edge from the truth | "
          "from 0.3 px to one side | to the other |")
    print("|---|---|---|---|---|---|---|---|")
    for size in args.sizes:
        truth, scene, trees = bs.load_scene(size)
        dist = {key: [] for key in ("perfect", "snapped", "no_strays", "hindsight",
                                    "edge0", "edge+", "edge-")}
        off_shipped, off_hindsight = [], []
        for name in sorted(truth.photos):
            pt = truth.photos[name]
            reg, _ = _register(scene, name, pt, size, bs.POSES)
            image = load_photo(pt.photo).image
            lum = S._gray(S._unit(image))
            rng = np.random.default_rng(n_photo)
            n_photo += 1

            def d3(px, k):
                return bs._distances(scene, reg.intrinsics, reg.pose,
                                     [(Interpretation("LineString", px, {}), k)], trees)

            for item, k in drawn_lines(scene, pt.intrinsics, pt.pose, truth.lines):
                perfect = item.pixels
                ends = np.clip(perfect[[0, -1]] + rng.normal(0, bs.CLICK_JITTER_PX, (2, 2)),
                               0, [image.shape[1] - 1, image.shape[0] - 1])
                shipped = S.snap_trace(image, ends, params)
                both = _both_polarities(image, ends, params)
                offs = [bs._offset_px(perfect, px) for px in both]
                off = bs._offset_px(perfect, shipped)
                off_shipped.append(off)
                off_hindsight.append(min(offs))
                dist["perfect"].append(d3(perfect, k))
                dist["snapped"].append(d3(shipped, k))
                dist["no_strays"].append(dist["perfect"][-1] if off > bs.OFF_CONTACT_PX
                                         else dist["snapped"][-1])
                dist["hindsight"].append(d3(both[int(np.argmin(offs))], k))
                for key, by in (("edge0", 0.0), ("edge+", 0.3), ("edge-", -0.3)):
                    dist[key].append(d3(S._refine_across(lum, _shifted(perfect, by), edge_params), k))
        med = {key: float(np.median(np.concatenate(v))) for key, v in dist.items()}
        r = {key: med[key] / med["perfect"] for key in med}
        print(f"| {size} | {r['snapped']:.2f} | {r['no_strays']:.2f} | {r['hindsight']:.2f} | "
              f"{np.mean(np.array(off_shipped) > bs.OFF_CONTACT_PX):.1%} / "
              f"{np.mean(np.array(off_hindsight) > bs.OFF_CONTACT_PX):.1%} | {r['edge0']:.2f} | "
              f"{r['edge+']:.2f} | {r['edge-']:.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

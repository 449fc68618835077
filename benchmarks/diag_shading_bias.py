"""Why a bare mesh under a low sun registers 3-5 px off: the shading bias of block matching.

On the rough benchmark's ``rough_changed_untextured`` tier (issue 13) area
matching ends 3-6 px off. This diagnostic separates the causes. For each
photo it renders, from the photo's **true** pose and relit for its sun,

* the user's model (relief smoothed) without texture, as the pipeline does;
* the **true** surface the photo was rendered from, also without texture;

matches the render's blocks in the photo exactly as area matching does
(:func:`napari_imgreg.registration.stages.area.match_blocks`, radius 12 px at
1024 px width) and reports the median block shift (photo minus render; zero
for an unbiased matcher at the true pose) and its component along the sun's
direction in the image. It then runs one area-matching trial from the true
pose on the model and reports where it ends (median check-point error at
1632 px). With ``--edges`` it also refines the pose by edge alignment from
the true pose (no search; all edge kinds, then skyline and occluding contours
alone), and reports where that ends and where the mean of the area and edge
poses is.

    .venv/bin/python benchmarks/diag_shading_bias.py --seeds 1 3 5 --photos 1 2
    .venv/bin/python benchmarks/diag_shading_bias.py --seeds 1 3 5 --photos 1 2 3 --edges

Needs the scenes cached by ``bench_register.py --tiers rough_changed_untextured``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).parent))

import bench_register as br  # noqa: E402
from napari_imgreg import Scene  # noqa: E402
from napari_imgreg.camera import Pose  # noqa: E402
from napari_imgreg.io.photos import load_photo  # noqa: E402
from napari_imgreg.prior import prior_for_photo  # noqa: E402
from napari_imgreg.registration import pipeline as P  # noqa: E402
from napari_imgreg.registration.params import RegistrationParams  # noqa: E402
from napari_imgreg.registration.stages.area import (  # noqa: E402
    match_blocks, prepare_photo, prepare_render)
from napari_imgreg.registration.stages.edges import EdgeParams, align_edges  # noqa: E402
from napari_imgreg.registration.stages.relight import render_sunlit  # noqa: E402
from napari_imgreg.sample import load_truth  # noqa: E402

WIDTH = 1024
RADIUS_PX = 12


def block_shift(ctx, scene, truth, sun, params) -> tuple[np.ndarray, float, int]:
    """Median block shift (px at ``WIDTH``), its component along the sun, blocks matched."""
    ap = params.area
    small, scale = ctx.photo_at(WIDTH)
    r = render_sunlit(scene, truth.intrinsics, truth.pose, sun, scale=scale)
    b = match_blocks(prepare_photo(small, ap.band_sigma_px),
                     prepare_render(r.rgb, r.mask, ap.band_sigma_px), r.mask,
                     template_px=ap.template_px, search_px=RADIUS_PX, stride_px=ap.stride_px,
                     min_score=ap.min_score, max_second_ratio=ap.max_second_ratio,
                     min_texture=ap.min_texture, min_coverage=ap.min_coverage)
    s = b.shift[b.accepted]
    # The sun's direction in the image, at a point 100 m ahead.
    ahead = truth.pose.center + 100.0 * truth.pose.R[2]
    p = truth.pose.project(truth.intrinsics, np.array([ahead, ahead + 5.0 * sun])) * scale
    d = (p[1] - p[0]) / np.linalg.norm(p[1] - p[0])
    return np.median(s, axis=0), float(np.median(s @ d)), len(s)


def _cp_px(pose: Pose, truth) -> float:
    """Median check-point error of a pose, px at 1632 px width."""
    err = np.linalg.norm(pose.project(truth.intrinsics, truth.check_xyz) - truth.check_pixels,
                         axis=1) * br.REFERENCE_WIDTH / truth.intrinsics.width
    return float(np.median(err))


def _edge_cells(bare, photo, truth, area_pose: Pose) -> list[str]:
    """Edge alignment from the true pose (all kinds; skyline and occluding only), and the
    mean of the area and edge poses: median check-point errors, px."""
    cells, edge_pose = [], None
    for weights in ({}, {"crease": 0.0, "albedo": 0.0}):
        ep = EdgeParams(search_rotation_deg=(0.0, 0.0, 0.0), levels=(768, 1632),
                        kind_weights=weights)
        a = align_edges(bare, photo.image, truth.intrinsics, truth.pose, ep,
                        position_sigma_m=5.0, search_position_m=0)
        cells.append(f"{_cp_px(a.pose, truth):.2f} px" + ("" if a.ok else " (not ok)"))
        edge_pose = edge_pose or a.pose
    mean_r = Rotation.from_matrix(np.stack([area_pose.R, edge_pose.R])).mean().as_matrix()
    mean = Pose.from_center(mean_r, 0.5 * (area_pose.center + edge_pose.center))
    cells.append(f"{_cp_px(mean, truth):.2f} px")
    return cells


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 3, 5])
    ap.add_argument("--photos", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--edges", action="store_true",
                    help="also edge alignment from the true pose, and the mean of both poses")
    args = ap.parse_args()
    params = RegistrationParams()
    extra = (" edges from the true pose | skyline and occluding only | mean of area and edges |"
             if args.edges else "")
    print("| scene | photo | sun elevation | model: median shift (px at 1024) | along the sun | "
          "true surface: median shift | along the sun | area trial from the true pose |" + extra)
    print("|---|---|---|---|---|---|---|---|" + ("---|---|---|" if args.edges else ""))
    for seed in args.seeds:
        root = br.DEFAULT_CACHE / f"large-seed{seed}-n8-g3-b2" / f"rough-r{br.ROUGH_VERSION}"
        model = Scene.load(root / "model" / "outcrop.obj")
        model.build_engine()
        bare = br.untextured(model)
        true_bare = Scene(np.load(root / "model" / "true_vertices.npy"), model.faces,
                          name="true surface")
        true_bare.build_engine()
        for k in args.photos:
            path = root / "rough_changed_light" / f"IMG_{k:04d}.jpg"
            truth, photo = load_truth(path), load_photo(path)
            prior = prior_for_photo(photo, bare)
            ctx = P._Context(bare, photo.image, truth.intrinsics, params, lambda: None)
            ctx.sun = prior.sun
            m_shift, m_along, _ = block_shift(ctx, bare, truth, prior.sun, params)
            t_shift, t_along, _ = block_shift(ctx, true_bare, truth, prior.sun, params)
            trial = P.run_to_end(P._run_trial(ctx, 0, truth.pose, params, "diagnostic",
                                              mode="sunlit", matcher="area", far_start=False))
            elev = float(np.degrees(np.arcsin(prior.sun[2])))
            cells = ""
            if args.edges:
                cells = " " + " | ".join(_edge_cells(bare, photo, truth, trial.pose)) + " |"
            print(f"| {seed} | {path.name} | {elev:.0f}° | ({m_shift[0]:+.2f}, {m_shift[1]:+.2f}) "
                  f"| {m_along:+.2f} | ({t_shift[0]:+.2f}, {t_shift[1]:+.2f}) | {t_along:+.2f} | "
                  f"{br._trial_cp(trial, truth):.2f} px |{cells}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

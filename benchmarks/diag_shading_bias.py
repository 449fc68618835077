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

With ``--sunshift`` it tests a sun-shift nuisance (``_sunshift.py``): at the
true pose, one length ``b`` fitted to the block shifts (how much of them
``b s(x)`` explains), then the pose alone and the pose with ``b`` solved from
the same blocks. ``--sunshift-trials`` runs area-matching trials with ``b``
solved in every round, from the true pose and from the pose the pipeline
registers on the untextured tier (cached in ``--poses``).

With ``--ground`` it asks whether the near ground pins the camera centre
that the cliff's blocks leave free: from the true pose the centre is moved
sideways (horizontal, across the view) and up by -0.8 to +0.8 m, the rotation
refitted to keep the cliff where it was (the bearings of the cliff's render
points, Wahba's problem), and the bare model relit from each pose is compared
with the photo on the near ground (the render's ground, lower 45 % of the
frame): correlation of the luminance blurred by 3 px, and of the gradient
orientation at 4 px (px at 1024 width). It reports where each peaks.

    .venv/bin/python benchmarks/diag_shading_bias.py --seeds 1 3 5 --photos 1 2
    .venv/bin/python benchmarks/diag_shading_bias.py --seeds 1 3 5 --photos 1 2 3 --edges
    .venv/bin/python benchmarks/diag_shading_bias.py --seeds 1 3 5 --photos 1 2 3 --sunshift
    .venv/bin/python benchmarks/diag_shading_bias.py --seeds 1 3 5 --photos 1 2 3 --sunshift-trials
    .venv/bin/python benchmarks/diag_shading_bias.py --seeds 1 3 5 --photos 1 2 --ground

Needs the scenes cached by ``bench_register.py --tiers rough_changed_untextured``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy import ndimage
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
import _sunshift as SS  # noqa: E402
from napari_imgreg.registration.pose import estimate_pose  # noqa: E402
from napari_imgreg.camera import pixels_to_full  # noqa: E402
from napari_imgreg.sample import load_truth  # noqa: E402

WIDTH = 1024
RADIUS_PX = 12


def _true_pose_blocks(ctx, scene, truth, sun, params):
    """The sun-lit render from the true pose (at ``WIDTH``), its scale, and
    its blocks matched in the photo as area matching does."""
    ap = params.area
    small, scale = ctx.photo_at(WIDTH)
    r = render_sunlit(scene, truth.intrinsics, truth.pose, sun, scale=scale)
    blocks = match_blocks(prepare_photo(small, ap.band_sigma_px),
                          prepare_render(r.rgb, r.mask, ap.band_sigma_px), r.mask,
                          template_px=ap.template_px, search_px=RADIUS_PX,
                          stride_px=ap.stride_px, min_score=ap.min_score,
                          max_second_ratio=ap.max_second_ratio, min_texture=ap.min_texture,
                          min_coverage=ap.min_coverage)
    return r, scale, blocks


def block_shift(ctx, scene, truth, sun, params) -> tuple[np.ndarray, float, int]:
    """Median block shift (px at ``WIDTH``), its component along the sun, blocks matched."""
    r, scale, b = _true_pose_blocks(ctx, scene, truth, sun, params)
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


def _cell_medians(points: np.ndarray, shift: np.ndarray, cell_px: float) -> np.ndarray:
    """Median shift of each square cell with five blocks or more, (C, 2)."""
    cell = np.floor(points / cell_px).astype(int)
    keys = cell[:, 0] * 100_003 + cell[:, 1]
    out = [np.median(shift[keys == k], axis=0) for k in np.unique(keys)
           if (keys == k).sum() >= 5]
    return np.array(out).reshape(-1, 2)


def sunshift_cells(ctx, scene, truth, sun, params) -> list[str]:
    """The sun-shift nuisance at the true pose (``--sunshift``): per model
    (tangent, shadow) the fitted ``b`` (m), the median block shift before and
    after removing ``b s(x)`` (px at ``WIDTH``), the share of the shifts'
    (uncentred) variance it explains; then the pose alone and the pose with
    ``b`` solved from the same blocks (median check-point error, px at 1632)."""
    ap = params.area
    r, scale, bm = _true_pose_blocks(ctx, scene, truth, sun, params)
    xyz, ok = r.lift(bm.render_points)
    ok &= bm.accepted
    rp, pp, xyz = bm.render_points[ok], bm.photo_points[ok], xyz[ok]
    nrm = SS.block_normals(r.normal, r.mask, ap.template_px)
    ij = np.round(rp).astype(int)
    n = nrm[ij[:, 1], ij[:, 0]]
    shift = pp - rp  # px at WIDTH
    uv = pixels_to_full(pp, scale)
    # The sun's direction in the image (as block_shift), for the along-sun median.
    ahead = truth.pose.center + 100.0 * truth.pose.R[2]
    q = truth.pose.project(truth.intrinsics, np.array([ahead, ahead + 5.0 * sun])) * scale
    sdir = (q[1] - q[0]) / np.linalg.norm(q[1] - q[0])
    # Blocks within the pipeline's RANSAC threshold (6 px at full width) of
    # the true pose: the wrong matches would swamp a least-squares fit.
    near = np.linalg.norm(shift, axis=1) < 6.0 * scale
    sh = shift[near]

    def stats(r: np.ndarray) -> str:
        m = np.median(r, axis=0)
        return (f"|med|={np.linalg.norm(m):.2f}, sun {np.median(r @ sdir):+.2f}, "
                f"med|r|={np.median(np.linalg.norm(r, axis=1)):.2f}")

    cells = [f"{near.sum()}/{len(shift)}: " + stats(sh)]
    fits = {}
    for mode in ("tangent", "shadow"):
        d3 = SS.sun_shift_directions(n, sun, mode)
        s_img = SS.image_directions(truth.intrinsics, truth.pose, xyz, d3) * scale
        si = s_img[near]
        b = SS.fit_shift_scalar(sh, si, huber_px=1.5)
        ex = 1.0 - float(np.sum((sh - b * si) ** 2) / np.sum(sh ** 2))
        # The systematic part: median shifts of cells an eighth of the width wide.
        c0, c1 = _cell_medians(rp[near], sh, WIDTH / 8), _cell_medians(rp[near], sh - b * si,
                                                                       WIDTH / 8)
        ex_c = 1.0 - float(np.sum(c1 ** 2) / np.sum(c0 ** 2))
        cells.append(f"b={b:+.2f} m (|s|={np.median(np.linalg.norm(si, axis=1)):.1f} px/m): "
                     + stats(sh - b * si) + f", {100 * ex:.0f} % (cells {100 * ex_c:.0f} %)")
        fits[mode] = (d3, b)
    # Poses from these blocks: RANSAC EPnP as the pipeline; the same refined
    # by robust LS with b fixed at 0 and with b free.
    est = estimate_pose(truth.intrinsics, xyz, uv, params.pose, rng_seed=0)
    cells.append(f"{_cp_px(est.pose, truth):.2f}" if est.ok else "–")
    start = est.pose if est.ok else truth.pose
    f0 = SS.solve_pose_sun_shift(truth.intrinsics, start, xyz, uv, fits["tangent"][0],
                                 fix_b=0.0)
    cells.append(f"{_cp_px(f0.pose, truth):.2f}")
    for mode in ("tangent", "shadow"):
        d3, b_true = fits[mode]
        f = SS.solve_pose_sun_shift(truth.intrinsics, start, xyz, uv, d3)
        fo = SS.solve_pose_sun_shift(truth.intrinsics, start, xyz, uv, d3, fix_b=b_true)
        cells.append(f"{_cp_px(f.pose, truth):.2f} (b={f.b:+.2f}±{f.b_sigma:.2f}, "
                     f"ρ={f.correlation:.3f}); b fixed at the true pose's: "
                     f"{_cp_px(fo.pose, truth):.2f}")
    cells.append(str(len(xyz)))
    return cells


def _ncc(a: np.ndarray, b: np.ndarray, m: np.ndarray) -> float:
    a, b = a[m] - a[m].mean(), b[m] - b[m].mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum() + 1e-9))


def _orientation_corr(a: np.ndarray, b: np.ndarray, m: np.ndarray, sigma: float) -> float:
    """Correlation of the gradient orientation (sign-free: doubled angles,
    weighted by squared magnitude) of two images over a mask."""
    za, zb = ((ndimage.gaussian_filter(x, sigma, order=(0, 1))
               + 1j * ndimage.gaussian_filter(x, sigma, order=(1, 0))) ** 2 for x in (a, b))
    num = (za[m] * np.conj(zb[m])).sum().real
    return float(num / np.sqrt((np.abs(za[m]) ** 2).sum() * (np.abs(zb[m]) ** 2).sum() + 1e-9))


def ground_main(args) -> int:
    """``--ground``: does the near ground pin the centre? (See the module docstring.)"""
    import cv2

    deltas = np.round(np.arange(-0.8, 0.81, 0.2), 2)
    print("| scene | photo | move | check-point error at ±0.4 / ±0.8 m (px) | "
          "blurred luminance peaks at (m), contrast | gradient orientation peaks at (m), contrast |")
    print("|---|---|---|---|---|---|")
    for seed, _, bare, path, truth, photo, prior in _photos(args):
        K, C0, R0 = truth.intrinsics, truth.pose.center, truth.pose.R
        scale = WIDTH / K.width
        r0 = render_sunlit(bare, K, truth.pose, prior.sun, scale=scale)
        h, w = r0.mask.shape
        cliff = r0.xyz[r0.mask & (np.abs(r0.normal[..., 2]) < 0.8)][::50].astype(float)
        bearings = (cliff - C0) @ R0.T
        side = np.array([R0[0, 0], R0[0, 1], 0.0])
        small = cv2.resize(photo.image, (w, h), interpolation=cv2.INTER_AREA)
        lum_photo = small.astype(np.float32).mean(axis=2)
        for name, e in (("sideways", side / np.linalg.norm(side)), ("up", np.array([0, 0, 1.0]))):
            cps, lum_s, ori_s = [], [], []
            for dlt in deltas:
                center = C0 + dlt * e
                rot, _ = Rotation.align_vectors(bearings, cliff - center)
                pose = Pose.from_center(rot.as_matrix(), center)
                r = render_sunlit(bare, K, pose, prior.sun, scale=scale)
                ground = r.mask & (r.normal[..., 2] > 0.8)
                ground[: int(0.55 * h)] = False
                lum = r.rgb.astype(np.float32).mean(axis=2)
                cps.append(_cp_px(pose, truth))
                lum_s.append(_ncc(ndimage.gaussian_filter(lum_photo, 3.0),
                                  ndimage.gaussian_filter(lum, 3.0), ground))
                ori_s.append(_orientation_corr(lum_photo, lum, ground, 4.0))
            mid = len(deltas) // 2
            cells = [f"{cps[mid - 2]:.1f}, {cps[mid + 2]:.1f} / {cps[0]:.1f}, {cps[-1]:.1f}"]
            for v in (np.array(lum_s), np.array(ori_s)):
                cells.append(f"{deltas[v.argmax()]:+.1f}, {v.max() - np.median(v):.3f}")
            print(f"| {seed} | {path.name} | {name} | " + " | ".join(cells) + " |", flush=True)
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 3, 5])
    ap.add_argument("--photos", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--edges", action="store_true",
                    help="also edge alignment from the true pose, and the mean of both poses")
    ap.add_argument("--sunshift", action="store_true",
                    help="the sun-shift nuisance at the true pose: fit b, then pose + b")
    ap.add_argument("--sunshift-trials", action="store_true",
                    help="area-matching trials with the sun-shift nuisance (off, tangent, "
                         "shadow) from the true pose and from the pipeline's own pose")
    ap.add_argument("--cache", type=Path, default=br.DEFAULT_CACHE,
                    help="the benchmark's data cache (default benchmarks/_cache)")
    ap.add_argument("--poses", type=Path, default=None,
                    help="JSON file caching the pipeline's own untextured-tier poses")
    ap.add_argument("--ground", action="store_true",
                    help="does the near ground pin the camera centre? similarity profiles "
                         "as the centre moves sideways and up from the true pose")
    args = ap.parse_args()
    params = RegistrationParams()
    if args.ground:
        return ground_main(args)
    if args.sunshift_trials:
        return sunshift_trials_main(args, params)
    if args.sunshift:
        return sunshift_main(args, params)
    extra = (" edges from the true pose | skyline and occluding only | mean of area and edges |"
             if args.edges else "")
    print("| scene | photo | sun elevation | model: median shift (px at 1024) | along the sun | "
          "true surface: median shift | along the sun | area trial from the true pose |" + extra)
    print("|---|---|---|---|---|---|---|---|" + ("---|---|---|" if args.edges else ""))
    true_bare, true_seed = None, None
    for seed, root, bare, path, truth, photo, prior in _photos(args):
        if seed != true_seed:  # the surface the photos were rendered from, once per scene
            true_bare = Scene(np.load(root / "model" / "true_vertices.npy"), bare.faces,
                              name="true surface")
            true_bare.build_engine()
            true_seed = seed
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


def _load(seed: int, cache: Path):
    root = cache / f"large-seed{seed}-n8-g3-b2" / f"rough-r{br.ROUGH_VERSION}"
    model = Scene.load(root / "model" / "outcrop.obj")
    model.build_engine()
    return root, br.untextured(model)


def _photos(args):
    """Per chosen photo of the changed-light tier: (seed, root, bare model, path,
    truth, photo, prior); each scene is loaded once."""
    for seed in args.seeds:
        root, bare = _load(seed, args.cache)
        for k in args.photos:
            path = root / "rough_changed_light" / f"IMG_{k:04d}.jpg"
            truth, photo = load_truth(path), load_photo(path)
            yield seed, root, bare, path, truth, photo, prior_for_photo(photo, bare)


def sunshift_main(args, params) -> int:
    print("| scene | photo | sun elev. | blocks near / accepted: median shift vector, along "
          "the sun, median length (px at 1024) | tangent: b, the same after removing b s(x), variance "
          "explained | shadow: same | pose alone RANSAC "
          "(cp px) | pose alone LS | pose + b tangent | pose + b shadow | blocks |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for seed, _, bare, path, truth, photo, prior in _photos(args):
        ctx = P._Context(bare, photo.image, truth.intrinsics, params, lambda: None)
        elev = float(np.degrees(np.arcsin(prior.sun[2])))
        cells = sunshift_cells(ctx, bare, truth, prior.sun, params)
        print(f"| {seed} | {path.name} | {elev:.0f}° | " + " | ".join(cells) + " |",
              flush=True)
    return 0


def sunshift_trials_main(args, params) -> int:
    """One area-matching trial per nuisance model, from the true pose and from
    the pose the pipeline registers on the untextured tier (median
    check-point error, px at 1632; the trial's last ``b``)."""
    import json

    from napari_imgreg.registration.pipeline import register

    cache = json.loads(args.poses.read_text()) if args.poses and args.poses.is_file() else {}
    modes = ("off", "tangent", "shadow")
    print("| scene | photo | start | start cp (px) | " + " | ".join(
        f"trial, sun_shift {m}" for m in modes) + " |")
    print("|---|---|---|---|" + "---|" * len(modes))
    for seed, _, bare, path, truth, photo, prior in _photos(args):
        key = f"{seed}/{path.name}"
        if key not in cache:
            reg = register(bare, photo.image, prior, params, path.name)
            cache[key] = {"R": reg.pose.R.tolist(), "t": reg.pose.t.tolist(),
                          "status": reg.status}
            if args.poses:
                args.poses.write_text(json.dumps(cache, indent=1))
        own = Pose(np.array(cache[key]["R"]), np.array(cache[key]["t"]))
        for label, start in (("true", truth.pose), ("pipeline", own)):
            cells = []
            for mode in modes:
                ctx = P._Context(bare, photo.image, truth.intrinsics, params, lambda: None)
                ctx.sun = prior.sun
                with SS.patched(mode):
                    t = P.run_to_end(P._run_trial(ctx, 0, start, params, "diagnostic",
                                                  mode="sunlit", matcher="area",
                                                  far_start=False))
                b = t.metrics.get("sun_shift_m")
                unc = t.uncertainty.reprojection_px if t.uncertainty is not None else None
                cells.append(f"{br._trial_cp(t, truth):.2f}"
                             + ("" if b is None else f" (b={b:+.2f}, "
                                f"ρ={t.metrics.get('sun_shift_confounding')})")
                             + ("" if unc is None else f", est {unc:.1f}"))
            print(f"| {seed} | {path.name} | {label} | {_cp_px(start, truth):.2f} | "
                  + " | ".join(cells) + " |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

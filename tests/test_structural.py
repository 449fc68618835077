"""Line and plane fits, orientation conventions, vetting, Fisher statistics, stereonet."""

from __future__ import annotations

import math

import numpy as np
import pytest

from napari_imgreg.interpret.structural import (
    FitThresholds,
    dip_dip_direction,
    equal_area,
    fisher_mean,
    fit_line,
    fit_plane,
    measure_facet,
    measure_trace,
    normal_from_dip,
    plunge_trend,
    pole_of_plane,
    save_stereonet,
    vector_from_plunge_trend,
)


def _angle_diff(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


def _plane_points(dip, ddir, n=400, size=10.0, noise=0.0, seed=0):
    rng = np.random.default_rng(seed)
    normal = normal_from_dip(dip, ddir)
    a = np.cross(normal, [0.0, 0.0, 1.0]) if dip > 1e-9 else np.array([1.0, 0, 0])
    a /= np.linalg.norm(a)
    b = np.cross(normal, a)
    uv = rng.uniform(-size, size, (n, 2))
    pts = uv[:, :1] * a + uv[:, 1:] * b + np.array([100.0, -50.0, 20.0])
    return pts + rng.normal(0, noise, pts.shape) if noise else pts


# ------------------------------------------------------------- conventions
def test_dip_direction_is_the_azimuth_of_steepest_descent():
    # z falls toward the north (+Y): dips north, dip direction 0.
    pts = np.array([[0, 0, 0], [10, 0, 0], [0, 10, -10 * math.tan(math.radians(30))],
                    [10, 10, -10 * math.tan(math.radians(30))], [5, 5, -5 * math.tan(math.radians(30))]])
    fit = fit_plane(pts, check_relief=False)
    assert fit.dip_deg == pytest.approx(30.0, abs=1e-9)
    assert _angle_diff(fit.dip_direction_deg, 0.0) < 1e-9
    assert dip_dip_direction(np.array([0, 0, -1.0])) == (0.0, 0.0)  # either normal sign
    assert dip_dip_direction(normal_from_dip(90.0, 250.0)) == pytest.approx((90.0, 250.0))


def test_plunge_is_positive_downward_and_trend_clockwise_from_north():
    assert plunge_trend(np.array([1.0, 0.0, -1.0])) == pytest.approx((45.0, 90.0))
    assert plunge_trend(np.array([-1.0, 0.0, 1.0])) == pytest.approx((45.0, 90.0))  # same line
    assert plunge_trend(np.array([0.0, -1.0, 0.0])) == pytest.approx((0.0, 0.0))  # horizontal
    assert plunge_trend(np.array([0.0, 0.0, 1.0])) == (90.0, 0.0)
    assert pole_of_plane(30.0, 120.0) == (60.0, 300.0)


@pytest.mark.parametrize("dip,ddir", [(0.5, 17.0), (12.0, 200.0), (45.0, 359.5), (65.0, 100.0),
                                      (89.5, 271.0), (30.0, 0.0)])
def test_plane_fit_known_orientation_with_noise(dip, ddir):
    fit = fit_plane(_plane_points(dip, ddir, noise=0.02), check_relief=False)
    assert fit.ok, fit.reason
    assert fit.dip_deg == pytest.approx(dip, abs=0.5)
    if dip > 1.0:
        assert _angle_diff(fit.dip_direction_deg, ddir) < 0.5
    assert fit.rms_m == pytest.approx(0.02, rel=0.2)
    assert fit.planarity > 0.99


@pytest.mark.parametrize("plunge,trend", [(0.0, 45.0), (25.0, 250.0), (60.0, 113.0), (88.0, 7.0)])
def test_line_fit_known_orientation_with_noise(plunge, trend):
    rng = np.random.default_rng(3)
    d = vector_from_plunge_trend(plunge, trend)
    t = rng.uniform(-20, 20, 300)[:, None]
    pts = t * d + rng.normal(0, 0.03, (300, 3)) + [5.0, 5.0, 5.0]
    fit = fit_line(pts)
    assert fit.plunge_deg == pytest.approx(plunge, abs=0.5)
    expected_trend = trend % 180.0 if plunge == 0.0 else trend
    if plunge < 89.0:
        assert _angle_diff(fit.trend_deg, expected_trend) < 0.5 or (
            plunge < 0.5 and _angle_diff(fit.trend_deg, expected_trend + 180) < 0.5)
    assert fit.collinearity > 0.99 and fit.length_m > 35.0


# ----------------------------------------------------------------- vetting
def test_collinear_points_give_no_plane():
    rng = np.random.default_rng(1)
    t = np.linspace(0, 30, 200)[:, None]
    pts = t * vector_from_plunge_trend(10.0, 80.0) + rng.normal(0, 0.01, (200, 3))
    fit = fit_plane(pts)
    assert fit is not None and not fit.ok and "planarity" in fit.reason
    m = measure_trace([pts], id="t1", label="fault")
    assert m.plunge_deg == pytest.approx(10.0, abs=0.5)
    assert m.dip_deg is None and m.dip_direction_deg is None and m.note.startswith("no plane")
    assert fit_plane(np.array([[0, 0, 0], [1, 1, 1], [2, 2, 2.0]])) is None  # exactly one line


def test_blob_has_low_planarity():
    pts = np.random.default_rng(2).normal(0, 1, (500, 3))
    fit = fit_plane(pts, check_relief=False)
    assert fit.planarity < 0.75 and not fit.ok


def test_surface_effect_rejects_the_outcrop_face():
    # A curved trace lying on the face itself: its best plane IS the face.
    pts = _plane_points(80.0, 180.0, n=200)
    face_normal = normal_from_dip(80.0, 180.0)
    fit = fit_plane(pts, surface_normal=face_normal)
    assert not fit.ok and "outcrop surface" in fit.reason
    tilted = normal_from_dip(60.0, 180.0)  # 20° away: accepted
    assert fit_plane(pts, surface_normal=tilted).ok


def test_nearly_straight_trace_is_rejected_by_relief():
    rng = np.random.default_rng(4)
    x = np.linspace(0, 40, 400)
    # A 40 m trace bowing by 0.2 m: planar, but the plane is ill-posed.
    pts = np.stack([x, 0.2 * np.sin(x / 40 * np.pi), 0.1 * x], axis=1)
    pts += rng.normal(0, 0.001, pts.shape)
    fit = fit_plane(pts)
    assert fit.planarity > 0.9 and not fit.ok and "relief" in fit.reason
    assert fit_plane(pts, FitThresholds(min_relief=0.0)).ok


def test_facet_and_trace_measurements():
    pts = _plane_points(33.0, 210.0, noise=0.01)
    m = measure_facet(pts, id="f1", label="sandstone", source="IMG_1.jpg")
    assert m.kind == "facet" and m.has_plane
    assert m.dip_deg == pytest.approx(33.0, abs=0.5)
    assert m.plunge_deg is None and m.trend_deg is None
    assert m.n_points == 400 and np.allclose(m.centroid, pts.mean(axis=0))
    few = measure_facet(pts[:2])
    assert few.dip_deg is None and few.planarity is None


# ------------------------------------------------------------------ Fisher
def _fisher_sample(mean, kappa, n, rng):
    """Fisher-distributed unit vectors (Wood's method) about ``mean``."""
    w = 1 + np.log(rng.uniform(np.exp(-2 * kappa), 1, n)) / kappa
    phi = rng.uniform(0, 2 * np.pi, n)
    s = np.sqrt(1 - w**2)
    v = np.stack([s * np.cos(phi), s * np.sin(phi), w], 1)
    mean = mean / np.linalg.norm(mean)
    z = np.array([0, 0, 1.0])
    axis = np.cross(z, mean)
    if np.linalg.norm(axis) < 1e-12:
        return v * np.sign(mean[2])
    axis /= np.linalg.norm(axis)
    ang = math.acos(np.clip(z @ mean, -1, 1))
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    R = np.eye(3) + math.sin(ang) * K + (1 - math.cos(ang)) * K @ K
    return v @ R.T


def test_fisher_mean_recovers_mean_and_alpha95_covers_it():
    rng = np.random.default_rng(5)
    true = vector_from_plunge_trend(78.0, 20.0)
    covered = 0
    for _ in range(200):
        v = _fisher_sample(true, 50.0, 20, rng)
        fm = fisher_mean(v)
        err = math.degrees(math.acos(min(1.0, abs(float(fm.vector @ true)))))
        covered += err <= fm.alpha95_deg
    assert 0.90 <= covered / 200 <= 0.99  # a 95 % cone
    fm = fisher_mean(_fisher_sample(true, 50.0, 2000, rng))
    assert fm.kappa == pytest.approx(50.0, rel=0.1)


def test_fisher_mean_of_axes_near_horizontal_does_not_cancel():
    # Poles of vertical planes striking N–S: half point east, half west.
    rng = np.random.default_rng(6)
    v = _fisher_sample(np.array([1.0, 0, 0]), 200.0, 40, rng)
    v[::2] *= -1
    fm = fisher_mean(v)
    assert fm.plunge_deg < 3.0 and _angle_diff(fm.trend_deg % 180, 90.0) < 3.0
    assert fm.alpha95_deg < 3.0
    single = fisher_mean(v[:1])
    assert single.alpha95_deg is None and single.kappa is None


# --------------------------------------------------------------- stereonet
def test_equal_area_projection():
    x, y = equal_area([90.0, 0.0, 0.0], [0.0, 0.0, 90.0])
    assert np.allclose([x[0], y[0]], 0.0)
    assert np.allclose([x[1], y[1]], [0.0, 1.0])  # north, on the primitive
    assert np.allclose([x[2], y[2]], [1.0, 0.0])  # east
    # Equal area: a 45° plunge sits at radius sqrt(2) sin(22.5°).
    x, y = equal_area(45.0, 0.0)
    assert math.hypot(x, y) == pytest.approx(math.sqrt(2) * math.sin(math.radians(22.5)))


def test_stereonet_picture(tmp_path):
    from PIL import Image

    ms = []
    for k, (dip, ddir) in enumerate([(12, 200), (14, 195), (11, 204), (65, 100), (63, 98)]):
        label = "sandstone" if dip < 30 else "fault"
        ms.append(measure_facet(_plane_points(dip, ddir, noise=0.01, seed=k), id=str(k), label=label))
    ms.append(measure_trace([np.linspace(0, 10, 20)[:, None] * vector_from_plunge_trend(20, 40)],
                            label="fault"))
    path = tmp_path / "net.png"
    fig = save_stereonet(path, ms, colors={"sandstone": "#ffd400", "fault": "#e31a1c"})
    img = np.asarray(Image.open(path))
    assert img.shape[0] > 500 and img.shape[1] > 500
    texts = " ".join(t.get_text() for t in fig.axes[0].texts)
    assert "sandstone: 3 planes" in texts and "α95" in texts and "1 trace" in texts


# ----------------------------------------------------------- issue 14: uncertainty
def test_viewing_plane_spread_known_answer():
    from napari_imgreg.interpret.uncertainty import viewing_plane

    cam = np.array([0.0, -100.0, 10.0])
    # Points in the plane z = 10 (through the camera): no spread.
    pts = np.array([[x, y, 10.0] for x, y in [(0, 0), (5, 3), (-7, 8), (2, -4)]])
    n, s = viewing_plane(pts, cam)
    assert s < 1e-9 and abs(abs(n[2]) - 1) < 1e-9
    # (±5, 0, 10 ± 0.5) in all four combinations: symmetric about z = 10, so
    # the best plane through C stays z = 10 and the RMS spread is 0.5 m.
    off = np.array([[x, 0.0, 10.0 + dz] for x in (-5, 5) for dz in (-0.5, 0.5)])
    assert viewing_plane(off, cam)[1] == pytest.approx(0.5, rel=1e-6)


def test_point_sigma_and_angle_sigmas_known_answers():
    from napari_imgreg.interpret.uncertainty import angle_sigmas, point_sigma

    # 1.5 px at 100 m with f = 1000 px: 0.15 m; at 60° incidence twice that.
    s = point_sigma(np.array([100.0, 100.0]), np.array([1.0, 0.5]), 1000.0, 1.5, 0.0)
    assert s == pytest.approx([0.15, 0.30])
    assert point_sigma(np.array([100.0]), np.array([1.0]), 1000.0, 0.0, 0.2)[0] == pytest.approx(0.2)
    # Azimuths wrap at 360°.
    assert angle_sigmas((10.0, 0.0), np.array([[9.0, 358.0], [11.0, 2.0]])) == (1.0, 2.0)


def test_pose_uncertainty_from_the_result_or_a_default():
    from napari_imgreg.interpret.uncertainty import PoseUncertainty

    u = PoseUncertainty.from_result(
        {"status": "registered", "pose": {}, "uncertainty": {
            "reprojection_px": 0.8, "position_m": 0.05, "rotation_deg": 0.02}}, 1000.0)
    assert (u.reprojection_px, u.position_m, u.rotation_deg, u.source) == (0.8, 0.05, 0.02, "result")
    d = PoseUncertainty.from_result({"status": "registered", "pose": {},
                                     "metrics": {"reprojection_error_px": 2.0}}, 1000.0, 50.0)
    assert d.source == "default" and d.reprojection_px == 2.0
    assert d.rotation_deg == pytest.approx(np.degrees(0.002)) and d.position_m == pytest.approx(0.1)
    # A NaN block is not trusted; a sensor record gets prior-sized errors.
    bad = PoseUncertainty.from_result({"status": "registered", "pose": {}, "uncertainty": {
        "reprojection_px": float("nan"), "position_m": 0.05, "rotation_deg": 0.02}}, 1000.0)
    assert bad.source == "default"
    assert PoseUncertainty.from_result({"camera": {}}, 1000.0).position_m == 5.0
    # A failed registration carries its prior's pose: prior-sized errors, not 2 px.
    failed = PoseUncertainty.from_result({"status": "failed", "pose": {},
                                          "metrics": {"reprojection_error_px": 2.0}}, 1000.0)
    assert (failed.reprojection_px, failed.position_m, failed.rotation_deg) == (50.0, 5.0, 3.0)
    assert failed.source == "default (not registered)"


def test_monte_carlo_sigma_of_a_straight_stroke_matches_the_closed_form():
    """A stroke between two drawn vertices seen face-on from 100 m: each vertex
    off by σ per axis across its ray and by s along it (the slide on an oblique
    surface). The line through the perturbed ends tilts by |Δ⊥| / L, Δ⊥ the
    ends' difference across the line (one axis across the ray, one along it),
    whose RMS is sqrt(2 (σ² + s²)) / L radians."""
    from napari_imgreg.interpret.uncertainty import ErrorModel, UncertaintyParams, monte_carlo

    L, sigma = 20.0, 0.1
    pts = np.linspace(0, 1, 50)[:, None] * np.array([L, 0.0, 0.0])
    for slide in (0.0, 0.2):
        model = ErrorModel(camera_position=np.array([10.0, -100.0, 0]), relative_m=sigma,
                           n_vertices=2, view_m=sigma,
                           along_ray_m=slide if slide else math.nan)
        mc = monte_carlo([[pts]], [model], UncertaintyParams(samples=4000, seed=1))
        tilt = []
        for (q,) in mc:
            d = q[-1] - q[0]
            tilt.append(np.arccos(abs(d[0]) / np.linalg.norm(d)))
        expected = math.sqrt(2 * (sigma**2 + slide**2)) / L
        assert np.sqrt(np.mean(np.square(tilt))) == pytest.approx(expected, rel=0.05)
        # The stroke stays straight: the interpolation is linear between the vertices.
        q = mc[0][0]
        assert np.linalg.svd(q - q.mean(0), compute_uv=False)[1] < 1e-9


def test_monte_carlo_error_off_the_viewing_plane_is_the_hands():
    """Issue 14: the drawing's error off the viewing plane is the image error's
    footprint (range × px / focal), whatever the obliquity; sliding along the
    ray stays in the viewing plane."""
    from napari_imgreg.interpret.uncertainty import (ErrorModel, UncertaintyParams,
                                                     monte_carlo, viewing_plane)

    cam = np.array([0.0, -100.0, 0.0])
    pts = np.stack([np.linspace(-10, 10, 40), np.zeros(40), np.zeros(40)], 1)
    normal, _ = viewing_plane(pts, cam)  # the plane z = 0
    model = ErrorModel(camera_position=cam, relative_m=0.3, n_vertices=2, view_m=0.1)
    mc = monte_carlo([[pts]], [model], UncertaintyParams(samples=3000, seed=2),
                     surface_normals=[np.array([0.0, -0.6, 0.8])])  # an oblique face
    off = np.array([(q[[0, -1]] - cam) @ normal for (q,) in mc])
    assert np.sqrt(np.mean(off**2)) == pytest.approx(0.1, rel=0.06)
    along = np.array([q[[0, -1], 1] for (q,) in mc])  # depth (the ray is ~ +y)
    assert np.sqrt(np.mean(along**2)) > 0.1  # the slide on the oblique face


def test_facet_gets_sigmas_and_csv_has_the_columns(tmp_path):
    import csv

    from napari_imgreg.interpret.files import write_measurements_csv
    from napari_imgreg.interpret.uncertainty import ErrorModel

    model = ErrorModel(camera_position=np.array([0, -80.0, 0]), relative_m=0.05, mesh_m=0.02,
                       rotation_deg=0.05, position_m=0.02)
    f = measure_facet(_plane_points(30, 120, noise=0.02, seed=2), id="f", label="x", source="a.jpg",
                      error_model=model)
    assert f.has_plane and 0 < f.dip_sigma_deg < 1.0 and f.dip_direction_sigma_deg > 0
    t = measure_trace([np.linspace(0, 10, 20)[:, None] * vector_from_plunge_trend(20, 40)],
                      id="t", label="x")
    path = tmp_path / "m.csv"
    write_measurements_csv(path, [f, t])
    rows = list(csv.DictReader(path.open()))
    for col in ("dip_sigma_deg", "dip_direction_sigma_deg", "plunge_sigma_deg",
                "trend_sigma_deg", "photo"):
        assert col in rows[0]
    assert float(rows[0]["dip_sigma_deg"]) > 0 and rows[0]["photo"] == "a.jpg"
    # No error model: every σ is empty, never a made-up number.
    assert rows[1]["plunge_sigma_deg"] == "" and rows[1]["dip_sigma_deg"] == ""


@pytest.mark.parametrize("dip", [60.0, 88.0, 89.7])
def test_steep_plane_sigmas_do_not_jump_across_the_vertical(dip):
    """A steep fault's Monte Carlo planes that tip past the vertical deviate
    by a little dip, not by 180° of dip direction: the σ of a plane dipping
    60° and of one dipping 88–89.7° are alike (at 89.7° the dip direction σ
    was 83°: every tipped sample counted as 180° off, and the dip σ too
    small; with 2° of scatter, already at 88°)."""
    from napari_imgreg.interpret.uncertainty import ErrorModel

    model = ErrorModel(camera_position=np.array([-80.0, 0.0, 0.0]), relative_m=0.05,
                       mesh_m=0.02, rotation_deg=0.5, position_m=0.02)
    f = measure_facet(_plane_points(dip, 100.0, size=4.0, noise=0.05, seed=3), id="f",
                      label="fault", error_model=model)
    assert f.has_plane and f.dip_deg == pytest.approx(dip, abs=0.5)
    assert 0.1 < f.dip_sigma_deg < 1.5
    # Across the pole: sin(dip) σ_ddir is about σ_dip for an even scatter.
    across = np.sin(np.radians(f.dip_deg)) * f.dip_direction_sigma_deg
    assert across == pytest.approx(f.dip_sigma_deg, rel=0.5)


def test_kamb_density_peaks_on_a_cluster():
    from napari_imgreg.interpret.structural import kamb_density

    rng = np.random.default_rng(0)
    v = vector_from_plunge_trend(60.0, 30.0) + rng.normal(0, 0.05, (50, 3))
    x, y, d = kamb_density(v, 61)
    k = np.nanargmax(d)
    px, py = equal_area(60.0, 30.0)
    assert np.hypot(x.ravel()[k] - px, y.ravel()[k] - py) < 0.08
    assert np.nanmax(d) > 10 and np.nanmin(d) < 0.5


def test_stereonet_is_written_in_the_format_its_suffix_names(tmp_path):
    from napari_imgreg.errors import InputError

    ms = [measure_facet(_plane_points(30.0, 90.0), id="a", label="bed")]
    save_stereonet(tmp_path / "net.PDF", ms)
    assert (tmp_path / "net.PDF").read_bytes().startswith(b"%PDF")
    for name in ("net", "net.jpg"):  # matplotlib: ValueError, or a JPEG; refused
        with pytest.raises(InputError, match=r"stereonet must be \.png, \.svg or \.pdf"):
            save_stereonet(tmp_path / name, ms)
        assert not (tmp_path / name).exists()


def test_stereonet_draws_cones_and_contours(tmp_path):
    from napari_imgreg.interpret.uncertainty import ErrorModel

    model = ErrorModel(camera_position=np.array([0, -80.0, 0]), relative_m=0.1, mesh_m=0.02)
    ms = [measure_facet(_plane_points(12 + k % 3, 200 + k, noise=0.05, seed=k), id=str(k),
                        label="bed", error_model=model) for k in range(8)]
    assert all(m.dip_sigma_deg for m in ms)
    fig = save_stereonet(tmp_path / "net.png", ms)
    ax = fig.axes[0]
    assert len(ax.collections) > 0  # the Kamb contours
    # One cone per pole at least, beyond the great circles, α95 and frame.
    assert len(ax.lines) >= 8 * 2 + 8


def test_pole_cone_holds_the_dip_directions_error_too():
    """The pole of a plane moves by σ_dip along its plunge and by
    sin(dip) σ_ddir across it; the cone is twice their quadratic sum (it was
    2 σ_dip alone: a steep fault's cone left out most of its azimuth error)."""
    from napari_imgreg.interpret.structural import Measurement, pole_cone_deg

    def plane(dip, s_dip, s_ddir):
        return Measurement("a", "fault", "trace", np.zeros(3), 10, dip_deg=dip,
                           dip_direction_deg=100.0, dip_sigma_deg=s_dip,
                           dip_direction_sigma_deg=s_ddir)

    assert pole_cone_deg(plane(65.0, 1.0, 2.0)) == pytest.approx(
        2.0 * np.hypot(1.0, np.sin(np.radians(65.0)) * 2.0))  # 3.9°, not 2°
    assert pole_cone_deg(plane(90.0, 3.0, 4.0)) == pytest.approx(10.0)
    # A near-horizontal plane's wild azimuth hardly moves its (vertical) pole.
    assert pole_cone_deg(plane(0.7, 1.4, 66.9)) == pytest.approx(
        2.0 * np.hypot(1.4, np.sin(np.radians(0.7)) * 66.9))
    assert pole_cone_deg(plane(30.0, 40.0, 40.0)) == 45.0  # capped
    assert pole_cone_deg(plane(30.0, None, None)) is None


def test_plane_from_three_points_known_answers():
    from napari_imgreg.interpret.structural import plane_from_three_points

    # A plane of 30°/120° through three points spanning it.
    n = normal_from_dip(30.0, 120.0)
    u = np.cross(n, [0.0, 0.0, 1.0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    pts = np.array([[0.0, 0.0, 0.0], 10 * u, 7 * v + 3 * u]) + [5.0, 2.0, 1.0]
    dip, ddir = plane_from_three_points(pts, camera_center=np.array([0.0, -80.0, 10.0]))
    assert dip == pytest.approx(30.0, abs=1e-9) and ddir == pytest.approx(120.0, abs=1e-9)
    # Hand-computable: z = -y through the origin dips 45° due north.
    assert plane_from_three_points(np.array([[0, 0, 0], [1, 0, 0], [0, 1, -1.0]])) == \
        pytest.approx((45.0, 0.0))
    # A horizontal plane: dip 0.
    assert plane_from_three_points(np.array([[0, 0, 3], [4, 0, 3], [0, 5, 3.0]]))[0] == 0.0
    assert "one line" in plane_from_three_points(np.array([[0, 0, 0], [1, 1, 1], [2, 2, 2.0]]))
    # The camera in the plane of the points: the viewing plane, refused.
    assert "viewing plane" in plane_from_three_points(pts, camera_center=pts[0] + 50 * u + 20 * v)


def test_along_ray_slide_known_answer_and_round_trip():
    """The depth error's RMS: range × px / focal × tan(incidence), gain capped."""
    from napari_imgreg.interpret.project import _along_ray_rms
    from napari_imgreg.interpret.uncertainty import ErrorModel

    # Face-on: no slide; cos 0.6 (tan 4/3): 100 m × 1.5 px / 1000 px × 4/3 = 0.2 m.
    assert _along_ray_rms(np.array([100.0]), np.array([1.0]), 1000.0, 1.5, 4.0) == 0.0
    assert _along_ray_rms(np.array([100.0]), np.array([0.6]), 1000.0, 1.5, 4.0) == \
        pytest.approx(0.2)
    # Grazing: capped at a gain of 4 (cos 1/4, tan √15).
    assert _along_ray_rms(np.array([100.0]), np.array([0.01]), 1000.0, 1.5, 4.0) == \
        pytest.approx(0.15 * math.sqrt(15))
    model = ErrorModel(np.zeros(3), 0.2, view_m=0.1, along_ray_m=0.17)
    back = ErrorModel.from_properties({"camera_position": [0, 0, 0],
                                       "uncertainty": model.to_properties()})
    assert back.along_ray_m == pytest.approx(0.17)
    older = ErrorModel.from_properties({"camera_position": [0, 0, 0], "sigma_m": 0.2})
    assert math.isnan(older.along_ray_m)  # files without it: from relative_m and view_m


@pytest.mark.parametrize("angle_deg, kept", [(3.5, False), (6.0, True)])
def test_a_plane_near_the_viewing_rays_is_refused(angle_deg, kept):
    """A trace bent within a plane that makes ``angle_deg`` with the rays from
    the camera: well off the viewing plane (many σ), but below 4° its dip's
    error outgrows the Monte Carlo's σ (issue 14: a 3.2° plane was 8° off)."""
    from napari_imgreg.interpret.structural import measure_trace
    from napari_imgreg.interpret.uncertainty import ErrorModel

    th = math.radians(angle_deg)
    x = np.linspace(-10, 10, 60)
    t = 5.0 * np.sin(x / 3.0)  # the bend, within the plane
    pts = np.stack([x, 100.0 + t * math.cos(th), t * math.sin(th)], axis=1)
    model = ErrorModel(camera_position=np.zeros(3), relative_m=0.01, n_vertices=20, view_m=0.01)
    m = measure_trace([pts], error_model=model)
    assert m.ray_angle_deg == pytest.approx(angle_deg, abs=0.3)
    assert m.view_spread > 5  # far off the viewing plane: only the angle decides
    assert m.has_plane is kept
    if not kept:
        assert "viewing rays" in m.note


def test_pose_uncertainty_of_a_registration_in_memory_reads_as_its_result():
    """The workspace and the workbench read a Registration object as
    ``project`` reads its RESULT.json: its estimate when registered; a failed
    one, whose pose is its prior's, prior-sized errors even with an estimate."""
    from types import SimpleNamespace

    from napari_imgreg.interpret.uncertainty import PoseUncertainty

    est = SimpleNamespace(reprojection_px=0.4, position_m=0.02, rotation_deg=0.01)
    u = PoseUncertainty.from_estimate(est, "registered", {}, 1000.0)
    assert (u.reprojection_px, u.position_m, u.rotation_deg, u.source) == (0.4, 0.02, 0.01, "result")
    assert PoseUncertainty.from_estimate(est, "failed", {}, 1000.0).position_m == 5.0
    d = PoseUncertainty.from_estimate(None, "registered", {"reprojection_error_px": 2.0}, 1000.0)
    assert d.source == "default" and d.reprojection_px == 2.0

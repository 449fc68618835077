"""Projection of drawn lines and polygons onto the surface: known answers."""

from __future__ import annotations

import numpy as np
import pytest
from interp_scenes import camera, combine, true_trace, wall_scene

from napari_imgreg import Intrinsics, Pose
from napari_imgreg.interpret.project import (
    Interpretation,
    ProjectionParams,
    densify,
    label_color,
    merge_interpretations,
    measure_features,
    project_interpretations,
    project_polyline,
)
from napari_imgreg.interpret.structural import normal_from_dip, vector_from_plunge_trend


def _draw(intr: Intrinsics, pose: Pose, xyz: np.ndarray) -> np.ndarray:
    """What a geologist draws: the true 3D trace as pixels in the photo."""
    return pose.project(intr, xyz)


def _distance_to_polyline(points: np.ndarray, line: np.ndarray) -> np.ndarray:
    """Distance of each point to a densely resampled polyline (metres)."""
    from scipy.spatial import cKDTree

    t = np.linspace(0, 1, 50)[:, None, None]
    dense = (line[:-1][None] * (1 - t) + line[1:][None] * t).reshape(-1, 3)
    return cKDTree(dense).query(points)[0]


def test_densify_keeps_vertices_about_one_sample_per_pixel():
    px = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 5.5]])
    s = densify(px, 1.0)
    assert np.allclose(s[0], px[0]) and np.allclose(s[-1], px[-1])
    assert any(np.allclose(p, px[1]) for p in s)
    steps = np.linalg.norm(np.diff(s, axis=0), axis=1)
    assert steps.max() <= 1.0 + 1e-9 and len(s) == 10 + 6 + 1
    ring = densify(px, 1.0, closed=True)
    assert np.allclose(ring[-1], px[0])


@pytest.mark.parametrize("dip,ddir", [(12.0, 200.0), (35.0, 60.0), (65.0, 100.0), (5.0, 330.0)])
def test_trace_on_relief_recovers_the_plane(dip, ddir):
    scene, X = wall_scene()
    intr, pose = camera()
    (trace,) = [t for t in true_trace(X, dip, ddir) if len(t) > 20]
    drawn = Interpretation("LineString", _draw(intr, pose, trace), {"label": "sandstone"})
    (f,) = project_interpretations(scene, intr, pose, [drawn], source="IMG_1.jpg")
    assert len(f.parts) == 1 and f.missed <= 2  # an end may graze the mesh border
    # About one ray per pixel, and the 3D line follows the relief.
    assert f.samples >= np.linalg.norm(np.diff(drawn.pixels, axis=0), axis=1).sum()
    assert np.percentile(_distance_to_polyline(f.points, trace), 95) < 0.05
    (m,) = measure_features([f])
    assert m.kind == "trace" and m.has_plane, m.note
    assert m.dip_deg == pytest.approx(dip, abs=0.5)
    assert abs((m.dip_direction_deg - ddir + 180) % 360 - 180) < 0.5
    assert m.planarity > 0.75


def test_straight_line_on_a_plane_recovers_plunge_and_trend(make_quad):
    # A planar slab dipping 40° toward 135°; a line within it plunging 25°.
    n = normal_from_dip(40.0, 135.0)
    strike = np.array([np.sin(np.radians(45.0)), np.cos(np.radians(45.0)), 0.0])
    down_dip = np.cross(n, strike)
    down_dip *= -np.sign(down_dip[2])
    # A direction in the plane plunging 25°: between strike and the dip line.
    a = np.arcsin(np.sin(np.radians(25.0)) / np.sin(np.radians(40.0)))
    d = np.cos(a) * strike + np.sin(a) * down_dip
    scene = make_quad([0, 0, 0], strike, down_dip, 40.0, 30.0)
    intr = Intrinsics(1000, 800, 900.0, 900.0, 499.5, 399.5)
    z = -n  # the camera looks straight down onto the slab
    x = np.cross(z, [0, 0, 1.0])
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    pose = Pose.from_center(R, 60.0 * n)
    xyz = np.array([-15.0, 15.0])[:, None] * d
    drawn = Interpretation("LineString", _draw(intr, pose, xyz), {"label": "fault"})
    (f,) = project_interpretations(scene, intr, pose, [drawn], source="IMG_2.jpg")
    (m,) = measure_features([f])
    want_plunge = np.degrees(np.arcsin(-d[2]))
    want_trend = np.degrees(np.arctan2(d[0], d[1])) % 360
    assert want_plunge == pytest.approx(25.0, abs=1e-6)
    assert m.plunge_deg == pytest.approx(want_plunge, abs=0.5)
    assert abs((m.trend_deg - want_trend + 180) % 360 - 180) < 0.5
    # A straight trace on a planar face defines no plane: the cells stay empty.
    assert m.dip_deg is None and m.dip_direction_deg is None and "no plane" in m.note
    # The polygon facet on the slab gives the slab's own dip / dip direction.
    ring = _draw(intr, pose, np.array([[-10, -10, 0], [10, -10, 0], [10, 10, 0], [-10, 10, 0.0]])
                 @ np.stack([strike, down_dip, n]))
    (facet,) = project_interpretations(
        scene, intr, pose, [Interpretation("Polygon", ring, {"label": "sandstone"})])
    assert facet.kind == "facet" and facet.ring_complete
    assert facet.patch_faces is not None and len(facet.patch_faces) >= 1
    (fm,) = measure_features([facet])
    assert fm.dip_deg == pytest.approx(40.0, abs=0.5)
    assert fm.dip_direction_deg == pytest.approx(135.0, abs=0.5)
    assert fm.plunge_deg is None and fm.trend_deg is None


def test_line_crossing_a_gap_is_split_not_bridged():
    scene, X = wall_scene(hole_x=(-3.0, 3.0))
    intr, pose = camera()
    (trace,) = [t for t in true_trace(X, 12.0, 200.0) if len(t) > 20]
    drawn = Interpretation("LineString", _draw(intr, pose, trace), {"label": "mudstone"})
    (f,) = project_interpretations(scene, intr, pose, [drawn])
    assert len(f.parts) == 2 and f.missed > 0
    left, right = sorted(f.parts, key=lambda p: p[:, 0].mean())
    assert left[:, 0].max() <= -3.0 + 1e-6 and right[:, 0].min() >= 3.0 - 1e-6
    for part in f.parts:  # no segment jumps the slot
        assert np.linalg.norm(np.diff(part, axis=0), axis=1).max() < 1.0


def test_line_over_an_occluding_ridge_is_split(make_box):
    wall, X = wall_scene()
    ridge = make_box([-4.0, -40.0, 0.0], [4.0, -34.0, 22.0])  # a pillar 35 m in front
    scene = combine(wall, ridge)
    intr, pose = camera()
    # Drawn across the pillar: left wall, pillar face, right wall.
    px = np.array([[200.0, 400.0], [1000.0, 400.0]])
    line = project_polyline(scene, intr, pose, px)
    parts = line.parts
    assert len(parts) == 3
    mid = parts[1]
    assert np.allclose(mid[:, 1], -40.0, atol=1e-3)  # the pillar's south face
    assert all(np.all(p[:, 1] > -10.0) for p in (parts[0], parts[2]))  # the wall behind
    for part in parts:
        assert np.linalg.norm(np.diff(part, axis=0), axis=1).max() < 1.0


def test_line_into_the_sky_ends_at_the_skyline():
    scene, _ = wall_scene()
    intr, pose = camera()
    px = np.array([[600.0, 600.0], [600.0, 0.0]])  # up the wall and past its top
    line = project_polyline(scene, intr, pose, px)
    assert len(line.parts) == 1 and (line.part < 0).sum() > 10
    assert line.parts[0][:, 2].max() <= 30.0 + 1e-6


def test_steep_but_continuous_surface_is_not_split(make_quad):
    # A steep ramp seen obliquely is continuous (not split); the grazing rule
    # only cuts where the surface would have to be seen within 5° of the ray.
    intr, pose = camera()
    steep = make_quad([0, 0, 15], [1, 0, 0], [0, np.sin(np.radians(70)), np.cos(np.radians(70))],
                      40, 20)
    line = project_polyline(steep, intr, pose, np.array([[600.0, 100.0], [600.0, 800.0]]))
    assert len(line.parts) == 1


def test_distortion_is_honoured():
    scene, X = wall_scene()
    intr, pose = camera(dist=(-0.12, 0.03, 0.0005, -0.0003, 0.0))
    target = X[30, 80]  # a grid vertex on the wall
    px = pose.project(intr, target[None])  # distorted pixel
    line = project_polyline(scene, intr, pose, np.vstack([px, px + [0.5, 0]]))
    assert np.linalg.norm(line.points[0] - target) < 1e-3


def test_engine_is_reused_and_sources_merge():
    scene, X = wall_scene()
    scene.build_engine()
    engine = scene.engine
    intr, pose_a = camera()
    pose_b = Pose.from_attitude(20.0, -2.0, 0.0, np.array([-30.0, -85.0, 15.0]))
    (trace,) = [t for t in true_trace(X, 30.0, 180.0) if len(t) > 20]
    sets = []
    for name, pose in (("IMG_A.jpg", pose_a), ("IMG_B.jpg", pose_b)):
        drawn = Interpretation("LineString", _draw(intr, pose, trace),
                               {"label": "sandstone", "id": "bed1"})
        sets.append(project_interpretations(scene, intr, pose, [drawn], source=name))
    assert scene.engine is engine  # the one engine, never rebuilt
    merged = merge_interpretations(*sets)
    assert [f.source for f in merged] == ["IMG_A.jpg", "IMG_B.jpg"]
    assert len({f.id for f in merged}) == 2
    # Both photos put the bed in the same place.
    for f in merged:
        assert np.percentile(_distance_to_polyline(f.points, trace), 95) < 0.05


def test_feature_off_the_surface_has_no_parts():
    scene, _ = wall_scene()
    intr, pose = camera()
    sky = Interpretation("LineString", np.array([[100.0, 5.0], [1100.0, 5.0]]), {"label": "fault"})
    (f,) = project_interpretations(scene, intr, pose, [sky])
    assert f.parts == [] and f.missed == f.samples
    assert measure_features([f]) == []


def test_label_colours():
    assert label_color("sandstone") == "#ffd400"
    assert label_color("mudstone") == "#8c8c8c"
    assert label_color("fault") == "#e31a1c"
    assert label_color("my-horizon") == label_color("my-horizon")
    assert label_color("fault", "#00ff00") == "#00ff00"


def test_projection_params_grazing_threshold(make_box):
    wall, _ = wall_scene()
    scene = combine(wall, make_box([-4.0, -40.0, 0.0], [4.0, -34.0, 22.0]))
    intr, pose = camera()
    px = np.array([[200.0, 400.0], [1000.0, 400.0]])
    # Disabling both rules bridges the occlusion: proof the rules do the splitting.
    off = ProjectionParams(grazing_deg=1e-6, jump_contrast=0.0)
    assert len(project_polyline(scene, intr, pose, px, params=off).parts) == 1
    assert vector_from_plunge_trend(0.0, 90.0) == pytest.approx([1.0, 0.0, 0.0])

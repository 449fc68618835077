"""The sun-shift nuisance of ``benchmarks/_sunshift.py`` (issue 13's diagnostic,
not used by the pipeline): known b and pose recovered."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from napari_imgreg.camera import Intrinsics, Pose
from napari_imgreg.registration.pose import estimate_pose

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"
if not (BENCH / "_sunshift.py").is_file():
    pytest.skip("benchmarks/_sunshift.py not present", allow_module_level=True)
sys.path.insert(0, str(BENCH))
from _sunshift import solve_pose_sun_shift, sun_shift_directions  # noqa: E402


def _scene(seed: int = 0):
    """A cliff face (x-z plane at y = 0), a ledge and ground in front: three
    orientations, so that a displacement along each one's tangent plane is no
    single camera move. Camera 60 m south, looking north."""
    rng = np.random.default_rng(seed)
    face = np.column_stack([rng.uniform(-30, 30, 300), np.zeros(300), rng.uniform(0, 40, 300)])
    ground = np.column_stack([rng.uniform(-30, 30, 200), rng.uniform(-25, -2, 200),
                              np.zeros(200)])
    ledge = np.column_stack([rng.uniform(-20, 20, 100), rng.uniform(-6, 0, 100),
                             np.full(100, 18.0)])
    xyz = np.vstack([face, ground, ledge])
    normals = np.vstack([np.tile([0.0, -1.0, 0.0], (300, 1)), np.tile([0.0, 0.0, 1.0], (300, 1))])
    intr = Intrinsics(1632, 1224, 1400.0, 1400.0, 815.5, 611.5)
    R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # looks along +y
    pose = Pose.from_center(R, np.array([0.0, -60.0, 15.0]))
    return intr, pose, xyz, normals


def test_directions_lie_in_the_tangent_plane_away_from_the_sun():
    sun = np.array([0.6, -0.6, 0.3])
    sun /= np.linalg.norm(sun)
    n = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0]])
    a = sun_shift_directions(n, sun, "tangent")
    assert np.allclose(np.linalg.norm(a, axis=1), 1.0)
    assert np.allclose(np.einsum("ij,ij->i", a, n), 0.0)
    assert (a @ sun < 0).all()
    # Shadow factor: cot of the sun's elevation above each surface, clipped.
    f = np.linalg.norm(sun_shift_directions(n, sun, "shadow", max_factor=10.0), axis=1)
    sn = n @ sun
    assert f == pytest.approx(np.sqrt(1 - sn ** 2) / sn)
    assert np.linalg.norm(sun_shift_directions(n, sun, "shadow", max_factor=0.5), axis=1) \
        == pytest.approx([0.5, 0.5])


@pytest.mark.parametrize("mode", ["tangent", "shadow"])
def test_pose_and_b_recovered_from_a_synthetic_block_field(mode):
    intr, truth, xyz, normals = _scene()
    sun = np.array([0.7, -0.5, 0.35])
    sun /= np.linalg.norm(sun)
    dirs = sun_shift_directions(normals, sun, mode)
    b_true = 0.4
    rng = np.random.default_rng(1)
    uv = truth.project(intr, xyz + b_true * dirs) + rng.normal(0, 0.2, (len(xyz), 2))
    # Started, as a round is, from the pose alone by RANSAC EPnP.
    est = estimate_pose(intr, xyz, uv)
    assert est.ok
    start = est.pose
    fit = solve_pose_sun_shift(intr, start, xyz, uv, dirs)
    assert fit.b == pytest.approx(b_true, abs=0.05)
    err = np.linalg.norm(fit.pose.project(intr, xyz) - truth.project(intr, xyz), axis=1)
    assert np.median(err) < 0.3
    assert fit.inliers.all()
    # The pose alone absorbs the shift into a wrong pose.
    alone = solve_pose_sun_shift(intr, start, xyz, uv, dirs, fix_b=0.0)
    err0 = np.linalg.norm(alone.pose.project(intr, xyz) - truth.project(intr, xyz), axis=1)
    assert np.median(err0) > 3 * np.median(err)


def test_b_on_one_plane_is_confounded_with_the_camera():
    intr, truth, xyz, normals = _scene()
    face = slice(0, 300)
    sun = np.array([0.7, -0.5, 0.35])
    sun /= np.linalg.norm(sun)
    dirs = sun_shift_directions(normals[face], sun, "tangent")
    uv = truth.project(intr, xyz[face] + 0.4 * dirs) + \
        np.random.default_rng(2).normal(0, 0.2, (300, 2))
    fit = solve_pose_sun_shift(intr, estimate_pose(intr, xyz[face], uv).pose, xyz[face], uv,
                               dirs)
    assert not fit.correlation < 0.999  # 1, or NaN: singular

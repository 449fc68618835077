"""Known-answer tests for :mod:`napari_imgreg.render` and ``Scene`` ray casting.

Every expected value is computed analytically in float64 from the contract's
camera model (pixel centres at integer coordinates, ``X_cam = R X + t``).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from napari_imgreg.camera import Intrinsics, Pose
from napari_imgreg.render import render
from napari_imgreg.scene import Scene

MM = 1e-3
W, H = 160, 120
INTR = Intrinsics(W, H, 110.0, 112.0, 80.7, 58.2)

# ---------------------------------------------------------------------------
# analytic helpers
# ---------------------------------------------------------------------------


def pixel_grid(intr):
    cols, rows = np.meshgrid(np.arange(intr.width, dtype=float), np.arange(intr.height, dtype=float))
    return cols, rows


def pinhole_rays(intr, pose):
    """World directions (H, W, 3) with camera-z component 1 (undistorted)."""
    cols, rows = pixel_grid(intr)
    d_cam = np.stack(
        [(cols - intr.cx) / intr.fx, (rows - intr.cy) / intr.fy, np.ones_like(cols)], axis=-1
    )
    return d_cam @ pose.R  # R.T @ d_cam for each pixel


def exact_undistorted_rays(intr, pose):
    """Like :func:`pinhole_rays` but through the distorted pixels, inverted to
    machine precision (iterated OpenCV undistortion)."""
    cols, rows = pixel_grid(intr)
    px = np.stack([cols.ravel(), rows.ravel()], axis=1).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    und = cv2.undistortPointsIter(px, intr.K, intr.dist_coeffs, None, None, crit).reshape(-1, 2)
    d_cam = np.c_[und, np.ones(len(und))].reshape(intr.height, intr.width, 3)
    return d_cam @ pose.R


def ray_plane(C, d, p0, n):
    """Hit parameters t (C + t d on the plane through p0 with normal n)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return ((np.asarray(p0) - C) @ n) / (d @ n)


def ray_box(C, d, lo, hi):
    """Slab method. Returns (t_near, axis of the entry face, hit)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (np.asarray(lo) - C) / d
        t2 = (np.asarray(hi) - C) / d
    tmin = np.minimum(t1, t2)
    tmax = np.maximum(t1, t2)
    tnear = tmin.max(axis=-1)
    tfar = tmax.min(axis=-1)
    axis = tmin.argmax(axis=-1)
    hit = (tnear <= tfar) & (tfar > 0)
    return tnear, axis, hit


def bilinear(tex, u, v):
    """Bilinear sample of ``tex`` at UV with texel centres at (i + 0.5) / size,
    v = 0 at the bottom row, edges replicated; float64."""
    th, tw = tex.shape[:2]
    x = u * tw - 0.5
    y = (1.0 - v) * th - 0.5
    x0 = np.floor(x).astype(int)
    y0 = np.floor(y).astype(int)
    fx = (x - x0)[..., None]
    fy = (y - y0)[..., None]
    xa, xb = np.clip(x0, 0, tw - 1), np.clip(x0 + 1, 0, tw - 1)
    ya, yb = np.clip(y0, 0, th - 1), np.clip(y0 + 1, 0, th - 1)
    t = tex.astype(float)
    top = t[ya, xa] * (1 - fx) + t[ya, xb] * fx
    bot = t[yb, xa] * (1 - fx) + t[yb, xb] * fx
    return top * (1 - fy) + bot * fy


# ---------------------------------------------------------------------------
# a tilted textured plane
# ---------------------------------------------------------------------------

# The plane: strike along axis A, dipping 55° toward azimuth 200°; a 60 × 40 m
# rectangle centred 50 m from the camera, so part of the image misses it.
DIP, DIP_DIR = 55.0, 200.0
_dd = math.radians(DIP_DIR)
_dip = math.radians(DIP)
PLANE_A = np.array([math.cos(_dd), -math.sin(_dd), 0.0])  # strike (horizontal)
PLANE_B = np.array(
    [-math.sin(_dd) * math.cos(_dip), -math.cos(_dd) * math.cos(_dip), math.sin(_dip)]
)  # up-dip
PLANE_N = np.cross(PLANE_A, PLANE_B)
PLANE_C = np.array([4.0, 3.0, 10.0])
HALF_A, HALF_B = 30.0, 20.0
CAM_C = PLANE_C + 50.0 * PLANE_N / np.linalg.norm(PLANE_N) * np.array([1, 1, 1]) + [6.0, -4.0, 3.0]


def plane_pose():
    """Camera 50 m off the plane, roughly facing it, with an odd attitude."""
    look = PLANE_C - CAM_C
    trend = math.degrees(math.atan2(look[0], look[1])) + 7.0
    plunge = math.degrees(math.asin(-look[2] / np.linalg.norm(look))) - 4.0
    return Pose.from_attitude(trend, plunge, 12.0, CAM_C)


def plane_truth(intr, pose, d=None, margin=MM):
    """Analytic hit points, UV and the unambiguous-pixel mask for the plane."""
    C = pose.center
    d = pinhole_rays(intr, pose) if d is None else d
    n = PLANE_N / np.linalg.norm(PLANE_N)
    t = ray_plane(C, d, PLANE_C, n)
    X = C + t[..., None] * d
    s = (X - PLANE_C) @ PLANE_A
    q = (X - PLANE_C) @ PLANE_B
    front = t > 0
    inside = front & (np.abs(s) <= HALF_A) & (np.abs(q) <= HALF_B)
    # pixels whose ray passes within `margin` of the rectangle's border are
    # left out of the mask comparison (float32 rays may fall either side)
    sure = ~front | (np.abs(np.abs(s) - HALF_A) > margin) & (np.abs(np.abs(q) - HALF_B) > margin)
    sure |= front & ((np.abs(s) > HALF_A + margin) | (np.abs(q) > HALF_B + margin))
    uv = np.stack([(s + HALF_A) / (2 * HALF_A), (q + HALF_B) / (2 * HALF_B)], axis=-1)
    return X, t, inside, sure, uv, n


@pytest.fixture
def gradient_texture():
    """64 × 48 texture: R grows with the column, G with the row *from the
    bottom*, B constant — a texel's colour tells where it is."""
    th, tw = 48, 64
    col = np.arange(tw)
    row = np.arange(th)
    tex = np.zeros((th, tw, 3), np.uint8)
    tex[..., 0] = (col * 4 + 2)[None, :]
    tex[..., 1] = ((th - 1 - row) * 5 + 3)[:, None]
    tex[..., 2] = 77
    return tex


@pytest.fixture
def plane_scene(make_quad, gradient_texture):
    return make_quad(PLANE_C, PLANE_A, PLANE_B, HALF_A, HALF_B, texture=gradient_texture)


def test_plane_geometry_exact(plane_scene):
    pose = plane_pose()
    res = render(plane_scene, INTR, pose)
    X, t, inside, sure, _, n = plane_truth(INTR, pose)
    assert res.rgb.shape == (H, W, 3) and res.rgb.dtype == np.uint8
    assert res.xyz.shape == (H, W, 3) and res.depth.shape == (H, W)
    assert res.normal.shape == (H, W, 3) and res.face_id.shape == (H, W)
    # the scene is framed so both hits and misses occur
    assert 0.2 < inside.mean() < 0.9
    assert (sure.sum() / sure.size) > 0.95
    np.testing.assert_array_equal(res.mask[sure], inside[sure])
    hit = res.mask
    err = np.linalg.norm(res.xyz[hit].astype(float) - X[hit], axis=1)
    assert err.max() <= 1 * MM, f"max 3D error {err.max() * 1000:.3f} mm"
    # depth is the camera-z of the analytic point (= t, since d_cam has z = 1)
    zc = pose.transform(X[hit])[:, 2]
    np.testing.assert_allclose(zc, t[hit], rtol=1e-9)
    np.testing.assert_allclose(res.depth[hit], zc, rtol=0, atol=1 * MM)
    # normal: the plane's, turned toward the camera
    toward = n if (pose.center - PLANE_C) @ n > 0 else -n
    np.testing.assert_allclose(res.normal[hit], np.broadcast_to(toward, (hit.sum(), 3)), atol=1e-5)
    # misses
    miss = ~res.mask
    assert np.isnan(res.xyz[miss]).all() and np.isnan(res.depth[miss]).all()
    assert (res.face_id[miss] == -1).all() and (res.face_id[hit] >= 0).all()
    assert (res.normal[miss] == 0).all()
    assert res.coverage == pytest.approx(res.mask.mean())
    assert res.shape == (H, W)
    assert res.intrinsics == INTR
    np.testing.assert_array_equal(res.cam_from_world.R, pose.R)


def test_plane_seen_from_behind_normal_turns_to_camera(make_quad):
    # plane y = 50 spanning ±100 m, wound so its geometric normal is +Y (away
    # from a camera south of it): the rendered normal must be -Y.
    scene = make_quad([0.0, 50.0, 0.0], [0, 0, 1], [1, 0, 0], 100.0, 100.0)
    np.testing.assert_allclose(scene.face_array("normals")[0], [0, 1, 0], atol=1e-7)
    pose = Pose.from_attitude(10.0, -10.0, 15.0, [3.0, -10.0, 2.0])
    res = render(scene, INTR, pose, mode="normal")
    d = pinhole_rays(INTR, pose)
    t = ray_plane(pose.center, d, [0, 50, 0], np.array([0.0, 1.0, 0.0]))
    X = pose.center + t[..., None] * d
    assert res.mask.all()
    assert np.abs(res.xyz - X).max() <= 1 * MM
    np.testing.assert_allclose(res.normal.reshape(-1, 3), np.tile([0, -1, 0], (H * W, 1)), atol=1e-6)
    # normal mode encodes n * 127.5 + 127.5
    np.testing.assert_array_equal(res.rgb[5, 7], [128, 0, 128])


def test_plane_texture_gradient_colours(plane_scene, gradient_texture):
    pose = plane_pose()
    res = render(plane_scene, INTR, pose)  # auto -> colour from the texture
    X, t, inside, sure, uv, _ = plane_truth(INTR, pose, margin=0.05)
    ok = inside & sure & res.mask
    expected = bilinear(gradient_texture, uv[..., 0], uv[..., 1])
    diff = np.abs(res.rgb[ok].astype(float) - expected[ok])
    assert diff.max() <= 2.0, f"max colour error {diff.max()}"
    # the texture spans a range of colours across the image (not a constant)
    assert np.ptp(res.rgb[ok][:, 0]) > 60 and np.ptp(res.rgb[ok][:, 1]) > 60
    assert (res.rgb[~res.mask] == 0).all()


def test_plane_texture_checkerboard_colours(make_quad):
    th, tw, cell = 40, 56, 4
    rr, cc = np.mgrid[0:th, 0:tw]
    on = ((rr // cell + cc // cell) % 2).astype(bool)
    tex = np.where(on[..., None], np.array([220, 30, 90], np.uint8), np.array([20, 200, 160], np.uint8))
    tex[: 2 * cell, : 2 * cell] = [255, 255, 0]  # marks the top-left corner (v = 1, u = 0)
    scene = make_quad(PLANE_C, PLANE_A, PLANE_B, HALF_A, HALF_B, texture=tex)
    pose = plane_pose()
    res = render(scene, INTR, pose, background=(1, 2, 3))
    _, _, inside, sure, uv, _ = plane_truth(INTR, pose, margin=0.05)
    ok = inside & sure & res.mask
    expected = bilinear(tex, uv[..., 0], uv[..., 1])
    # texel-space position: bilinear is constant away from cell edges
    x = uv[..., 0] * tw - 0.5
    y = (1 - uv[..., 1]) * th - 0.5
    flat = (
        (np.mod(x, cell) > 0.05) & (np.mod(x, cell) < cell - 1 - 0.05)
        & (np.mod(y, cell) > 0.05) & (np.mod(y, cell) < cell - 1 - 0.05)
    )
    interior = ok & flat
    assert interior.sum() > 0.3 * ok.sum()
    diff = np.abs(res.rgb[interior].astype(float) - expected[interior])
    assert diff.max() <= 2.0
    # across cell edges only sub-texel interpolation error remains
    diff_all = np.abs(res.rgb[ok].astype(float) - expected[ok])
    assert diff_all.max() <= 8.0
    # the yellow marker shows where u is small and v is large
    yellow = (res.rgb == [255, 255, 0]).all(axis=-1)
    assert yellow.any()
    assert (uv[yellow][:, 0] < 2.5 * cell / tw).all() and (uv[yellow][:, 1] > 1 - 2.5 * cell / th).all()
    assert (res.rgb[~res.mask] == [1, 2, 3]).all()


def test_plane_scale_half(plane_scene):
    pose = plane_pose()
    res = render(plane_scene, INTR, pose, scale=0.5)
    half = INTR.scaled(0.5)
    assert res.shape == (H // 2, W // 2)
    assert res.intrinsics == half
    assert (half.width, half.height) == (W // 2, H // 2)
    assert half.fx == INTR.fx / 2 and half.cx == (INTR.cx + 0.5) / 2 - 0.5
    X, _, inside, sure, _, _ = plane_truth(half, pose)
    np.testing.assert_array_equal(res.mask[sure], inside[sure])
    hit = res.mask
    assert np.abs(res.xyz[hit] - X[hit]).max() <= 1 * MM
    # a half-resolution pixel p sees what the full image sees at 2p + 0.5
    full = render(plane_scene, INTR, pose)
    both = res.mask & full.mask[::2, ::2] & full.mask[1::2, 1::2]
    mid = (full.xyz[::2, ::2].astype(float) + full.xyz[1::2, 1::2]) / 2
    # (midpoint of two pixel centres on a plane: exact up to perspective)
    assert np.abs(res.xyz[both] - mid[both]).max() < 0.05


def test_plane_with_distortion(plane_scene):
    dist = (-0.12, 0.03, 0.0005, -0.0003, 0.0)
    intr = Intrinsics(W, H, 130.0, 128.0, 80.3, 58.9, dist)
    pose = plane_pose()
    res = render(plane_scene, intr, pose)
    hit = res.mask
    assert hit.mean() > 0.2
    # the surface point of each pixel reprojects (with distortion) onto it
    cols, rows = pixel_grid(intr)
    px = np.stack([cols, rows], axis=-1)[hit]
    Xc = pose.transform(res.xyz[hit].astype(float))
    cvp, _ = cv2.projectPoints(Xc.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), intr.K, intr.dist_coeffs)
    reproj = np.linalg.norm(cvp.reshape(-1, 2) - px, axis=1)
    assert reproj.max() < 0.01, f"max reprojection error {reproj.max():.4f} px"
    # ... and equals the analytic point along the exactly undistorted ray
    X, _, inside, sure, _, _ = plane_truth(intr, pose, d=exact_undistorted_rays(intr, pose))
    np.testing.assert_array_equal(res.mask[sure], inside[sure])
    assert np.linalg.norm(res.xyz[hit] - X[hit], axis=1).max() <= 1 * MM
    # the distortion is visible: the undistorted model would be far off
    X0, *_ = plane_truth(intr, pose)
    assert np.nanmax(np.linalg.norm(res.xyz[hit] - X0[hit], axis=1)) > 0.5


def test_plane_with_wide_angle_distortion(make_quad):
    # Monotonic (invertible) radial distortion over the whole frame, as on
    # action cameras and wide drone lenses; the plane y = 50 fills the frame.
    intr = Intrinsics(W, H, 100.0, 100.0, 79.5, 59.5, (-0.2, 0.03, 0.0, 0.0, 0.0))
    r = np.linspace(0, 2, 2001)
    assert (np.diff(r * (1 - 0.2 * r**2 + 0.03 * r**4)) > 0).all()
    scene = make_quad([0.0, 50.0, 0.0], [1, 0, 0], [0, 0, 1], 500.0, 500.0)
    pose = Pose.from_attitude(10.0, 5.0, -8.0, [3.0, -2.0, 1.0])
    res = render(scene, intr, pose)
    hit = res.mask
    assert hit.all()
    cols, rows = pixel_grid(intr)
    px = np.stack([cols, rows], axis=-1)[hit]
    reproj = np.linalg.norm(pose.project(intr, res.xyz[hit].astype(float)) - px, axis=1)
    assert reproj.max() < 0.01, f"max reprojection error {reproj.max():.4f} px"


def test_render_accepts_intrinsics_rebuilt_from_dict(plane_scene):
    intr = Intrinsics.from_dict(INTR.to_dict())
    res = render(plane_scene, intr, plane_pose())
    ref = render(plane_scene, INTR, plane_pose())
    np.testing.assert_array_equal(res.rgb, ref.rgb)


def test_render_accepts_intrinsics_built_from_to_dict_kwargs(plane_scene):
    intr = Intrinsics(**Intrinsics(W, H, 130.0, 128.0, 80.3, 58.9, (-0.05, 0, 0, 0, 0)).to_dict())
    res = render(plane_scene, intr, plane_pose())
    assert res.mask.any()


def test_threaded_render_equals_single_thread(plane_scene, monkeypatch):
    # > 100 000 pixels takes the multi-block path
    intr = Intrinsics(400, 300, 275.0, 275.0, 199.5, 149.5)
    pose = plane_pose()
    monkeypatch.setenv("NAPARI_IMGREG_THREADS", "1")
    one = render(plane_scene, intr, pose)
    monkeypatch.setenv("NAPARI_IMGREG_THREADS", "3")
    many = render(plane_scene, intr, pose)
    # identical up to Embree's packet grouping (a ray on a shared edge may
    # pick either triangle)
    assert (one.face_id == many.face_id).mean() > 0.999
    np.testing.assert_array_equal(one.mask, many.mask)
    assert np.abs(one.xyz[one.mask] - many.xyz[one.mask]).max() < 1e-4
    assert np.abs(one.rgb.astype(int) - many.rgb).max() <= 1
    X, *_ = plane_truth(intr, pose)
    assert np.abs(many.xyz[many.mask] - X[many.mask]).max() <= 1 * MM


# ---------------------------------------------------------------------------
# a closed box
# ---------------------------------------------------------------------------

BOX_LO = np.array([-5.0, -4.0, 0.0])
BOX_HI = np.array([8.0, 6.0, 7.0])


def box_pose():
    C = np.array([-15.0, -19.0, 14.0])
    look = (BOX_LO + BOX_HI) / 2 - C
    trend = math.degrees(math.atan2(look[0], look[1]))
    plunge = math.degrees(math.asin(-look[2] / np.linalg.norm(look)))
    return Pose.from_attitude(trend - 3.0, plunge + 2.0, -9.0, C)


def test_box_outward_normals(make_box):
    scene = make_box(BOX_LO, BOX_HI)
    assert scene.n_faces == 12
    centroids = scene.vertices[scene.faces].mean(axis=1)
    outward = centroids - (BOX_LO + BOX_HI) / 2
    assert (np.einsum("ij,ij->i", scene.face_array("normals"), outward) > 0).all()


def test_box_geometry_exact(make_box):
    scene = make_box(BOX_LO, BOX_HI)
    pose = box_pose()
    res = render(scene, INTR, pose)
    C = pose.center
    d = pinhole_rays(INTR, pose)
    t, axis, inside = ray_box(C, d, BOX_LO, BOX_HI)
    _, _, hit_big = ray_box(C, d, BOX_LO - MM, BOX_HI + MM)
    _, _, hit_small = ray_box(C, d, BOX_LO + MM, BOX_HI - MM)
    sure = hit_big == hit_small
    assert 0.1 < inside.mean() < 0.9
    np.testing.assert_array_equal(res.mask[sure], inside[sure])
    hit = res.mask
    X = C + t[..., None] * d
    err = np.linalg.norm(res.xyz[hit].astype(float) - X[hit], axis=1)
    assert err.max() <= 1 * MM, f"max 3D error {err.max() * 1000:.3f} mm"
    np.testing.assert_allclose(res.depth[hit], t[hit], atol=1 * MM)
    # three faces are visible from this oblique corner view
    assert len(np.unique(axis[hit & sure])) == 3
    # normal = the entry face's outward normal
    expect_n = np.zeros_like(X)
    ii = np.nonzero(hit)
    expect_n[ii + (axis[hit],)] = -np.sign(d[ii + (axis[hit],)])
    ok = hit & sure
    np.testing.assert_allclose(res.normal[ok], expect_n[ok], atol=1e-6)
    # the triangle named by face_id contains the point
    tri = scene.vertices[scene.faces[res.face_id[hit]]]
    P = res.xyz[hit].astype(float)
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    nrm = np.cross(e1, e2)
    assert np.abs(np.einsum("ij,ij->i", P - tri[:, 0], nrm) / np.linalg.norm(nrm, axis=1)).max() < MM
    # barycentric coordinates in [0, 1] (up to a millimetre on 10 m edges)
    G = np.stack([e1, e2], axis=-1)  # (N, 3, 2)
    lam, *_ = zip(*[np.linalg.lstsq(g, p - a, rcond=None) for g, p, a in zip(G, P, tri[:, 0])])
    lam = np.array(lam)
    tol = 1e-4
    assert (lam >= -tol).all() and (lam.sum(axis=1) <= 1 + tol).all()
    # misses
    miss = ~res.mask
    assert miss.any()
    assert np.isnan(res.xyz[miss]).all() and np.isnan(res.depth[miss]).all()
    assert (res.face_id[miss] == -1).all()


def test_box_from_inside_sees_the_far_walls(make_box):
    scene = make_box(BOX_LO, BOX_HI)
    C = np.array([1.0, 0.5, 2.0])
    pose = Pose.from_attitude(75.0, 20.0, 5.0, C)
    res = render(scene, INTR, pose)
    assert res.mask.all()
    d = pinhole_rays(INTR, pose)
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (BOX_LO - C) / d
        t2 = (BOX_HI - C) / d
    t = np.maximum(t1, t2).min(axis=-1)  # exit distance
    X = C + t[..., None] * d
    assert np.abs(res.xyz - X).max() <= 1 * MM


# ---------------------------------------------------------------------------
# colour modes
# ---------------------------------------------------------------------------


def _rgb_triangle():
    V = np.array([[-20.0, 40.0, -15.0], [20.0, 40.0, -15.0], [0.0, 40.0, 20.0]])
    colours = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255]], np.uint8)
    return Scene(V, np.array([[0, 1, 2]]), vertex_colors=colours), V, colours


def test_vertex_colours_interpolate_barycentrically():
    scene, V, colours = _rgb_triangle()
    pose = Pose.from_attitude(8.0, 3.0, -6.0, [1.0, 0.0, 0.5])
    res = render(scene, INTR, pose)  # auto -> vertex colours
    d = pinhole_rays(INTR, pose)
    t = ray_plane(pose.center, d, V[0], np.array([0.0, 1.0, 0.0]))
    X = pose.center + t[..., None] * d
    # barycentrics in the x-z plane
    M = np.array([[V[0, 0], V[1, 0], V[2, 0]], [V[0, 2], V[1, 2], V[2, 2]], [1.0, 1.0, 1.0]])
    lam = np.linalg.solve(M, np.stack([X[..., 0], X[..., 2], np.ones_like(t)], axis=-1)[..., None])[..., 0]
    inside = (lam > 1e-3).all(axis=-1)
    outside = (lam < -1e-3).any(axis=-1)
    assert inside.any() and outside.any()
    assert res.mask[inside].all() and not res.mask[outside].any()
    expected = lam @ colours.astype(float)
    diff = np.abs(res.rgb[inside].astype(float) - expected[inside])
    assert diff.max() <= 1.0
    assert np.abs(res.xyz[res.mask] - X[res.mask]).max() <= 1 * MM


def test_untextured_auto_is_shaded_grey():
    V = np.array([[-100.0, 50.0, -100.0], [100.0, 50.0, -100.0], [100.0, 50.0, 100.0], [-100.0, 50.0, 100.0]])
    scene = Scene(V, np.array([[0, 1, 2], [0, 2, 3]]))
    pose = Pose.from_attitude(10.0, 5.0, 3.0, [0.0, 0.0, 0.0])
    light = np.array([0.3, -1.0, 0.5])
    res = render(scene, INTR, pose, light_direction=light, ambient=0.2)
    assert res.mask.all()
    n = np.array([0.0, -1.0, 0.0])  # toward the camera
    shade = 0.2 + 0.8 * max(0.0, n @ (light / np.linalg.norm(light)))
    expected = math.floor(180.0 * shade + 0.5)
    assert (res.rgb == expected).all()
    # light from behind the surface: ambient only
    res = render(scene, INTR, pose, light_direction=-light, ambient=0.2)
    assert (res.rgb == math.floor(180.0 * 0.2 + 0.5)).all()
    # explicit modes
    assert (render(scene, INTR, pose, mode="color").rgb == 180).all()
    shaded = render(scene, INTR, pose, mode="shaded", light_direction=light, ambient=0.2)
    assert (shaded.rgb == expected).all()
    # default light: over the photographer's shoulder, so a facing wall is lit
    default = render(scene, INTR, pose)
    assert 180 * 0.35 < default.rgb.mean() <= 180


def test_color_shaded_multiplies_texture(plane_scene, gradient_texture):
    pose = plane_pose()
    light = pose.center - PLANE_C
    colour = render(plane_scene, INTR, pose, mode="color")
    both = render(plane_scene, INTR, pose, mode="color_shaded", light_direction=light, ambient=0.5)
    n = PLANE_N / np.linalg.norm(PLANE_N)
    n = n if light @ n > 0 else -n
    shade = 0.5 + 0.5 * (n @ (light / np.linalg.norm(light)))
    m = colour.mask
    np.testing.assert_allclose(both.rgb[m].astype(float), colour.rgb[m] * shade, atol=1.0)


def test_background_and_bad_mode():
    scene, *_ = _rgb_triangle()
    pose = Pose.from_attitude(0.0, 0.0, 0.0, [0.0, 0.0, 0.0])
    res = render(scene, INTR, pose, background=(10, 20, 30))
    assert (res.rgb[~res.mask] == [10, 20, 30]).all()
    sky = render(scene, INTR, Pose.from_attitude(180.0, 0.0, 0.0, [0.0, 0.0, 0.0]), background=(9, 9, 9))
    assert not sky.mask.any() and (sky.rgb == 9).all() and np.isnan(sky.xyz).all()
    with pytest.raises(ValueError):
        render(scene, INTR, pose, mode="wireframe")


# ---------------------------------------------------------------------------
# Scene.cast_rays
# ---------------------------------------------------------------------------


def test_cast_rays_hits_misses_and_max_distance(make_quad):
    scene = make_quad([0.0, 50.0, 0.0], [1, 0, 0], [0, 0, 1], 100.0, 100.0)
    rng = np.random.default_rng(0)
    origins = np.c_[rng.uniform(-20, 20, 200), rng.uniform(-10, 10, 200), rng.uniform(-5, 5, 200)]
    dirs = np.c_[rng.uniform(-0.5, 0.5, 200), np.ones(200), rng.uniform(-0.5, 0.5, 200)]
    dirs[:20, 1] = -1.0  # pointing away: misses
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    hits = scene.cast_rays(origins, dirs)
    assert hits.distance.dtype == np.float32 and hits.face_id.dtype == np.int32
    t = (50.0 - origins[:, 1]) / dirs[:, 1]
    expect_hit = t > 0
    np.testing.assert_array_equal(hits.hit, expect_hit)
    np.testing.assert_allclose(hits.distance[expect_hit], t[expect_hit], rtol=1e-5)
    assert np.isinf(hits.distance[~expect_hit]).all()
    assert (hits.face_id[~expect_hit] == -1).all()
    assert set(np.unique(hits.face_id[expect_hit])) <= {0, 1}
    pts = scene.surface_points(hits)
    np.testing.assert_allclose(
        pts[expect_hit], origins[expect_hit] + t[expect_hit, None] * dirs[expect_hit], atol=MM
    )
    np.testing.assert_allclose(
        pts[expect_hit],
        origins[expect_hit] + hits.distance[expect_hit, None].astype(float) * dirs[expect_hit],
        atol=MM,
    )
    np.testing.assert_allclose(pts[expect_hit, 1], 50.0, atol=1e-5)
    assert np.isnan(pts[~expect_hit]).all()
    # max_distance: scalar and per ray
    far = scene.cast_rays(origins, dirs, max_distance=float(t[expect_hit].min()) - 0.01)
    assert not far.hit.any()
    limit = np.where(np.arange(200) % 2 == 0, t + 0.01, t - 0.01)
    lim = scene.cast_rays(origins, dirs, max_distance=limit)
    np.testing.assert_array_equal(lim.hit, expect_hit & (np.arange(200) % 2 == 0))


def test_cast_rays_single_origin_broadcasts(make_quad):
    scene = make_quad([0.0, 50.0, 0.0], [1, 0, 0], [0, 0, 1], 10.0, 10.0)
    d = np.array([[0.0, 1.0, 0.0], [0.1, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.15]])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    origin = np.array([0.0, 0.0, 0.0])
    hits = scene.cast_rays(origin, d)
    # 50 m ahead the quad spans ±10 m: tan 45° and (0.1, 0.15 -> 5, 7.5 m) ...
    np.testing.assert_array_equal(hits.hit, [True, True, False, True])
    pts = scene.surface_points(hits)
    np.testing.assert_allclose(pts[hits.hit], [[0, 50, 0], [5, 50, 0], [0, 50, 7.5]], atol=1e-4)


def test_cast_rays_threaded_matches(make_box, monkeypatch):
    scene = make_box(BOX_LO, BOX_HI)
    rng = np.random.default_rng(1)
    n = 120_000
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    origin = np.array([1.0, 0.0, 3.0])  # inside: every ray hits a wall
    monkeypatch.setenv("NAPARI_IMGREG_THREADS", "1")
    one = scene.cast_rays(origin, d)
    monkeypatch.setenv("NAPARI_IMGREG_THREADS", "2")
    two = scene.cast_rays(origin, d)
    np.testing.assert_allclose(one.distance, two.distance, rtol=1e-6)
    assert (one.face_id == two.face_id).mean() > 0.999
    assert one.hit.all()
    with np.errstate(divide="ignore"):
        t = np.maximum((BOX_LO - origin) / d, (BOX_HI - origin) / d).min(axis=1)
    np.testing.assert_allclose(one.distance, t, rtol=1e-5, atol=1e-5)

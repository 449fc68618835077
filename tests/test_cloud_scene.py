"""The point-cloud scene and its splat renderer, against known answers.

Small synthetic clouds sampled at random from known planes: a tilted square
in front of a larger back plane, seen by a pinhole camera whose every pixel
has an analytic depth.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from napari_imgreg.camera import Intrinsics, Pose
from napari_imgreg.cloud import CloudParams, CloudScene
from napari_imgreg.errors import InputError
from napari_imgreg.render import RenderResult
from napari_imgreg.render_points import SplatParams, splat_cloud

W, H, F = 200, 150, 200.0
INTR = Intrinsics(W, H, F, F, (W - 1) / 2, (H - 1) / 2)
# Looking straight down (-Z) from 5 m; camera x = +X, y = -Y.
POSE = Pose.from_center(np.diag([1.0, -1.0, -1.0]), np.array([0.1, -0.05, 5.0]))

# Back plane z = 0 over [-2.5, 2.5]²; front square on z = 1 + 0.2 x - 0.1 y
# over [-0.8, 0.8]² (about 3.9–4.2 m from the camera).
BACK_HALF, FRONT_HALF = 2.5, 0.8
FRONT_N = np.array([-0.2, 0.1, 1.0]) / np.linalg.norm([-0.2, 0.1, 1.0])


def _front_z(x, y):
    return 1.0 + 0.2 * x - 0.1 * y


@pytest.fixture(scope="module")
def planes():
    rng = np.random.default_rng(7)
    nb, nf = 50_000, 16_000  # ~2.2 cm and ~1.3 cm mean spacing: < 1 px at 4–5 m
    xb, yb = rng.uniform(-BACK_HALF, BACK_HALF, (2, nb))
    xf, yf = rng.uniform(-FRONT_HALF, FRONT_HALF, (2, nf))
    xyz = np.concatenate([np.stack([xb, yb, np.zeros(nb)], 1),
                          np.stack([xf, yf, _front_z(xf, yf)], 1)])
    intensity = np.concatenate([np.full(nb, 0.2), np.full(nf, 0.9)])
    scene = CloudScene(xyz, intensity=intensity, name="planes",
                       viewpoints=np.array([[0.0, 0.0, 10.0]]))
    scene.build_engine()
    return scene


def _truth(intr: Intrinsics, pose: Pose):
    """Analytic depth and which surface (0 back, 1 front, -1 none) per pixel."""
    cols, rows = np.meshgrid(np.arange(intr.width), np.arange(intr.height))
    dcam = np.stack([(cols - intr.cx) / intr.fx, (rows - intr.cy) / intr.fy,
                     np.ones(cols.shape)], -1)
    dw = dcam @ pose.R  # world direction with camera z = 1
    C = pose.center
    # Back plane z = 0.
    t_back = -C[2] / dw[..., 2]
    pb = C + dw * t_back[..., None]
    in_back = (np.abs(pb[..., 0]) <= BACK_HALF) & (np.abs(pb[..., 1]) <= BACK_HALF)
    # Front plane n · (p - (0, 0, 1)) = 0.
    t_front = (FRONT_N @ (np.array([0, 0, 1.0]) - C)) / (dw @ FRONT_N)
    pf = C + dw * t_front[..., None]
    in_front = (np.abs(pf[..., 0]) <= FRONT_HALF) & (np.abs(pf[..., 1]) <= FRONT_HALF)
    surface = np.where(in_front, 1, np.where(in_back, 0, -1))
    depth = np.where(in_front, t_front, np.where(in_back, t_back, np.nan))
    # Distance of each pixel's hit from the nearest edge of its surface, in
    # pixels (one pixel ≈ depth / F metres): within a splat radius (~1.5 px
    # here, where the one-sided neighbourhood of an edge point doubles its
    # spacing) a splat's extent is legitimately uncertain.
    edge_f = FRONT_HALF - np.maximum(np.abs(pf[..., 0]), np.abs(pf[..., 1]))
    edge_b = BACK_HALF - np.maximum(np.abs(pb[..., 0]), np.abs(pb[..., 1]))
    near_edge = (np.minimum(np.abs(edge_f) * F / t_front, np.abs(edge_b) * F / t_back) < 2.0)
    return depth, surface, near_edge


@pytest.fixture(scope="module")
def rendered(planes):
    return RenderResult(**splat_cloud(planes, INTR, POSE))


def test_plane_cloud_renders_the_analytic_depth(planes, rendered):
    depth, surface, near_edge = _truth(INTR, POSE)
    away = ~near_edge
    # The mask is right away from the edges: every surface pixel is covered
    # (holes filled), no pixel beyond the back plane is.
    assert (rendered.mask[away] == (surface[away] >= 0)).all()
    # Depth within 1 mm of the analytic one on every pixel of both planes,
    # including the back plane right beside the front square's silhouette:
    # nothing is filled across the 1 m depth jump.
    seen = away & (surface >= 0)
    err = np.abs(rendered.depth[seen] - depth[seen])
    assert err.max() < 1e-3, err.max()
    # The pixel shows the right surface (its point index is front or back).
    front_ids = rendered.face_id[seen] >= 50_000
    assert (front_ids == (surface[seen] == 1)).all()
    # Intensity as grey: 0.2 → 51, 0.9 → 230.
    grey = rendered.rgb[seen][:, 0].astype(int)
    assert np.abs(np.where(surface[seen] == 1, 230, 51) - grey).max() <= 1


def test_without_hole_filling_random_samples_leave_holes(planes, rendered):
    # Random sampling leaves gaps between the discs: empty pixels, and pixels
    # of the back plane seen through the front square. Filling closes both.
    depth, surface, near_edge = _truth(INTR, POSE)
    inner = (surface >= 0) & ~near_edge
    raw = RenderResult(**splat_cloud(planes, INTR, POSE, params=SplatParams(fill_passes=0)))
    wrong = inner & ~(np.abs(raw.depth - depth) < 0.01)  # NaN (empty) counts as wrong
    assert wrong.sum() > 20
    assert (np.abs(rendered.depth[inner] - depth[inner]) < 1e-3).all()


def test_render_follows_the_mesh_renderer_conventions(planes, rendered):
    r = rendered
    assert r.rgb.dtype == np.uint8 and r.rgb.shape == (H, W, 3)
    assert r.xyz.dtype == np.float32 and r.depth.dtype == np.float32
    assert r.normal.dtype == np.float32 and r.face_id.dtype == np.int32
    assert r.mask.dtype == bool and (r.mask == (r.face_id >= 0)).all()
    empty = ~r.mask
    assert empty.any()
    assert np.isnan(r.xyz[empty]).all() and np.isnan(r.depth[empty]).all()
    assert (r.normal[empty] == 0).all() and (r.rgb[empty] == 0).all()
    assert np.isfinite(r.xyz[r.mask]).all()
    # xyz is the camera ray at the rendered depth; normals unit, toward the camera.
    cam = POSE.transform(r.xyz[r.mask].reshape(-1, 3))
    assert np.allclose(cam[:, 2], r.depth[r.mask], atol=1e-4)
    n = r.normal[r.mask]
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)
    view = r.xyz[r.mask] - POSE.center
    assert (np.einsum("ij,ij->i", n, view) < 0).all()
    # The stages' look-up works on it.
    pts, ok = r.lift(np.array([[100.0, 75.0], [-5.0, 3.0]]))
    assert ok.tolist() == [True, False] and np.isfinite(pts[0]).all()
    assert r.intrinsics == INTR and r.cam_from_world is POSE
    assert {"project", "splat", "fill", "total"} <= set(r.timings_s)


def test_modes_scale_and_bad_input(planes):
    half = RenderResult(**splat_cloud(planes, INTR, POSE, scale=0.5, mode="normal"))
    assert half.shape == (75, 100) and half.intrinsics == INTR.scaled(0.5)
    shaded = splat_cloud(planes, INTR, POSE, mode="shaded", light_direction=[0, 0, 1])
    # Lit straight along the back plane's normal: ambient + (1 - ambient) = full grey.
    centre_back = shaded["rgb"][5, 5]
    assert abs(int(centre_back[0]) - 180) <= 1
    with pytest.raises(InputError, match="scale"):
        splat_cloud(planes, INTR, POSE, scale=0.0)
    with pytest.raises(ValueError, match="mode"):
        splat_cloud(planes, INTR, POSE, mode="sketch")


def test_known_points_render_at_their_projected_pixels():
    # Sparse points with a tiny spacing: each covers just the pixel it falls
    # in, through a camera with strong distortion.
    rng = np.random.default_rng(3)
    intr = Intrinsics(160, 120, 150.0, 150.0, 81.3, 58.2, (-0.25, 0.08, 0.001, -0.002, 0.0))
    pose = Pose.from_attitude(30.0, 10.0, 5.0, np.array([0.0, 0.0, 1.5]))
    # Distinct pixels, each point within 0.2 px of its pixel's centre (so
    # its 0.75 px minimum footprint reaches no other pixel).
    grid = np.stack(np.meshgrid(np.arange(8, 152, 18), np.arange(8, 115, 22)), -1).reshape(-1, 2)
    uv_true = grid[:40] + rng.uniform(-0.2, 0.2, (40, 2))
    depth = rng.uniform(3.0, 9.0, 40)
    xyz = pose.inverse_transform(intr.unproject(uv_true, depth))
    scene = CloudScene(xyz, spacing=np.full(40, 1e-3), normals=np.tile([0.0, 0.0, 1.0], (40, 1)))
    r = RenderResult(**splat_cloud(scene, intr, pose, params=SplatParams(fill_passes=0)))
    cols, rows = np.rint(uv_true).astype(int).T
    assert (r.face_id[rows, cols] == np.arange(40)).all()
    assert np.allclose(r.depth[rows, cols], depth, rtol=1e-3)
    assert r.mask.sum() == 40  # nothing else drawn


def test_pca_normals_of_a_plane_cloud(planes):
    n = planes.normals
    back, front = n[:50_000], n[50_000:]
    # Interior points (edge neighbourhoods are one-sided but still planar).
    assert (back @ np.array([0, 0, 1.0]) > 0.999).all()  # toward the scanner above
    assert (front @ FRONT_N > 0.999).all()
    assert planes.spacing.dtype == np.float32 and (planes.spacing > 0).all()
    assert np.median(planes.surface_variation) < 1e-6
    assert planes.face_array("normals") is planes.normals
    with pytest.raises(ValueError, match="no per-face 'uv'"):
        planes.face_array("uv")


@pytest.mark.parametrize("budget", [1e12, 0.0], ids=["point-by-point", "virtual-camera"])
def test_rays_meet_the_plane_at_the_analytic_point(planes, budget):
    scene = CloudScene(planes.xyz, normals=planes.normals, spacing=planes.spacing,
                       params=CloudParams(max_brute_force=budget))
    rng = np.random.default_rng(5)
    pix = rng.uniform([0, 0], [W - 1, H - 1], (300, 2))
    origin, d = POSE.rays(INTR, pix)
    hits = scene.cast_rays(origin, d)
    # Analytic first hit: the front plane where inside its square, else the back.
    t_front = (FRONT_N @ (np.array([0, 0, 1.0]) - origin)) / (d @ FRONT_N)
    pf = origin + d * t_front[:, None]
    t_back = -origin[2] / d[:, 2]
    pb = origin + d * t_back[:, None]
    in_front = np.max(np.abs(pf[:, :2]), axis=1) <= FRONT_HALF
    in_back = np.max(np.abs(pb[:, :2]), axis=1) <= BACK_HALF
    t_true = np.where(in_front, t_front, t_back)
    margin = ((np.abs(np.max(np.abs(pf[:, :2]), axis=1) - FRONT_HALF) > 0.05)
              & (np.abs(np.max(np.abs(pb[:, :2]), axis=1) - BACK_HALF) > 0.05))
    assert (hits.hit == (in_front | in_back))[margin].all()
    margin &= in_front | in_back
    assert margin.sum() > 200
    err = np.abs(hits.distance - t_true)[margin]
    assert err.max() < 1e-4, err.max()
    pts = scene.surface_points(hits)
    assert np.allclose(pts[margin], (origin + d * t_true[:, None])[margin], atol=1e-4)
    assert ((hits.face_id >= 50_000) == in_front)[margin].all()
    # Away from the cloud: a miss, with the RayHits conventions.
    miss = scene.cast_rays(np.array([10.0, 10.0, 5.0]), np.array([[0.0, 0.0, 1.0]]))
    assert miss.face_id[0] == -1 and np.isinf(miss.distance[0])
    assert np.isnan(scene.surface_points(miss)).all()
    short = scene.cast_rays(origin, d[:5], max_distance=1.0)
    assert not short.hit.any()


def test_terrain_height_without_a_dem(planes):
    # The lowest points under (x, y): the back plane at 0, not the square at ~1.
    assert planes.terrain_height(0.0, 0.0) == pytest.approx(0.0, abs=1e-6)
    with pytest.raises(InputError, match="no points within"):
        planes.terrain_height(2000.0, 0.0)
    # The map view's surface model: the square's highest point in the 0.5 m
    # cell at its centre, the back plane (0) around it, nothing beyond the
    # cloud; north row first.
    xs = np.linspace(-3.0, 3.0, 13)
    grid = planes.height_grid(xs, xs[::-1])
    assert grid.shape == (13, 13)
    assert np.isnan(grid[0, 0]) and grid[6, 1] == pytest.approx(0.0)
    assert grid[6, 6] == pytest.approx(_front_z(0.25, -0.25), abs=0.01)  # highest corner


def test_from_point_cloud_and_the_normals_cache(planes, tmp_path):
    reader_result = SimpleNamespace(xyz=planes.xyz[:2000], intensity=np.arange(2000.0),
                                    rgb=None)
    scene = CloudScene.from_point_cloud(reader_result, name="scan")
    assert scene.is_cloud and scene.name == "scan" and scene.n_points == 2000
    assert scene.intensity.min() == 0.0 and scene.intensity.max() == 1.0  # normalised
    assert scene.bounds.shape == (2, 3) and not scene.has_texture
    scene.source = tmp_path / "scan.las"
    normals = scene.normals  # computed, and cached beside the source
    cache = tmp_path / "scan.las.imgreg-normals.npz"
    assert cache.exists()
    again = CloudScene.from_point_cloud(reader_result)
    again.source = scene.source
    again._read_cache()
    assert again._normals is not None
    # Exactly as computed: a run with the cache registers as the first run did.
    assert np.array_equal(again.normals, normals)
    assert np.array_equal(again.surface_variation, scene.surface_variation)
    assert np.array_equal(again.spacing, scene.spacing)
    # Other points: the cache is not used.
    other = CloudScene(planes.xyz[:2000] + 1.0)
    other.source = scene.source
    other._read_cache()
    assert other._normals is None


def test_load_reads_the_file_and_reuses_its_normals_cache(planes, tmp_path):
    from napari_imgreg.io.pointclouds import PointCloud, write_point_cloud

    path = tmp_path / "scan.ply"
    some = np.r_[0:1500, 50_000:51_500]  # both planes: two intensities
    write_point_cloud(path, PointCloud(xyz=planes.xyz[some], intensity=planes.intensity[some]))
    first = CloudScene.load(path)
    assert first.n_points == 3000 and first.source == path and first.name == "scan"
    assert first.has_intensity and first._normals is None
    first.build_engine()
    assert (tmp_path / "scan.ply.imgreg-normals.npz").exists()
    second = CloudScene.load(path)
    assert second._normals is not None  # from the cache, not computed again
    assert np.allclose(second.normals, first.normals, atol=1e-3)


def test_cloud_and_mesh_scenes_read_one_dem_the_same_way():
    """Both scenes take the DEM through geo.dem_height_local: CRS heights minus the origin."""
    from napari_imgreg.geo import dem_height_local

    class FlatDem:  # a DEM at 350 m + 0.01 m per metre east, in CRS coordinates
        def height_at(self, e, n):
            return 350.0 + 0.01 * (e - 579000.0)

    class Origin:
        origin = (579000.0, 5912000.0, 340.0)

    assert dem_height_local(FlatDem(), Origin(), 100.0, 5.0) == pytest.approx(11.0)
    assert dem_height_local(FlatDem(), None, 579100.0, 0.0) == pytest.approx(351.0)


# ------------------------------------------------------- level of detail
@pytest.fixture(scope="module")
def lod_planes(planes):
    """The plane cloud with a level of detail (every size gets one)."""
    from napari_imgreg.cloud import LodParams

    scene = CloudScene(planes.xyz, intensity=planes.intensity, normals=planes.normals,
                       spacing=planes.spacing,
                       params=CloudParams(lod=LodParams(min_points=0, block_points=1024)))
    scene.build_engine()
    return scene


def test_level_of_detail_levels_nest_in_blocks(lod_planes):
    lod = lod_planes.level_of_detail
    n = lod_planes.n_points
    # Every point once, in blocks; each level a prefix of its block, no
    # larger than the finer one, each coarser level about a quarter of it.
    assert np.array_equal(np.sort(lod.ids), np.arange(n))
    assert lod.counts[:, 0].sum() == n and (np.diff(lod.counts, axis=1) <= 0).all()
    assert np.array_equal(lod.starts, np.r_[0, np.cumsum(lod.counts[:-1, 0])])
    per_level = lod.counts.sum(axis=0)
    assert 2.5 < per_level[0] / per_level[1] < 6.0
    assert np.allclose(lod.xyz32, lod_planes.xyz32[lod.ids])
    assert np.array_equal(lod.normals, lod_planes.normals[lod.ids])
    # Each block's points lie within its sphere.
    block = np.repeat(np.arange(lod.n_blocks), lod.counts[:, 0])
    off = np.linalg.norm(lod.xyz32 - lod.centre[block], axis=1)
    assert (off <= lod.half_diagonal[block] + 1e-5).all()
    # An even sample for display: a whole level, within the budget.
    few = lod.sample(20_000)
    assert len(few) == per_level[np.flatnonzero(per_level <= 20_000)[0]]
    assert len(np.unique(few)) == len(few)
    assert np.abs(lod_planes.xyz[few, :2].mean(axis=0)).max() < 0.2  # spread over the planes
    # A small cloud has none by default.
    assert CloudScene(lod_planes.xyz[:5000]).level_of_detail is None


def test_level_of_detail_render_matches_every_point(lod_planes):
    # From far away (12 m up: ~6 cm per pixel) the coarse levels suffice:
    # far fewer points are drawn, the image is the same surfaces.
    pose = Pose.from_center(np.diag([1.0, -1.0, -1.0]), np.array([0.1, -0.05, 12.0]))
    lod = lod_planes.level_of_detail
    from napari_imgreg.render_points import _field_of_view

    blocks, level, _ = lod.choose(pose.R, pose.t, _field_of_view(INTR), F, 0.75, 0.01, 1.0)
    assert lod.counts[blocks, level].sum() < 0.5 * lod_planes.n_points
    auto = RenderResult(**splat_cloud(lod_planes, INTR, pose))  # "auto" is the default
    full = RenderResult(**splat_cloud(lod_planes, INTR, pose, detail="full"))
    assert "select" in auto.timings_s
    # render() passes the choice through: "full" there is every point too.
    from napari_imgreg.render import render

    assert np.array_equal(render(lod_planes, INTR, pose, detail="full").depth, full.depth,
                          equal_nan=True)
    assert "select" in render(lod_planes, INTR, pose).timings_s
    assert abs(auto.mask.mean() - full.mask.mean()) < 0.01
    both = auto.mask & full.mask
    # Depth of the right plane (within 1 cm of every point's; the two planes
    # are ~1 m apart), the right intensity, scene indices in face_id.
    assert np.median(np.abs(auto.depth[both] - full.depth[both])) < 1e-3
    assert (np.abs(auto.depth[both] - full.depth[both]) < 0.01).mean() > 0.98
    assert (auto.rgb[both, 0] == full.rgb[both, 0]).mean() > 0.98
    ids = auto.face_id[auto.mask]
    seen = lod_planes.xyz[ids]
    cam = pose.transform(seen)
    assert np.median(np.abs(cam[:, 2] - auto.depth[auto.mask])) < 0.05
    # Close up every block in view is drawn whole: the plane's exact depth.
    near = RenderResult(**splat_cloud(lod_planes, INTR, POSE))
    depth, surface, near_edge = _truth(INTR, POSE)
    seen = ~near_edge & (surface >= 0)
    assert np.abs(near.depth[seen] - depth[seen]).max() < 1e-3
    # Looking away: nothing in view, nothing drawn.
    away = Pose.from_center(np.eye(3), np.array([0.0, 0.0, 5.0]))  # camera z = +Z: up
    blocks, _, _ = lod.choose(away.R, away.t, _field_of_view(INTR), F, 0.75, 0.01, 1.0)
    assert len(blocks) == 0
    assert not splat_cloud(lod_planes, INTR, away)["mask"].any()
    with pytest.raises(ValueError, match="detail"):
        splat_cloud(lod_planes, INTR, POSE, detail="coarse")
    with pytest.raises(ValueError, match="render_detail"):
        CloudParams(render_detail="coarse")


# ------------------------------------------- the faster kernels, same image
def _before():
    """The kernels as they were before the speed-ups (loaded from the
    repository's history by ``benchmarks/_splat_before.py``), or skip where
    the benchmarks folder or the history is not there."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "benchmarks" / "_splat_before.py"
    if not path.exists():
        pytest.skip("benchmarks/_splat_before.py not present")
    spec = importlib.util.spec_from_file_location("_splat_before_loader", path)
    loader = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(loader)
    module = loader.load()
    if module is None:
        pytest.skip(f"commit {loader.BEFORE_COMMIT} not in this checkout's history")
    return module


@pytest.mark.parametrize("case", ["plain", "distorted-blended"])
def test_faster_kernels_draw_the_same_image_as_before(planes, case, monkeypatch):
    # Bit for bit: depth, point index and colour, on two threads (balanced
    # bands; the old split was even) with hole filling of every pass.
    monkeypatch.setenv("NAPARI_IMGREG_THREADS", "2")
    before = _before()
    intr, pose, params = INTR, POSE, SplatParams()
    if case == "distorted-blended":
        intr = Intrinsics(W, H, F, F, 97.0, 77.0, (-0.2, 0.05, 0.001, -0.001, 0.0))
        pose = Pose.from_center(POSE.R, np.array([0.3, 0.2, 2.6]))  # near: large splats
        params = SplatParams(blend_min_radius_px=0.5, fill_passes=5)
    new = splat_cloud(planes, intr, pose, params=params)
    old = before.splat_cloud(planes, intr, pose, params=before.SplatParams(**vars(params)))
    assert new["mask"].mean() > 0.5
    for key in ("depth", "face_id", "rgb", "xyz", "normal"):
        assert np.array_equal(new[key], old[key], equal_nan=True), key


def test_render_does_not_depend_on_the_threads(planes, monkeypatch):
    monkeypatch.setenv("NAPARI_IMGREG_THREADS", "1")
    one = splat_cloud(planes, INTR, POSE)
    monkeypatch.setenv("NAPARI_IMGREG_THREADS", "3")
    three = splat_cloud(planes, INTR, POSE)
    for key in ("depth", "face_id", "rgb"):
        assert np.array_equal(one[key], three[key], equal_nan=True), key


def test_level_of_detail_is_cached_beside_the_file(lod_planes, tmp_path):
    params = lod_planes.params

    def scene():
        s = CloudScene(lod_planes.xyz, normals=lod_planes.normals, spacing=lod_planes.spacing,
                       params=params)
        s.source = tmp_path / "scan.laz"
        return s

    first = scene().level_of_detail
    assert (tmp_path / "scan.laz.imgreg-lod.npz").exists()
    again = scene()
    order = again._read_lod_cache()
    assert order is not None and np.array_equal(order[0], first.ids)
    assert np.array_equal(again.level_of_detail.counts, first.counts)
    # Other points: not used.
    other = CloudScene(lod_planes.xyz + 1.0, params=params)
    other.source = tmp_path / "scan.laz"
    assert other._read_lod_cache() is None


@pytest.mark.parametrize("bad", ["normals", "surface_variation", "shape"])
def test_a_well_formed_but_wrong_normals_cache_is_computed_again(planes, tmp_path, bad):
    """A cache with the right fingerprint but NaN normals (or surface
    variation, or arrays of the wrong length) is not trusted: the load
    computes the normals again, and the rewritten cache is finite."""
    from napari_imgreg.io.pointclouds import PointCloud, write_point_cloud

    path = tmp_path / "scan.ply"
    write_point_cloud(path, PointCloud(xyz=planes.xyz[:2000], intensity=None))
    first = CloudScene.load(path)
    normals = first.normals.copy()
    n = first.n_points
    arrays = {"normals": first.normals.astype(np.float16), "spacing": first.spacing,
              "surface_variation": first.surface_variation.astype(np.float16)}
    if bad == "shape":
        arrays = {k: v[: n - 1] for k, v in arrays.items()}
    else:
        arrays[bad] = np.full_like(arrays[bad], np.nan)
    cache = tmp_path / "scan.ply.imgreg-normals.npz"
    np.savez(cache, fingerprint=np.array(first._fingerprint()), **arrays)
    second = CloudScene.load(path)
    assert second._normals is None  # the cache was not used
    assert np.isfinite(second.normals).all() and np.isfinite(second.surface_variation).all()
    assert np.allclose(second.normals, normals, atol=1e-3)
    with np.load(cache) as data:  # written again, finite
        assert np.isfinite(data["normals"].astype(np.float32)).all()


def test_parallel_rays_as_a_sun_casts_them_agree_with_the_brute_force(planes):
    # Shadow rays: many origins, one direction (toward a sun). The binned
    # path answers them as testing every point does, and a large query
    # (300 rays × 150k points over the budget) no longer tests every point.
    sun = np.array([0.3, -0.2, 1.0])
    sun /= np.linalg.norm(sun)
    rng = np.random.default_rng(11)
    # Origins on the back plane, 1 cm above it: shadowed where the front
    # square stands between them and the sun.
    origins = np.column_stack([rng.uniform(-BACK_HALF, BACK_HALF, (400, 2)), np.full(400, 0.01)])
    dirs = np.tile(sun, (400, 1))
    brute = CloudScene(planes.xyz, normals=planes.normals, spacing=planes.spacing,
                       params=CloudParams(max_brute_force=1e12))
    binned = CloudScene(planes.xyz, normals=planes.normals, spacing=planes.spacing,
                        params=CloudParams(max_brute_force=0.0))
    a, b = brute.cast_rays(origins, dirs), binned.cast_rays(origins, dirs)
    assert (a.face_id == b.face_id).all()
    assert np.allclose(a.distance[a.hit], b.distance[b.hit], atol=1e-6)
    # Analytically: the ray meets the front plane inside its square.
    t_front = ((np.array([0, 0, 1.0]) - origins) @ FRONT_N) / (sun @ FRONT_N)
    pf = origins + sun * t_front[:, None]
    inside = np.max(np.abs(pf[:, :2]), axis=1)
    clear = np.abs(inside - FRONT_HALF) > 0.05
    assert clear.sum() > 300
    assert (b.hit == ((inside <= FRONT_HALF) & (t_front > 0)))[clear].all()
    assert 20 < b.hit.sum() < 350  # the square shades ~10 % of the back plane

"""A surface model from a DEM/DSM (and an orthophoto), and terrain heights."""

import numpy as np
import pytest
import tifffile

from napari_imgreg import Intrinsics, Pose, Scene, render
from napari_imgreg.geo import DEM, Georef

E0, N0 = 579_000.0, 5_912_000.0


def plane_dem(tmp_path, with_hole=False):
    """h = 300 + 0.2 (E − E0) − 0.1 (N − N0) on a 2 m grid, 60 × 80 cells."""
    rows, cols, step = 60, 80, 2.0
    e = E0 + np.arange(cols) * step
    n = N0 + (rows - 1 - np.arange(rows)) * step
    E, N = np.meshgrid(e, n)
    h = 300 + 0.2 * (E - E0) - 0.1 * (N - N0)
    if with_hole:
        h[20:25, 30:35] = np.nan
    dem = DEM.from_array(h, x0=E0, y0=n[0], dx=step, dy=step, crs="EPSG:32630", source="dsm.tif")
    path = tmp_path / "dsm.tif"
    dem.save_geotiff(path)
    return path, dem


def test_dem_mesh_follows_the_heights(tmp_path):
    path, dem = plane_dem(tmp_path)
    scene = Scene.from_dem(path)
    assert scene.georef is not None and scene.georef.crs == "EPSG:32630"
    enh = scene.vertices + scene.georef.origin
    np.testing.assert_allclose(enh[:, 2], 300 + 0.2 * (enh[:, 0] - E0) - 0.1 * (enh[:, 1] - N0),
                               atol=1e-4)  # heights are float32 in the GeoTIFF
    assert scene.n_faces == 2 * 59 * 79
    # Triangles face up (counter-clockwise seen from above).
    assert (scene.face_array("normals")[:, 2] > 0).all()
    # Terrain height through the DEM equals the plane, in the local frame.
    x, y = 37.3, 51.9
    e, n = x + scene.georef.origin[0], y + scene.georef.origin[1]
    expected = 300 + 0.2 * (e - E0) - 0.1 * (n - N0) - scene.georef.origin[2]
    assert scene.terrain_height(x, y) == pytest.approx(expected, abs=1e-4)  # float32 GeoTIFF


def test_nodata_leaves_a_hole(tmp_path):
    path, _ = plane_dem(tmp_path, with_hole=True)
    scene = Scene.from_dem(path)
    assert scene.n_faces < 2 * 59 * 79
    assert np.isfinite(scene.vertices).all()


def test_orthophoto_textures_the_dem(tmp_path):
    path, dem = plane_dem(tmp_path)
    # An orthophoto on a 1 m grid: red rises eastward, green northward.
    rows, cols = 120, 160
    ortho = np.zeros((rows, cols, 3), np.uint8)
    ortho[..., 0] = np.linspace(0, 255, cols)[None, :].astype(np.uint8)
    ortho[..., 1] = np.linspace(255, 0, rows)[:, None].astype(np.uint8)
    y_top = N0 + 118.0 + 0.5  # centre of the first row
    x_left = E0 - 0.5
    # PixelIsArea tiepoint at the top-left corner of the top-left pixel.
    tifffile.imwrite(
        tmp_path / "ortho.tif", ortho, photometric="rgb",
        extratags=[
            (33550, "d", 3, (1.0, 1.0, 0.0), True),
            (33922, "d", 6, (0.0, 0.0, 0.0, x_left - 0.5, y_top + 0.5, 0.0), True),
            (34735, "H", 16, (1, 1, 0, 3, 1024, 0, 1, 1, 1025, 0, 1, 1, 3072, 0, 1, 32630), True),
        ],
    )
    scene = Scene.from_dem(path, orthophoto=tmp_path / "ortho.tif")
    assert scene.has_texture
    # Look straight down from 100 m above the middle of the DEM.
    centre = scene.vertices.mean(axis=0) + [0, 0, 100]
    pose = Pose.from_attitude(0.0, 90.0, 0.0, centre)
    result = render(scene, Intrinsics.from_fov(64, 48, 30.0), pose)
    assert result.mask.all()
    red = result.rgb[..., 0].astype(float)
    green = result.rgb[..., 1].astype(float)
    # East is to the image's right and north to its top in this view.
    assert red[:, -1].mean() > red[:, 0].mean() + 10
    assert green[0].mean() > green[-1].mean() + 10
    # And the colour is the orthophoto's at the surface point seen.
    p = result.xyz[24, 32] + scene.georef.origin
    col = (p[0] - x_left) / 1.0
    assert result.rgb[24, 32, 0] == pytest.approx(255 * col / (cols - 1), abs=4)

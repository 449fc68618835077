"""napari integration: manifest, reader, sample data, and what the canvas shows.

Runs in a real napari viewer (napari needs an X server: `make test` runs the
suite under Xvfb).
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from PIL import Image

from napari_imgreg import Scene
from napari_imgreg.widgets._layers import napari_from_world, surface_layer_data, world_from_napari
from napari_imgreg._reader import get_reader


def _marked_wall(tmp_path):
    """A 40 × 20 m wall in the plane y = 0 facing south; its texture's top-left
    quadrant is red, so a mirrored or flipped display is easy to spot."""
    vertices = np.array([[0, 0, 0], [40, 0, 0], [40, 0, 20], [0, 0, 20]], float)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    texture = np.full((64, 128, 3), 200, np.uint8)
    texture[:32, :64] = (255, 0, 0)
    mesh = trimesh.Trimesh(
        vertices, faces, process=False,
        visual=trimesh.visual.TextureVisuals(uv=uv, image=Image.fromarray(texture)),
    )
    path = tmp_path / "wall.obj"
    mesh.export(path)
    return path


def test_manifest_is_valid():
    from npe2 import PluginManifest

    manifest = PluginManifest.from_distribution("napari-imgreg")
    assert manifest.name == "napari-imgreg"
    keys = {s.key for s in manifest.contributions.sample_data}
    assert {"outcrop_model", "outcrop_photo"} <= keys


def test_axis_conversion_round_trips():
    xyz = np.random.default_rng(0).normal(size=(10, 3))
    np.testing.assert_array_equal(world_from_napari(napari_from_world(xyz)), xyz)
    # napari axis 0 is height, and the permutation is cyclic (keeps handedness).
    assert napari_from_world(np.array([1.0, 2.0, 3.0])).tolist() == [3.0, 1.0, 2.0]
    perm = np.eye(3)[[2, 0, 1]]
    assert np.linalg.det(perm) == pytest.approx(1.0)


def test_reader_only_claims_meshes(tmp_path):
    assert get_reader(str(tmp_path / "photo.jpg")) is None
    assert get_reader([str(tmp_path / "a.obj"), str(tmp_path / "b.obj")]) is None
    path = _marked_wall(tmp_path)
    reader = get_reader(str(path))
    assert callable(reader)
    (data, kwargs, kind), = reader(str(path))
    assert kind == "surface"
    assert kwargs["texture"].shape == (64, 128, 3)
    assert kwargs["texcoords"].shape == (4, 2)


def test_opened_mesh_is_displayed_unmirrored(make_napari_viewer, tmp_path):
    """Seen from the south, looking north with z up, the red quadrant must be at
    the top left, exactly where our own renderer puts it."""
    viewer = make_napari_viewer(show=True)
    layers = viewer.open(str(_marked_wall(tmp_path)), plugin="napari-imgreg")
    assert layers[0].__class__.__name__ == "Surface"
    viewer.dims.ndisplay = 3
    viewer.reset_view()
    viewer.scene.camera.set_view_direction(
        view_direction=tuple(napari_from_world(np.array([0.0, 1.0, 0.0]))),
        up_direction=tuple(napari_from_world(np.array([0.0, 0.0, 1.0]))),
    )
    shot = viewer.screenshot(canvas_only=True)[..., :3].astype(int)
    red = (shot[..., 0] > 200) & (shot[..., 1] < 80) & (shot[..., 2] < 80)
    assert red.sum() > 100, "texture not shown"
    rows, cols = np.nonzero(red)
    wall = shot.sum(axis=2) > 60
    wall_rows, wall_cols = np.nonzero(wall)
    assert rows.mean() < wall_rows.mean(), "texture upside down"
    assert cols.mean() < wall_cols.mean(), "model mirrored"


def test_surface_layer_data_colour_modes():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    f = np.array([[0, 1, 2]])
    _, kw, _ = surface_layer_data(Scene(v, f, vertex_colors=np.full((3, 3), 255, np.uint8)))
    assert kw["vertex_colors"].max() == pytest.approx(1.0)
    _, kw, _ = surface_layer_data(Scene(v, f))
    assert "texture" not in kw and "vertex_colors" not in kw


@pytest.mark.slow
def test_sample_data_open_in_napari(make_napari_viewer):
    viewer = make_napari_viewer()
    viewer.open_sample("napari-imgreg", "outcrop_model")
    surface = viewer.layers[-1]
    assert surface.__class__.__name__ == "Surface"
    assert surface.texture is not None and len(surface.data[1]) > 10_000
    viewer.open_sample("napari-imgreg", "outcrop_photo")
    photo, render = viewer.layers[-2], viewer.layers[-1]
    assert photo.rgb and render.rgb
    assert photo.data.shape == render.data.shape
    # The render from the prior shows the outcrop: most of it is surface, not sky.
    assert (np.asarray(render.data).sum(axis=2) > 0).mean() > 0.3

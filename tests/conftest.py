"""Shared fixtures: small synthetic scenes with exactly known geometry, and
the command-line runner of the CLI tests."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import pytest

from napari_imgreg.scene import Scene


def _quad(center, axis_a, axis_b, half_a, half_b, texture=None, vertex_colors=None):
    """A planar rectangle ``center + s*a + t*b``, |s| <= half_a, |t| <= half_b.

    Two triangles; UV (0, 0) at (-half_a, -half_b), u along ``a``, v along ``b``.
    The geometric normal (V1 - V0) x (V2 - V0) is ``a x b``.
    """
    c = np.asarray(center, float)
    a = np.asarray(axis_a, float)
    b = np.asarray(axis_b, float)
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    st = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
    vertices = c + st[:, :1] * half_a * a + st[:, 1:] * half_b * b
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    uv = (st + 1.0) / 2.0 if texture is not None else None
    return Scene(vertices, faces, uv, texture, vertex_colors)


def _box(lo, hi):
    """Closed axis-aligned box, 12 outward-wound triangles."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    corners = np.array(
        [[(hi if (i >> k) & 1 else lo)[k] for k in range(3)] for i in range(8)]
    )  # corner i: bit k set -> hi on axis k
    quads = [
        (0, 4, 6, 2),  # x = lo, outward -X
        (1, 3, 7, 5),  # x = hi, +X
        (0, 1, 5, 4),  # y = lo, -Y
        (2, 6, 7, 3),  # y = hi, +Y
        (0, 2, 3, 1),  # z = lo, -Z
        (4, 5, 7, 6),  # z = hi, +Z
    ]
    faces = []
    for a, b, c, d in quads:
        faces += [(a, b, c), (a, c, d)]
    return Scene(corners, np.array(faces))


@pytest.fixture
def make_quad():
    """Factory: ``make_quad(center, axis_a, axis_b, half_a, half_b, texture=, vertex_colors=)``."""
    return _quad


@pytest.fixture
def make_box():
    """Factory: ``make_box(lo, hi)`` -> closed axis-aligned box Scene."""
    return _box


# ------------------------------------------------------------ command line
@pytest.fixture
def wall_mesh(tmp_path):
    """A textured 40 m × 20 m wall in the plane y = 0, written as ``wall.obj``.

    Its texture's red grows eastward (+x), green is 120: a level camera at
    (20, −30, 10) looking north sees it 30 m away.
    """
    import trimesh
    from PIL import Image

    vertices = np.array([[0, 0, 0], [40, 0, 0], [40, 0, 20], [0, 0, 20]], float)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    texture = np.zeros((64, 128, 3), np.uint8)
    texture[..., 0] = np.linspace(0, 255, 128)[None, :]
    texture[..., 1] = 120
    mesh = trimesh.Trimesh(
        vertices, faces, process=False,
        visual=trimesh.visual.TextureVisuals(uv=uv, image=Image.fromarray(texture)),
    )
    mesh_path = tmp_path / "wall.obj"
    mesh.export(mesh_path)
    return mesh_path


@pytest.fixture
def wall_and_record(wall_mesh):
    """The wall (:func:`wall_mesh`) and a sensor record ``IMG_0001.json`` of a
    160 × 120 camera facing it from (20, −30, 10): (mesh path, record path)."""
    import json

    record = {
        "camera": {"width": 160, "height": 120, "fx": 100.0, "fy": 100.0, "cx": 79.5, "cy": 59.5},
        "position": {"x": 20.0, "y": -30.0, "z": 10.0},
        "orientation": {"trend_deg": 0.0, "plunge_deg": 0.0, "roll_deg": 0.0},
    }
    prior_path = wall_mesh.parent / "IMG_0001.json"
    prior_path.write_text(json.dumps(record))
    return wall_mesh, prior_path


@pytest.fixture
def dated_orient_tables(tmp_path):
    """An orientation survey's tables in ``scene/orient/`` (no georef.json, no
    photos beside them), the phone's dated 2027-07-02: (estimated, measured)."""
    from dataclasses import replace
    from datetime import date

    from napari_imgreg.io.orientation_tables import write_orientation_csv
    from napari_imgreg.sample.survey import simulate_survey

    survey = simulate_survey(np.random.default_rng(7))
    folder = tmp_path / "scene" / "orient"
    folder.mkdir(parents=True)
    est, meas = folder / "estimated.csv", folder / "measured.csv"
    write_orientation_csv(est, survey.estimated)
    dated = replace(survey.measured, capture_dates=[date(2027, 7, 2)] * len(survey.measured))
    write_orientation_csv(meas, dated)
    return est, meas


@dataclass
class CliRun:
    """What one ``napari-imgreg`` command did: exit code, stdout, stderr, time."""

    code: int
    out: str
    err: str
    seconds: float

    @property
    def line(self) -> str:
        """The one line of stderr (asserted: exactly one non-blank line, no traceback)."""
        lines = [line for line in self.err.splitlines() if line.strip()]
        assert len(lines) == 1 and "Traceback" not in self.err, self.err
        return lines[0]


@pytest.fixture
def run_cli(capsys):
    """Run the command line in-process: ``run_cli(argv, max_seconds=30) -> CliRun``.

    Arguments may be paths or numbers (turned to str). A bad input must be
    refused at the boundary, so a run longer than ``max_seconds`` fails the
    test (None: no bound, for commands that do real work).
    """
    from napari_imgreg.cli import main

    def run(argv, max_seconds: float | None = 30.0) -> CliRun:
        capsys.readouterr()  # what came before is not this command's
        t0 = time.perf_counter()
        code = main([str(a) for a in argv])
        elapsed = time.perf_counter() - t0
        captured = capsys.readouterr()
        if max_seconds is not None:
            assert elapsed < max_seconds, f"took {elapsed:.0f} s"
        return CliRun(code, captured.out, captured.err, elapsed)

    return run


@pytest.fixture
def no_sample_cache(monkeypatch, tmp_path_factory):
    """An empty sample cache (``NAPARI_IMGREG_CACHE``, outside ``tmp_path``):
    ``sample --out`` then generates the scene (the generator a test stands in
    for) instead of copying the cached one."""
    monkeypatch.setenv("NAPARI_IMGREG_CACHE", str(tmp_path_factory.mktemp("empty_cache")))


@pytest.fixture
def sample_reference():
    """``sample_reference(photo_name) -> (workspace, truth)``: the small sample
    scene with one photo, its reference render made from its pose (the Manual
    tab's starting point); the workspace is detached afterwards."""
    from napari_imgreg.sample import load_truth, sample_scene
    from napari_imgreg.workspace import Workspace

    made = []

    def make(photo_name: str = "IMG_0001.jpg"):
        folder = sample_scene("small")
        ws = Workspace()
        made.append(ws)
        ws.open_scene(folder / "outcrop.obj", dem=folder / "dem.tif")
        ws.add_photos([folder / photo_name])
        ws.make_reference()
        return ws, load_truth(folder / photo_name)

    yield make
    for ws in made:
        ws.detach()

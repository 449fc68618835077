"""Synthetic outcrops with exactly known geology, for the interpretation tests.

A corrugated wall facing south (so a geological plane's trace on it bends
across relief), its true trace of a plane of known dip / dip direction, and a
camera looking at it from the south.
"""

from __future__ import annotations

import numpy as np
from skimage.measure import find_contours

from napari_imgreg import Intrinsics, Pose, Scene
from napari_imgreg.interpret.structural import normal_from_dip

WALL_X = (-40.0, 40.0)
WALL_Z = (0.0, 30.0)


def wall_grid(nx: int = 161, nz: int = 61, amplitude: float = 4.0, wavelength: float = 25.0):
    """Grid points (nz, nx, 3) of the wall ``y = amplitude * sin(2π x / wavelength)``."""
    x = np.linspace(*WALL_X, nx)
    z = np.linspace(*WALL_Z, nz)
    X, Z = np.meshgrid(x, z)
    Y = amplitude * np.sin(2 * np.pi * X / wavelength) + 0.1 * Z  # leans back slightly
    return np.stack([X, Y, Z], axis=-1)


def grid_faces(nz: int, nx: int, keep: np.ndarray | None = None) -> np.ndarray:
    """Two triangles per grid cell; ``keep`` (nz-1, nx-1) bool drops cells (holes)."""
    idx = np.arange(nz * nx).reshape(nz, nx)
    a, b = idx[:-1, :-1], idx[:-1, 1:]
    c, d = idx[1:, :-1], idx[1:, 1:]
    if keep is None:
        keep = np.ones(a.shape, bool)
    a, b, c, d = a[keep], b[keep], c[keep], d[keep]
    return np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])


def wall_scene(hole_x: tuple[float, float] | None = None, **kwargs) -> tuple[Scene, np.ndarray]:
    """The corrugated wall as a Scene (optionally with a vertical slot cut out)."""
    X = wall_grid(**kwargs)
    nz, nx = X.shape[:2]
    keep = None
    if hole_x is not None:
        xc = (X[:-1, :-1, 0] + X[:-1, 1:, 0]) / 2
        keep = ~((xc > hole_x[0]) & (xc < hole_x[1]))
    return Scene(X.reshape(-1, 3), grid_faces(nz, nx, keep), name="wall"), X


def true_trace(X: np.ndarray, dip: float, ddir: float, point=(0.0, 0.0, 15.0)) -> list[np.ndarray]:
    """Where the plane (dip, dip direction) through ``point`` meets the grid surface.

    The plane's signed distance is linear in position and the mesh is linear
    along grid edges, so the contour points lie exactly on plane and mesh.
    """
    n = normal_from_dip(dip, ddir)
    field = (X - np.asarray(point)) @ n
    out = []
    for c in find_contours(field, 0.0):
        rows, cols = c[:, 0], c[:, 1]
        r0, c0 = np.floor(rows).astype(int), np.floor(cols).astype(int)
        r1 = np.minimum(r0 + 1, X.shape[0] - 1)
        c1 = np.minimum(c0 + 1, X.shape[1] - 1)
        fr, fc = (rows - r0)[:, None], (cols - c0)[:, None]
        pts = ((1 - fr) * (1 - fc) * X[r0, c0] + (1 - fr) * fc * X[r0, c1]
               + fr * (1 - fc) * X[r1, c0] + fr * fc * X[r1, c1])
        out.append(pts)
    return out


def camera(distance: float = 90.0, width: int = 1200, height: int = 900, f: float = 1000.0,
           dist: tuple = ()) -> tuple[Intrinsics, Pose]:
    """A camera south of the wall at ``distance`` m, looking north at its middle."""
    intr = Intrinsics(width, height, f, f, (width - 1) / 2, (height - 1) / 2, dist)
    pose = Pose.from_attitude(0.0, -2.0, 0.0, np.array([0.0, -distance, 15.0]))
    return intr, pose


def combine(*scenes: Scene) -> Scene:
    """One Scene from several (vertices and faces concatenated)."""
    vertices, faces, n = [], [], 0
    for s in scenes:
        vertices.append(s.vertices)
        faces.append(s.faces + n)
        n += len(s.vertices)
    return Scene(np.concatenate(vertices), np.concatenate(faces), name="combined")


def flat_face(x_range, y_of, z_range=WALL_Z, n: int = 41, along: str = "x"):
    """A flat vertical face as a grid (n, n, 3): ``along="x"`` spans x with
    ``y = y_of(x, z)``; ``along="y"`` spans y (``x_range`` is then y's range)
    at ``x = y_of(y, z)``."""
    u = np.linspace(*x_range, n)
    z = np.linspace(*z_range, n)
    U, Z = np.meshgrid(u, z)
    W = y_of(U, Z)
    pts = np.stack([U, W, Z], -1) if along == "x" else np.stack([W, U, Z], -1)
    return pts


def corner_scene() -> tuple[Scene, np.ndarray, np.ndarray]:
    """Two flat faces meeting at a corner: one facing south (y = 0), one
    facing west (x = 45). A plane's trace on each is a straight line, so each
    photo's trace alone defines no plane; together they do."""
    south = flat_face((-40.0, 45.0), lambda u, z: np.zeros_like(u))
    west = flat_face((0.0, 80.0), lambda u, z: np.full_like(u, 45.0), along="y")
    scenes = []
    for g in (south, west):
        nz, nx = g.shape[:2]
        scenes.append(Scene(g.reshape(-1, 3), grid_faces(nz, nx), name="face"))
    return combine(*scenes), south, west


def camera_at(center, trend_deg: float, width: int = 1200, height: int = 900, f: float = 1000.0):
    """A level camera at ``center`` looking toward ``trend_deg``."""
    intr = Intrinsics(width, height, f, f, (width - 1) / 2, (height - 1) / 2, ())
    return intr, Pose.from_attitude(trend_deg, 0.0, 0.0, np.asarray(center, np.float64))

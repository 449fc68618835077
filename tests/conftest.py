"""Shared fixtures: small synthetic scenes with exactly known geometry."""

from __future__ import annotations

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

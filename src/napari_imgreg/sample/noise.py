"""Deterministic smooth noise, separable resampling and photographic detail.

Everything here is sampled in *physical* coordinates (metres), so a scene looks
the same whatever its grid or texture resolution: only the sampling density
changes, never the pattern.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy import ndimage

__all__ = [
    "rng_for",
    "Lattice",
    "smooth_lattice",
    "interp_matrix",
    "separable_sample",
    "smoothstep",
    "detail_image",
    "sample_detail",
    "dem_relief",
]


def rng_for(seed: int, *stream: int) -> np.random.Generator:
    """An independent random stream per (seed, component).

    Separate streams keep components independent: changing the texture
    resolution never moves a camera.
    """
    return np.random.default_rng(np.random.SeedSequence([int(seed), *map(int, stream)]))


def smoothstep(x: np.ndarray | float) -> np.ndarray:
    """Cubic Hermite step: 0 below 0, 1 above 1, smooth in between."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


# ---------------------------------------------------------------- lattices
@dataclass
class Lattice:
    """A 2-D field on a regular lattice in physical coordinates.

    Attributes
    ----------
    data : (R, C) float32 array
        Values; row ``i`` is at ``s0 + i * cell``, column ``j`` at ``x0 + j * cell``.
    x0, s0 : float
        Physical coordinates of ``data[0, 0]``, metres.
    cell : float
        Lattice spacing, metres.
    """

    data: np.ndarray
    x0: float
    s0: float
    cell: float

    def rows(self, s: np.ndarray) -> np.ndarray:
        """Fractional row positions of physical ``s`` (metres)."""
        return (np.asarray(s, np.float64) - self.s0) / self.cell

    def cols(self, x: np.ndarray) -> np.ndarray:
        """Fractional column positions of physical ``x`` (metres)."""
        return (np.asarray(x, np.float64) - self.x0) / self.cell

    def at(self, x: np.ndarray, s: np.ndarray) -> np.ndarray:
        """Bilinear values at scattered points (arrays of any equal shape)."""
        x = np.asarray(x, np.float64)
        coords = np.stack([self.rows(np.broadcast_to(s, x.shape)).ravel(), self.cols(x).ravel()])
        return ndimage.map_coordinates(self.data, coords, order=1, mode="nearest").reshape(x.shape)

    def grid(self, x: np.ndarray, s: np.ndarray) -> np.ndarray:
        """Bilinear values on the grid ``s`` (rows) × ``x`` (columns), (len(s), len(x))."""
        return separable_sample(self.data, self.rows(s), self.cols(x))


def smooth_lattice(
    rng: np.random.Generator,
    x_range: tuple[float, float],
    s_range: tuple[float, float],
    sigma_m: float | tuple[float, float],
    cells_per_sigma: float = 3.0,
) -> Lattice:
    """Gaussian-filtered white noise with unit standard deviation.

    Parameters
    ----------
    rng : Generator
        Random stream.
    x_range, s_range : (float, float)
        Physical extent to cover, metres (a margin of 3 sigma is added).
    sigma_m : float or (sigma_x, sigma_s)
        Correlation length(s) in metres; anisotropic noise (long in ``s``)
        makes gullies and weathering streaks running down a face.
    cells_per_sigma : float
        Lattice cells per (smallest) sigma.
    """
    sx, ss = (sigma_m, sigma_m) if np.isscalar(sigma_m) else sigma_m
    cell = min(sx, ss) / cells_per_sigma
    x0, s0 = x_range[0] - 3 * sx, s_range[0] - 3 * ss
    nc = int(np.ceil((x_range[1] + 3 * sx - x0) / cell)) + 1
    nr = int(np.ceil((s_range[1] + 3 * ss - s0) / cell)) + 1
    white = rng.standard_normal((nr, nc), dtype=np.float32)
    field = ndimage.gaussian_filter(white, (ss / cell, sx / cell), mode="wrap")
    field /= max(float(field.std()), 1e-12)
    return Lattice(field.astype(np.float32), x0, s0, cell)


def interp_matrix(pos: np.ndarray, n: int) -> sp.csr_matrix:
    """Sparse linear-interpolation matrix, shape (len(pos), n).

    Row ``k`` holds the two weights that interpolate a length-``n`` signal at
    fractional index ``pos[k]`` (clamped to the ends).
    """
    pos = np.clip(np.asarray(pos, np.float64).ravel(), 0.0, n - 1)
    m = len(pos)
    if n == 1:
        return sp.csr_matrix((np.ones(m, np.float32), (np.arange(m), np.zeros(m, int))), (m, 1))
    i0 = np.minimum(np.floor(pos).astype(np.int64), n - 2)
    f = (pos - i0).astype(np.float32)
    rows = np.repeat(np.arange(m), 2)
    cols = np.stack([i0, i0 + 1], axis=1).ravel()
    vals = np.stack([1.0 - f, f], axis=1).ravel()
    return sp.csr_matrix((vals, (rows, cols)), shape=(m, n))


def separable_sample(grid: np.ndarray, row_pos: np.ndarray, col_pos: np.ndarray) -> np.ndarray:
    """Bilinear resampling of a grid at a separable set of positions.

    Exact bilinear interpolation (unlike ``cv2.remap``, which quantises
    positions to 1/32 cell) done as two sparse products, so resampling a
    texture-sized grid costs O(pixels).

    Parameters
    ----------
    grid : (R, C) or (R, C, K) array
        Values on the grid.
    row_pos : (M,) array
        Fractional row indices of the output rows.
    col_pos : (N,) array
        Fractional column indices of the output columns.

    Returns
    -------
    (M, N) or (M, N, K) float32 array
    """
    g = np.asarray(grid, np.float32)
    squeeze = g.ndim == 2
    if squeeze:
        g = g[..., None]
    R, C, K = g.shape
    ar = interp_matrix(row_pos, R)
    ac = interp_matrix(col_pos, C)
    tmp = ar @ g.reshape(R, C * K)  # (M, C*K)
    M = tmp.shape[0]
    tmp = np.ascontiguousarray(tmp.reshape(M, C, K).transpose(1, 0, 2)).reshape(C, M * K)
    out = (ac @ tmp).reshape(len(np.atleast_1d(col_pos)), M, K).transpose(1, 0, 2)
    out = np.ascontiguousarray(out, dtype=np.float32)
    return out[..., 0] if squeeze else out


# ------------------------------------------------------- photographic detail
@functools.lru_cache(maxsize=4)
def detail_image(name: str) -> np.ndarray:
    """Zero-mean, unit-std log-luminance detail from a bundled scikit-image photo.

    The photo's large-scale shading is removed (ratio to a blurred copy), so
    only texture remains; the log keeps it a multiplicative luminance factor.

    Parameters
    ----------
    name : {"gravel", "brick", "grass"}
        A greyscale photo bundled with scikit-image (no download).

    Returns
    -------
    (512, 512) float32 array
    """
    import skimage.data

    img = getattr(skimage.data, name)().astype(np.float32) + 8.0
    if img.ndim == 3:
        img = img.mean(axis=2)
    d = np.log(img) - np.log(ndimage.gaussian_filter(img, 24.0, mode="reflect"))
    d -= d.mean()
    d /= max(float(d.std()), 1e-6)
    out = np.clip(d, -4.0, 4.0).astype(np.float32)
    out.setflags(write=False)
    return out


def _fold(p: np.ndarray, n: int) -> np.ndarray:
    """Mirror-tile coordinates into [0, n - 1]: mirrored tiling has no seams."""
    period = 2.0 * (n - 1)
    p = np.mod(p, period)
    return np.where(p > n - 1, period - p, p)


def sample_detail(
    name: str,
    u: np.ndarray,
    v: np.ndarray,
    metres_per_tile: float,
    angle_deg: float = 0.0,
    offset: tuple[float, float] = (0.0, 0.0),
) -> np.ndarray:
    """Sample a detail photo at physical coordinates, rotated and scaled.

    Parameters
    ----------
    name : str
        See :func:`detail_image`.
    u, v : arrays of equal shape
        Physical coordinates on the surface (e.g. along strike and down the
        face), metres.
    metres_per_tile : float
        Physical size of the 512-pixel photo.
    angle_deg : float
        Rotation of the photo on the surface.
    offset : (float, float)
        Shift in photo pixels (different seeds see different parts).

    Returns
    -------
    float32 array, shape of ``u``
        Zero-mean, unit-std detail.
    """
    import cv2

    img = detail_image(name)
    n = img.shape[0]
    a = np.radians(angle_deg)
    k = n / metres_per_tile
    px = (np.cos(a) * u - np.sin(a) * v) * k + offset[0]
    py = (np.sin(a) * u + np.cos(a) * v) * k + offset[1]
    mx = _fold(px, n).astype(np.float32)
    my = _fold(py, n).astype(np.float32)
    shape = mx.shape
    if mx.ndim != 2 or max(shape) >= 32000:
        # cv2.remap wants a 2-D map under 32767 on a side: lay points out in rows.
        width = 1024
        pad = (-mx.size) % width
        mx = np.concatenate([mx.ravel(), np.zeros(pad, np.float32)]).reshape(-1, width)
        my = np.concatenate([my.ravel(), np.zeros(pad, np.float32)]).reshape(-1, width)
    out = cv2.remap(img, mx, my, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
    return out.ravel()[: int(np.prod(shape))].reshape(shape)


# ------------------------------------------------------------- real terrain
@functools.lru_cache(maxsize=1)
def _jacksboro() -> np.ndarray:
    """The Jacksboro fault DEM bundled with matplotlib, (344, 403) float32 metres."""
    from matplotlib import cbook

    data = cbook.get_sample_data("jacksboro_fault_dem.npz")
    return np.asarray(data["elevation"], dtype=np.float32)


def dem_relief(rng: np.random.Generator, fraction: float = 0.5) -> np.ndarray:
    """A random window of a real DEM, zero-mean and unit-std.

    Parameters
    ----------
    rng : Generator
        Chooses the window, its flips and transposition.
    fraction : float
        Window size as a fraction of the DEM's shorter side.

    Returns
    -------
    (n, n) float32 array
        Smoothed (the DEM holds whole metres) relief pattern.
    """
    dem = _jacksboro()
    n = int(min(dem.shape) * fraction)
    r0 = int(rng.integers(0, dem.shape[0] - n + 1))
    c0 = int(rng.integers(0, dem.shape[1] - n + 1))
    w = dem[r0 : r0 + n, c0 : c0 + n].astype(np.float32)
    if rng.random() < 0.5:
        w = w[::-1]
    if rng.random() < 0.5:
        w = w[:, ::-1]
    if rng.random() < 0.5:
        w = w.T
    w = ndimage.gaussian_filter(w, 1.5, mode="nearest")
    w = w - w.mean()
    return np.ascontiguousarray(w / max(float(w.std()), 1e-6), dtype=np.float32)

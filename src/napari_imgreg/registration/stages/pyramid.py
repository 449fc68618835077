"""What the coarse-to-fine stages share: pyramid levels, bilinear sampling, the render
callback, the checks of their settings.

Edge alignment (:mod:`~napari_imgreg.registration.stages.edges`) and the
mutual-information refinement (:mod:`~napari_imgreg.registration.stages.dense`)
both work on a pyramid of image widths, coarse to fine: at each level the
camera is scaled, the photo resized (area averaging) and a quantity sampled
bilinearly at projected model points — distance fields for the edges, photo
values and their gradients for MI. Both render the model through the same
callback type, :class:`RenderFn`.

Pixel convention (that of :meth:`~napari_imgreg.camera.Intrinsics.scaled`):
integer coordinates are pixel centres, so pixel (0, 0) is the centre of the
first pixel and an image of width ``w`` covers ``x`` in [−0.5, w − 0.5].
Bilinear samples are defined between the outermost centres, ``x`` in
[0, w − 1] and ``y`` in [0, h − 1].
"""

from __future__ import annotations

import inspect
import warnings
from dataclasses import dataclass, fields, replace
from typing import Callable, Iterable, Protocol

import cv2
import numpy as np

from ...camera import Intrinsics, Pose
from ...render import RenderResult, render
from ...scene import Scene
from ...validate import check_ranges

__all__ = [
    "check_ranges",
    "with_keywords",
    "RenderFn",
    "scene_renderer",
    "as_render_fn",
    "level_widths",
    "resize_to",
    "PyramidLevel",
    "BilinearTaps",
    "bilinear_taps",
    "sample_bilinear",
]


# ----------------------------------------------------------- stage settings
# check_ranges is the package's one range check of parameter dataclasses
# (napari_imgreg.validate), kept importable from here.


def with_keywords(params, keywords: dict, where: str):
    """``params`` with fields replaced by keyword arguments of version 0.1.

    Until 0.2 a stage function took its settings as keyword arguments; they
    still work, with a DeprecationWarning naming ``where``. A keyword that is
    no field is a TypeError, as for any function.
    """
    if not keywords:
        return params
    names = {f.name for f in fields(params)}
    unknown = sorted(set(keywords) - names)
    if unknown:
        raise TypeError(f"{where}() got unexpected keyword argument(s) {', '.join(unknown)}")
    cls = type(params).__name__
    warnings.warn(
        f"{where}(..., {', '.join(sorted(keywords))}=...) is deprecated since napari-imgreg "
        f"0.2; pass params={cls}(...)", DeprecationWarning, stacklevel=3)
    return replace(params, **keywords)


# ------------------------------------------------------------ render callback
class RenderFn(Protocol):
    """``render_fn(intrinsics, pose, scale) -> RenderResult``: the model seen by a camera.

    ``intrinsics`` is the full-size camera (edge alignment may pass one widened
    beyond the photo, MI refinement one with a refined focal length), ``pose``
    the ``cam_from_world`` and ``scale`` the resolution factor, as in
    :func:`~napari_imgreg.render.render`. A stage uses only the render's
    ``xyz``, ``mask``, ``normal``, ``depth``, ``rgb`` and camera, so a
    renderer may relight (sun-lit renders) or ignore ``intrinsics`` changes
    it cannot honour.
    """

    def __call__(self, intrinsics: Intrinsics, pose: Pose, scale: float, /) -> RenderResult:
        ...


def scene_renderer(scene: Scene, mode: str = "auto") -> RenderFn:
    """The default :class:`RenderFn`: :func:`~napari_imgreg.render.render` of ``scene``."""
    def render_fn(intrinsics: Intrinsics, pose: Pose, scale: float) -> RenderResult:
        return render(scene, intrinsics, pose, scale=scale, mode=mode)
    return render_fn


def _positional_capacity(fn: Callable) -> tuple[int, float]:
    """(required, accepted) positional arguments of ``fn``; (0, inf) when unknown."""
    try:
        sig = inspect.signature(fn)
    except (TypeError, ValueError):
        return 0, float("inf")
    required, accepted = 0, 0.0
    for p in sig.parameters.values():
        if p.kind is p.VAR_POSITIONAL:
            return required, float("inf")
        if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD):
            accepted += 1
            required += p.default is p.empty
    return required, accepted


def as_render_fn(render_fn: Callable, scene: Scene | None, where: str) -> RenderFn:
    """``render_fn`` as a :class:`RenderFn`, adapting the callbacks of version 0.1.

    Until 0.2 edge alignment called ``render_fn(scene, intrinsics, pose,
    scale)`` and MI refinement ``render_fn(pose, scale)``; such a callable
    still works, with a DeprecationWarning naming ``where``.
    """
    required, accepted = _positional_capacity(render_fn)
    if required >= 4:
        legacy, adapted = "render_fn(scene, intrinsics, pose, scale)", (
            lambda intr, pose, scale: render_fn(scene, intr, pose, scale))
    elif accepted == 2:
        legacy, adapted = "render_fn(pose, scale)", (
            lambda intr, pose, scale: render_fn(pose, scale))
    else:
        return render_fn
    warnings.warn(
        f"{where}: a {legacy} callback is deprecated since napari-imgreg 0.2; "
        "pass render_fn(intrinsics, pose, scale) (registration.stages.pyramid.RenderFn)",
        DeprecationWarning, stacklevel=3)
    return adapted


# ------------------------------------------------------------- pyramid levels
def level_widths(levels: Iterable[int], full_width: int) -> list[int]:
    """The distinct level widths, px, coarse to fine, none wider than ``full_width``."""
    return sorted({min(int(w), full_width) for w in levels})


def resize_to(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``image`` resized to ``size`` = (width, height) by area averaging (itself when it fits)."""
    if image.shape[1] == size[0] and image.shape[0] == size[1]:
        return image
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)


class PyramidLevel:
    """One image size of a coarse-to-fine pyramid.

    Parameters
    ----------
    intrinsics : Intrinsics
        The full-size camera.
    scale : float
        Level resolution over the full resolution (1.0: full size).

    Attributes
    ----------
    scale : float
    intr : Intrinsics
        The camera at this level (pixel centres kept at integers).
    """

    def __init__(self, intrinsics: Intrinsics, scale: float) -> None:
        self.scale = scale
        self.intr = intrinsics.scaled(scale)

    @property
    def width(self) -> int:
        """Level width, px."""
        return self.intr.width

    @property
    def height(self) -> int:
        """Level height, px."""
        return self.intr.height

    def scaled(self, intrinsics: Intrinsics) -> Intrinsics:
        """Another full-size camera (e.g. with a refined focal length) at this level."""
        return intrinsics.scaled(self.scale)

    def resize(self, image: np.ndarray) -> np.ndarray:
        """A full-size (H, W[, C]) image at this level's size (area averaging)."""
        return resize_to(image, (self.width, self.height))


# --------------------------------------------------------- bilinear sampling
@dataclass
class BilinearTaps:
    """Where and with what weights points are sampled bilinearly in flat images.

    Attributes
    ----------
    index : (N,) intp array
        Flat index of each point's upper-left neighbour (row-major, plus the
        layer's offset in a stack).
    index_below : (N,) intp array
        ``index`` plus one row.
    fx, fy : (N,) float arrays
        Position within the pixel square, in [0, 1].
    """

    index: np.ndarray
    index_below: np.ndarray
    fx: np.ndarray
    fy: np.ndarray

    def sample(self, flat: np.ndarray) -> np.ndarray:
        """Bilinear values of a flat image (or stack) at the points, (N,).

        The result has the common type of ``flat`` and the weights.
        """
        # np.take: several times faster than fancy indexing for 1-D gathers.
        a, b = np.take(flat, self.index), np.take(flat, self.index + 1)
        c, d = np.take(flat, self.index_below), np.take(flat, self.index_below + 1)
        top = a + self.fx * (b - a)
        return top + self.fy * (c + self.fx * (d - c) - top)


def bilinear_taps(x: np.ndarray, y: np.ndarray, shape: tuple[int, int],
                  layer: np.ndarray | None = None, dtype=None) -> BilinearTaps:
    """Bilinear taps of points inside an image of ``shape`` = (H, W) (H, W ≥ 2).

    Parameters
    ----------
    x, y : (N,) float arrays
        Pixel positions (centre convention, see the module notes), within
        [0, W − 1] × [0, H − 1]: the caller masks points outside.
    shape : (int, int)
        (height, width) of one image.
    layer : (N,) int array, optional
        Image of a (L, H, W) stack each point samples.
    dtype : numpy dtype, optional
        Type of the weights (default: that of ``x − floor(x)``); float32
        halves the memory traffic of large gathers.

    Returns
    -------
    BilinearTaps
    """
    h, w = shape
    # Exact weights: cv2.remap rounds positions to 1/32 px, which makes an
    # objective a staircase under an optimiser's small steps.
    x0 = np.minimum(np.floor(x).astype(np.intp), w - 2)
    y0 = np.minimum(np.floor(y).astype(np.intp), h - 2)
    fx, fy = x - x0, y - y0
    if dtype is not None:
        fx, fy = fx.astype(dtype), fy.astype(dtype)
    index = y0 * w + x0
    if layer is not None:
        index = layer.astype(np.intp) * (h * w) + index
    return BilinearTaps(index, index + w, fx, fy)


def sample_bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray, *,
                    layer: np.ndarray | None = None, outside: float = np.nan) -> np.ndarray:
    """Bilinear samples of an image at (x, y), ``outside`` beyond its outermost pixel centres.

    Parameters
    ----------
    image : (H, W) or (L, H, W) array
        One image, or a stack sampled at ``layer``.
    x, y : (N,) float arrays
        Pixel positions (centre convention, see the module notes); non-finite
        positions are outside.
    layer : (N,) int array, optional
        With a stack: the image each point samples.
    outside : float
        Value off the image.

    Returns
    -------
    (N,) array
        Exact for a linear ramp ``a + b x + c y`` inside the image.
    """
    h, w = image.shape[-2:]
    inside = (x >= 0) & (y >= 0) & (x <= w - 1) & (y <= h - 1) & np.isfinite(x) & np.isfinite(y)
    xs = np.where(inside, x, 0.0)
    ys = np.where(inside, y, 0.0)
    taps = bilinear_taps(xs, ys, (h, w), layer if image.ndim == 3 else None)
    return np.where(inside, taps.sample(image.reshape(-1)), outside)

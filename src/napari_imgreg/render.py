"""Synthetic images of a Scene: colour and per-pixel 3D coordinates by ray casting.

One ray per pixel centre is cast through Embree. The hit distance gives the 3D
point (so lifting an image feature to 3D is a look-up in ``xyz``, not another
ray cast); Embree's barycentric ``(u, v)`` and primitive id give the texture
coordinate, which is sampled bilinearly from the texture.
"""

from __future__ import annotations

import functools
import math
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from .camera import Intrinsics, Pose, check_pose, scaled_size
from .errors import InputError
from .scene import Scene, has_colours, ray_threads
from .validate import FieldValueError, check_number, check_render_size

__all__ = ["RenderResult", "render", "RENDER_MODES"]

RENDER_MODES = ("auto", "color", "shaded", "color_shaded", "normal")

# Grey used for untextured, uncoloured surfaces.
_GREY = 180.0


@dataclass
class RenderResult:
    """A synthetic image and its per-pixel geometry.

    Attributes
    ----------
    rgb : (H, W, 3) uint8 array
        Colour; ``background`` where nothing is hit.
    xyz : (H, W, 3) float32 array
        World (local-frame) coordinates of the surface seen at each pixel
        centre, metres; NaN where nothing is hit.
    depth : (H, W) float32 array
        Depth along the optical axis (camera z), metres; NaN where no hit.
    normal : (H, W, 3) float32 array
        Unit surface normal (world frame) turned toward the camera; 0 where
        no hit.
    face_id : (H, W) int32 array
        Index of the triangle seen, -1 where no hit.
    mask : (H, W) bool array
        True where the surface is hit.
    intrinsics : Intrinsics
        The camera the image was rendered with (at the rendered resolution).
    cam_from_world : Pose
        The pose it was rendered from.
    timings_s : dict
        Seconds spent casting and shading (``cast_shade``), sampling the
        texture (``texture``) and in all (``total``).
    shading_share : float or None
        Of a render relit for another sun
        (:func:`~napari_imgreg.registration.stages.relight.render_sunlit`):
        the share of its fine contrast that is synthetic shading rather than
        the model's own colours, in [0, 1] (1 for an untextured mesh). None:
        not relit. (The registration also gives 1 to a plain render with no
        photographed colours, grey shading or a scan's intensity: none of the
        photo's light is in it.)
    """

    rgb: np.ndarray
    xyz: np.ndarray
    depth: np.ndarray
    normal: np.ndarray
    face_id: np.ndarray
    mask: np.ndarray
    intrinsics: Intrinsics
    cam_from_world: Pose
    timings_s: dict = field(default_factory=dict)
    shading_share: float | None = None

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width) in pixels."""
        return self.mask.shape

    @property
    def coverage(self) -> float:
        """Fraction of pixels that see the surface."""
        return float(self.mask.mean())

    def lift(self, pixels: np.ndarray, max_depth_jump: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
        """3D points under sub-pixel positions, by bilinear look-up in ``xyz``.

        Parameters
        ----------
        pixels : (N, 2) array
            Positions (x, y) in this render's pixels.
        max_depth_jump : float
            Reject a position whose four neighbouring depths spread more than
            this fraction of their mean: it straddles an occluding edge, where
            interpolating would invent a point in mid-air.

        Returns
        -------
        points : (N, 3) float64 array
            Model-frame points (NaN where rejected).
        valid : (N,) bool array
        """
        px = np.asarray(pixels, np.float64).reshape(-1, 2)
        h, w = self.shape
        x, y = px[:, 0], px[:, 1]
        inside = (x >= 0) & (y >= 0) & (x <= w - 1) & (y <= h - 1)
        x0 = np.clip(np.floor(x).astype(int), 0, max(w - 2, 0))
        y0 = np.clip(np.floor(y).astype(int), 0, max(h - 2, 0))
        fx = np.clip(x - x0, 0, 1)[:, None]
        fy = np.clip(y - y0, 0, 1)[:, None]
        corners = [(y0, x0), (y0, x0 + 1), (y0 + 1, x0), (y0 + 1, x0 + 1)]
        weights = [(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy]
        depths = np.stack([self.depth[r, c] for r, c in corners], axis=1)
        finite = np.isfinite(depths).all(axis=1)
        smooth = np.zeros(len(px), bool)
        d = depths[finite]
        smooth[finite] = (d.max(axis=1) - d.min(axis=1)) <= max_depth_jump * d.mean(axis=1)
        valid = inside & finite & smooth
        pts = sum(wgt * self.xyz[r, c].astype(np.float64) for (r, c), wgt in zip(corners, weights))
        pts = np.where(valid[:, None], pts, np.nan)
        return pts, valid


@functools.lru_cache(maxsize=8)
def _camera_rays(intrinsics: Intrinsics) -> np.ndarray:
    """Unit camera-frame ray directions of every pixel centre, (H*W, 3) float32.

    NaN for a pixel that no ray reaches: beyond where the distortion
    polynomial folds back (:func:`~napari_imgreg.render_points.unfolded_rays`).
    Cached: a registration renders the same camera many times.
    """
    w, h = intrinsics.width, intrinsics.height
    if intrinsics.has_distortion:
        from .render_points import unfolded_rays

        cols, rows = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        pixels = np.stack([cols.ravel(), rows.ravel()], axis=1)
        d = intrinsics.normalized_rays(pixels)
        d[~unfolded_rays(intrinsics, pixels, d)] = np.nan
    else:
        xn = (np.arange(w, dtype=np.float64) - intrinsics.cx) / intrinsics.fx
        yn = (np.arange(h, dtype=np.float64) - intrinsics.cy) / intrinsics.fy
        d = np.empty((h, w, 3))
        d[..., 0] = xn[None, :]
        d[..., 1] = yn[:, None]
        d[..., 2] = 1.0
        d = d.reshape(-1, 3)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    out = d.astype(np.float32)
    out.setflags(write=False)
    return out


def render(
    scene: Scene,
    intrinsics: Intrinsics,
    cam_from_world: Pose,
    scale: float = 1.0,
    mode: str = "auto",
    background: tuple[int, int, int] = (0, 0, 0),
    light_direction: np.ndarray | None = None,
    ambient: float = 0.35,
    detail: str | None = None,
) -> RenderResult:
    """Render colour and per-pixel geometry of a scene from a camera pose.

    Parameters
    ----------
    scene : Scene or CloudScene, or path
        The textured surface (a path is loaded by :meth:`Scene.load`); its
        ray engine is built on first use. A point cloud is drawn by :func:`napari_imgreg.render_points.splat_cloud`.
    intrinsics : Intrinsics
        The camera (its distortion is honoured: the render matches the photo).
    cam_from_world : Pose
        World-to-camera pose (finite, ``R`` a rotation).
    scale : float
        Render at ``scale`` times the camera's resolution (e.g. 0.25 for a
        quick preview); the result's ``intrinsics`` is the scaled camera.
        Positive and finite; the render may have at most
        :data:`~napari_imgreg.validate.MAX_RENDER_PIXELS` pixels.
    mode : {"auto", "color", "shaded", "color_shaded", "normal"}
        ``color``: texture or vertex colours (grey when the mesh has none);
        ``shaded``: grey Lambert shading; ``color_shaded``: colour times
        shading; ``normal``: the normal map as colour; ``auto``: ``color`` for
        coloured meshes, ``shaded`` otherwise.
    background : (3,) ints
        RGB where nothing is hit.
    light_direction : (3,) array, optional
        Direction *toward* the light, world frame, for the shaded modes.
        Default: from over the photographer's left shoulder.
    ambient : float
        Ambient share of the shading, in [0, 1].
    detail : {None, "auto", "full"}
        A point cloud only: ``"full"`` draws every point, ``"auto"`` a large
        cloud's level of detail (each visible block at the coarsest level
        whose splats stay about a pixel wide); ``None``: the cloud's
        ``CloudParams.render_detail`` (default ``"auto"``). Meshes ignore it.

    Returns
    -------
    RenderResult

    Raises
    ------
    InputError
        A scale that is not a positive number, a render larger than
        :data:`~napari_imgreg.validate.MAX_RENDER_PIXELS`, an unknown mode, a
        pose that is not finite or not a rotation, ``ambient`` outside [0, 1]
        or a light direction that is not a non-zero 3-vector.
    """
    if mode not in RENDER_MODES:
        raise InputError(f"render mode must be one of {', '.join(RENDER_MODES)}, not {mode!r}")
    if isinstance(scene, (str, os.PathLike)):
        scene = Scene.load(scene)
    check_pose(cam_from_world, "cam_from_world")
    try:
        ambient = check_number(ambient, "ambient", 0.0, 1.0)
    except FieldValueError as exc:
        raise InputError(f"render {exc}") from None
    if light_direction is not None:
        light_direction = np.asarray(light_direction, np.float64)
        if (light_direction.shape != (3,) or not np.all(np.isfinite(light_direction))
                or np.linalg.norm(light_direction) == 0):
            raise InputError("render light_direction must be a finite, non-zero (3,) vector, "
                             f"got {light_direction.tolist()}")
    if getattr(scene, "is_cloud", False):  # a lidar scan: splats, same result
        from .render_points import splat_cloud

        return RenderResult(**splat_cloud(scene, intrinsics, cam_from_world, scale=scale,
                                          mode=mode, background=background,
                                          light_direction=light_direction, ambient=ambient,
                                          detail=detail))
    if mode == "auto":
        mode = "color" if has_colours(scene) else "shaded"
    # Bounded work: refuse a render too large for memory before allocating it
    # (``render --scale 100`` of a 12 MP photo would need 7 TB).
    try:
        scale = check_number(scale, "scale", 0.0, math.inf, low_open=True)
    except FieldValueError as exc:
        raise InputError(f"render scale {exc.problem}") from None
    check_render_size(*scaled_size(intrinsics.width, intrinsics.height, scale))
    intr = intrinsics.scaled(scale)
    h, w = intr.height, intr.width
    n_pix = h * w
    t0 = time.perf_counter()
    rays_cam = _camera_rays(intr)
    R32 = cam_from_world.R.astype(np.float32)
    center = cam_from_world.center.astype(np.float32)
    engine = scene.engine  # built once per scene, before the workers start
    light = None
    if mode in ("shaded", "color_shaded"):
        light = _light_direction(cam_from_world.R) if light_direction is None else light_direction
        light = np.asarray(light, np.float64)
        light = (light / np.linalg.norm(light)).astype(np.float32)
    use_texture = mode in ("color", "color_shaded") and scene.has_texture
    use_colors = (
        mode in ("color", "color_shaded") and not use_texture and scene.vertex_colors is not None
    )
    fnormals = scene.face_array("normals")
    fuv = scene.face_array("uv").reshape(-1, 6) if use_texture else None
    fcol = scene.face_array("colors").reshape(-1, 9) if use_colors else None
    tex_h, tex_w = scene.texture.shape[:2] if use_texture else (0, 0)
    wraps = use_texture and scene.uv_wraps
    bg = np.asarray(background, np.uint8)

    xyz = np.empty((n_pix, 3), np.float32)
    depth = np.empty(n_pix, np.float32)
    normal = np.empty((n_pix, 3), np.float32)
    face_id = np.empty(n_pix, np.int32)
    rgb = np.empty((n_pix, 3), np.uint8)
    map_xy = np.empty((n_pix, 2), np.float32) if use_texture else None
    shading = np.empty(n_pix, np.float32) if (use_texture and light is not None) else None

    def cast_and_shade(lo: int, hi: int) -> None:
        # One block of pixels: Embree and large numpy operations release the
        # GIL, so blocks run in parallel on all cores.
        d = rays_cam[lo:hi] @ R32  # world directions (R.T @ d_cam, row-wise)
        unreached = np.isnan(d[:, 0]) if intr.has_distortion else None
        if unreached is not None:
            d[unreached] = R32[2]  # any direction; the pixel stays empty
        origins = np.empty_like(d)
        origins[:] = center
        res = engine.run(origins, d, output=1)
        face = res["primID"]
        if unreached is not None:
            face[unreached] = -1
        miss = face < 0
        face_id[lo:hi] = face
        face_id[lo:hi][miss] = -1
        face[miss] = 0
        dist = res["tfar"]
        dist[miss] = np.nan
        # float32 keeps ~10 µm at 100 m; the local frame keeps numbers small.
        p = d * dist[:, None]
        p += center
        xyz[lo:hi] = p
        depth[lo:hi] = dist * rays_cam[lo:hi, 2]
        nrm = np.take(fnormals, face, axis=0)  # take: ~2x faster than fancy indexing
        nrm[np.einsum("ij,ij->i", nrm, d) > 0] *= -1  # turn toward the camera
        nrm[miss] = 0
        normal[lo:hi] = nrm
        bu = res["u"]
        bv = res["v"]
        shade = None
        if light is not None:
            shade = ambient + (1.0 - ambient) * np.clip(nrm @ light, 0.0, None)
        if use_texture:
            c = np.take(fuv, face, axis=0)  # (n, 6): u0 v0 u1 v1 u2 v2
            tu = c[:, 0] + bu * (c[:, 2] - c[:, 0]) + bv * (c[:, 4] - c[:, 0])
            tv = c[:, 1] + bu * (c[:, 3] - c[:, 1]) + bv * (c[:, 5] - c[:, 1])
            if wraps:
                tu -= np.floor(tu)
                tv -= np.floor(tv)
            # Texel centres sit at (i + 0.5) / size; v = 0 is the bottom row.
            map_xy[lo:hi, 0] = tu * tex_w - 0.5
            map_xy[lo:hi, 1] = (1.0 - tv) * tex_h - 0.5
            if shading is not None:
                shading[lo:hi] = shade
            return
        if mode == "normal":
            colours = nrm * 127.5 + 127.5
        elif fcol is not None:
            c = np.take(fcol, face, axis=0).reshape(-1, 3, 3)
            colours = (
                (1.0 - bu - bv)[:, None] * c[:, 0] + bu[:, None] * c[:, 1] + bv[:, None] * c[:, 2]
            )
        else:
            colours = np.full((hi - lo, 3), _GREY, np.float32)
        if shade is not None:
            colours = colours * shade[:, None]
        out = np.clip(colours + 0.5, 0, 255).astype(np.uint8)
        out[miss] = bg
        rgb[lo:hi] = out

    n_threads = ray_threads()
    n_blocks = 1 if (n_pix < 100_000 or n_threads == 1) else 4 * n_threads
    bounds = np.linspace(0, n_pix, n_blocks + 1).astype(int)
    if n_blocks == 1:
        cast_and_shade(0, n_pix)
    else:
        with ThreadPoolExecutor(n_threads) as pool:
            list(pool.map(cast_and_shade, bounds[:-1], bounds[1:]))
    t1 = time.perf_counter()

    mask = (face_id >= 0).reshape(h, w)
    rgb = rgb.reshape(h, w, 3)
    if use_texture:
        import cv2  # here: ``import napari_imgreg`` does not load OpenCV

        border = cv2.BORDER_WRAP if wraps else cv2.BORDER_REPLICATE
        # One bilinear look-up for all pixels (OpenCV runs it multi-threaded).
        rgb = cv2.remap(
            scene.texture, map_xy.reshape(h, w, 2), None,
            interpolation=cv2.INTER_LINEAR, borderMode=border,
        )
        if shading is not None:
            rgb = np.clip(rgb * shading.reshape(h, w, 1) + 0.5, 0, 255).astype(np.uint8)
        rgb[~mask] = bg
    t2 = time.perf_counter()

    return RenderResult(
        rgb=rgb,
        xyz=xyz.reshape(h, w, 3),
        depth=depth.reshape(h, w),
        normal=normal.reshape(h, w, 3),
        face_id=face_id.reshape(h, w),
        mask=mask,
        intrinsics=intr,
        cam_from_world=cam_from_world,
        timings_s={"cast_shade": t1 - t0, "texture": t2 - t1, "total": t2 - t0},
    )


def _light_direction(R: np.ndarray) -> np.ndarray:
    """Toward a light above and to the left of the camera, world frame."""
    # Camera frame: x right, y down, z forward; the light sits up-left-behind.
    toward_light_cam = np.array([-0.4, -0.6, -0.7])
    return R.T @ toward_light_cam

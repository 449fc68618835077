"""A generated sample outcrop: a layered cliff photographed from the ground.

Deterministic from a seed and made without network access, it is the test
case of the package: a textured mesh with its georeference and DEM, photos
with their phone sensor records, and the ground truth every later measure is
checked against (true camera poses, check points, bedding and fault planes
and their traces on the surface).

>>> from napari_imgreg.sample import sample_scene, load_truth   # doctest: +SKIP
>>> folder = sample_scene("small")                               # doctest: +SKIP
>>> truth = load_truth(folder / "IMG_0001.jpg")                  # doctest: +SKIP

Folder layout (see :func:`generate_outcrop`)::

    scene.json                 manifest: size, seed, files, photos, examples, survey sun
    survey.json                the sun the texture was photographed under (true azimuth, time)
    outcrop.obj/.mtl           the model (local ENU metres)
    outcrop_texture.jpg        its texture: albedo x survey-day shading
    albedo.png                 reflectance only (for synthesising photos)
    georef.json, dem.tif       EPSG:32630 frame, 5 m DEM (top surface)
    geology.json               bedding, beds, fault (the truth)
    truth_lines.geojson        true 3-D traces of bed boundaries and the fault
    IMG_0001.jpg               photo (EXIF: camera, focal length, time, GPS)
    IMG_0001.json              phone sensor record (contract §3): the prior
    IMG_0001.truth.json        true camera and pose, conditions, check points
    IMG_0001.lines.geojson     an example drawing: the visible true contacts and
                               fault as a geologist draws them (pixel GeoJSON, :mod:`.drawing`)
    IMG_0001.pairs.csv         example control points: eight surveyed targets
                               (easting, northing, elevation) and where they were
                               clicked in the photo (±1 px), for ``register --pairs``
    orient/                    an example survey for ``napari-imgreg orient``
                               (cameras.xml, phone.csv, model.obj, truth.json; :mod:`.survey`)
    scan.laz, scan.json        optional (``generate_outcrop(..., scan=ScanSpec())``):
                               a terrestrial laser scan of the surface (:mod:`.scan`)
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from .._atomic import atomic_path, atomic_write, umask
from .._json import dump as strict_json_dump
from .._platform import cache_root
from ..scene import ray_threads
from ..camera import Intrinsics, Pose
from .noise import rng_for
from .suntime import time_for_sun
from .outcrop import (
    SIZES,
    Outcrop,
    OutcropSpec,
    build_geometry,
    build_texture,
    dip_from_normal,
    plane_normal,
    quantize_vertices,
    write_model,
)
from .drawing import drawing_geojson, visible_stretches
from .photo import (
    CONDITION_PRESETS,
    PhotoConditions,
    camera_intrinsics,
    make_exif,
    sample_poses,
    select_check_points,
    sun_vector,
    synthesize_photo,
)

__all__ = [
    "GENERATOR_VERSION",
    "MODEL_VERSION",
    "SIZES",
    "OutcropSpec",
    "PhotoConditions",
    "PhotoTruth",
    "CONDITION_PRESETS",
    "SceneTruth",
    "generate_outcrop",
    "write_outcrop_folder",
    "check_outcrop_folder",
    "sample_scene",
    "cache_dir",
    "verify_sample_scene",
    "write_cache_manifest",
    "CACHE_MANIFEST",
    "load_truth",
    "truth_pairs",
    "write_survey",
    "plane_normal",
    "dip_from_normal",
    "truth_lines",
]

log = logging.getLogger(__name__)

#: Bump when the generated content changes: cached scenes are keyed by it.
#: 6: an example drawing per photo and the orientation example (``orient/``).
#: 7: example control points per photo (``IMG_0001.pairs.csv``).
GENERATOR_VERSION = "7"
#: Version of the model (mesh, texture, cameras, priors, check points) alone:
#: the benchmark, which re-makes the photos, keys its cache on it.
MODEL_VERSION = "3"

# Random stream ids (see noise.rng_for).
_S_POSES, _S_PHOTO = 4, 100
_S_DRAWING, _S_ORIENT_SURVEY = 300, 301
_S_PAIRS = 302
#: The example control points: how many, and the click error (Gaussian σ, pixels).
EXAMPLE_PAIRS, EXAMPLE_PAIR_CLICK_PX = 8, 1.0
#: Sub-folder of the orientation example (see :func:`.survey.write_orientation_example`).
ORIENT_EXAMPLE_DIR = "orient"


# ----------------------------------------------------------------- truth
def truth_lines(outcrop: Outcrop, min_length_m: float = 5.0) -> dict[str, Any]:
    """Where the bed boundaries and the fault meet the exposed rock face.

    The stratigraphic height (and the signed fault distance) is linear in
    position, and the model is linear along every grid edge, so contouring it
    on the grid (marching squares, in ``(s, x)`` parameter space) gives points
    exactly on both the plane and the mesh. Each fault block is contoured on
    its own, so no trace runs along the fault's offset.

    Returns
    -------
    dict
        GeoJSON FeatureCollection of LineStrings ``[x, y, z]`` (local metres);
        ``properties.label`` is ``"bed_boundary"`` or ``"fault"``.
    """
    from scipy import ndimage
    from skimage.measure import find_contours

    geo = outcrop.geology
    X = outcrop.X
    exposed = outcrop.rock > 0.5
    h = geo.h_strat(X)
    fd = geo.fault_distance(X)
    features: list[dict[str, Any]] = []

    def lines_of(field: np.ndarray, level: float) -> list[np.ndarray]:
        out = []
        for c in find_contours(field, level):
            if len(c) < 3:
                continue
            pts = np.stack(
                [ndimage.map_coordinates(X[..., k], c.T, order=1) for k in range(3)], axis=1
            )
            if np.linalg.norm(np.diff(pts, axis=0), axis=1).sum() >= min_length_m:
                out.append(pts)
        return out

    for block, sel in (("footwall", fd <= 0), ("hanging_wall", fd > 0)):
        field = np.where(exposed & sel, h, np.nan)
        if not np.isfinite(field).any():
            continue
        lo, hi = np.nanmin(field), np.nanmax(field)
        for k, b in enumerate(geo.boundaries):
            if not lo < b < hi:
                continue
            below = "sandstone" if geo.lithology[k] == 0 else "mudstone"
            above = "sandstone" if geo.lithology[k + 1] == 0 else "mudstone"
            for pts in lines_of(field, b):
                features.append(_feature(pts, {
                    "label": "bed_boundary", "boundary_index": k, "h": float(b),
                    "below": below, "above": above, "block": block,
                }))
    for pts in lines_of(np.where(exposed, fd, np.nan), 0.0):
        features.append(_feature(pts, {"label": "fault"}))
    return {"type": "FeatureCollection", "features": features}


def _feature(pts: np.ndarray, props: dict[str, Any]) -> dict[str, Any]:
    return {
        "type": "Feature",
        "geometry": {"type": "LineString", "coordinates": np.round(pts, 4).tolist()},
        "properties": props,
    }


def _make_dem(scene, spec: OutcropSpec, georef):
    """The top surface sampled by vertical rays on a coarse grid, in CRS heights."""
    from ..geo import DEM

    lo, hi = scene.bounds
    cell = spec.dem_cell_m
    e0, n0, h0 = georef.origin
    # Cell centres on whole multiples of the cell size in the CRS.
    es = np.arange(np.ceil((lo[0] + e0) / cell) * cell, hi[0] + e0 + 1e-6, cell)
    ns = np.arange(np.floor((hi[1] + n0) / cell) * cell, lo[1] + n0 - 1e-6, -cell)
    E, N = np.meshgrid(es - e0, ns - n0)
    top = float(hi[2]) + 10.0
    origins = np.stack([E.ravel(), N.ravel(), np.full(E.size, top)], axis=1)
    hits = scene.cast_rays(origins, np.tile([0.0, 0.0, -1.0], (E.size, 1)))
    heights = np.where(hits.hit, top - hits.distance.astype(np.float64), np.nan).reshape(E.shape)
    return DEM.from_array(heights + h0, float(es[0]), float(ns[0]), cell, cell,
                          crs=georef.crs, source="dem.tif")


def _write_json(path: Path, data: Any, indent: int | None = 1) -> None:
    with atomic_write(path, encoding="utf-8") as fh:
        strict_json_dump(data, fh, indent=indent, separators=None if indent else (",", ":"))
        fh.write("\n")


def _clipped_normal(rng: np.random.Generator, sigma: float, size: int | None = None) -> Any:
    """Gaussian noise clipped at 3 sigma (a sane prior, never a wild outlier)."""
    return np.clip(rng.normal(0.0, sigma, size), -3 * sigma, 3 * sigma)


# -------------------------------------------------------------- generate
def generate_outcrop(
    out_dir: str | os.PathLike,
    size: str = "small",
    seed: int = 0,
    spec: OutcropSpec | None = None,
    scan: Any = None,
) -> Path:
    """Generate the sample outcrop scene into a folder.

    Parameters
    ----------
    out_dir : path-like
        Folder to write (created; existing files of the same names are
        replaced, each atomically).
    size : {"small", "large"}
        Named size (ignored for the numbers when ``spec`` is given, but
        recorded in ``scene.json``).
    seed : int
        Everything random derives from it: same seed, same files.
    spec : OutcropSpec, optional
        Full control (other geometry, more photos, ...).
    scan : napari_imgreg.sample.scan.ScanSpec, optional
        Also write a terrestrial laser scan of the surface (``scan.laz``,
        ``scan.json``; needs ``laspy[lazrs]``).

    Returns
    -------
    Path
        ``out_dir``.
    """
    from ..geo import Georef
    from PIL import Image

    from .survey import write_orientation_example

    t_start = time.perf_counter()
    spec = spec if spec is not None else OutcropSpec.for_size(size)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}

    t0 = time.perf_counter()
    oc = build_geometry(spec, seed)
    quantize_vertices(oc)
    timings["geometry"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    build_texture(oc)
    timings["texture"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    files = write_model(oc, out)
    georef = Georef(spec.crs, np.asarray(spec.origin, np.float64))
    georef.save(out / "georef.json")
    scene = oc.scene("albedo")
    dem = _make_dem(scene, spec, georef)
    dem.save_geotiff(out / "dem.tif")
    _write_json(out / "geology.json", oc.geology.to_dict())
    true_lines = truth_lines(oc)
    _write_json(out / "truth_lines.geojson", true_lines, indent=None)
    timings["write_model"] = time.perf_counter() - t0
    files.update({"georef": "georef.json", "dem": "dem.tif", "geology": "geology.json",
                  "truth_lines": "truth_lines.geojson"})
    if scan is not None:  # the photos' own surface, scanned (issue 16)
        from .scan import scan_outcrop

        t0 = time.perf_counter()
        files.update(scan_outcrop(oc, scene, georef, out, scan))
        timings["scan"] = time.perf_counter() - t0

    # ---- photos
    t0 = time.perf_counter()
    intr = camera_intrinsics(*spec.photo_size, spec.focal_length_mm, spec.sensor_size_mm)
    prof = oc.profile
    s_mid = 0.5 * (prof.knots["foot"] + prof.knots["top"])
    y_mid = float(np.interp(s_mid, prof.s, prof.y))
    y_south = float(prof.y[0])

    def bay(x: float) -> float:
        return -spec.bay_depth_m * (2.0 * x / spec.width_m) ** 2

    face_rock = oc.face_rock
    poses = sample_poses(
        scene, intr,
        face_line=lambda x: y_mid + bay(x),
        ground_y_min=lambda x: y_south + bay(x),
        face_rock=face_rock,
        n=spec.n_photos,
        rng=rng_for(seed, _S_POSES),
        x_half=spec.width_m / 2.0,
        distance_m=spec.camera_distance_m,
        trend_range_deg=spec.trend_range_deg,
        plunge_range_deg=spec.plunge_range_deg,
        roll_range_deg=spec.roll_range_deg,
        height_above_ground_m=spec.height_above_ground_m,
    )
    timings["poses"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    diag = float(np.hypot(*spec.sensor_size_mm))
    f35 = int(round(spec.focal_length_mm * np.hypot(36.0, 24.0) / diag))
    vertex_normals = oc.vertex_normals

    def make_photo(k: int) -> dict[str, str]:
        pose, fractions = poses[k]
        name = f"IMG_{k + 1:04d}"
        rng = rng_for(seed, _S_PHOTO + k)  # one stream per photo: order-independent
        strength = float(rng.uniform(*spec.condition_strength))
        cond = PhotoConditions.from_rng(
            rng, strength,
            survey_sun=(spec.survey_sun_azimuth_deg, spec.survey_sun_elevation_deg),
            survey_ambient=spec.survey_ambient,
        )
        # The capture time is when the sun stood where this photo is lit
        # from; the photo takes that instant's sun (a few hundredths of a
        # degree from the one drawn), so its EXIF time gives its light.
        sun_time = time_for_sun(cond.sun, georef, pose.center, year=spec.photo_year)
        cond = replace(cond, sun_azimuth_deg=sun_time.azimuth_deg,
                       sun_elevation_deg=sun_time.elevation_deg)
        img = synthesize_photo(scene, intr, pose, cond, vertex_normals, spec.supersample)
        record, prior = _sensor_record(spec, intr, pose, dem, georef, rng)
        lat, lon, alt = georef.local_to_geodetic(prior["position"])
        exif = make_exif(spec.camera_make, spec.camera_model, spec.focal_length_mm, f35,
                         sun_time.when, lat, lon, alt, intr.width, intr.height)
        with atomic_path(out / f"{name}.jpg") as tmp:
            Image.fromarray(img).save(tmp, format="JPEG", quality=cond.jpeg_quality, exif=exif)
        _write_json(out / f"{name}.json", record)
        checks = select_check_points(scene, intr, pose, face_rock, spec.n_check_points, rng)
        prior_pose = Pose.from_attitude(prior["trend_deg"], prior["plunge_deg"], prior["roll_deg"],
                                        prior["position"])
        truth = {
            "photo": f"{name}.jpg",
            "camera": intr.to_dict(),
            "pose": pose.to_dict(),
            "conditions": {**cond.to_dict(), "strength": strength},
            "check_points": checks,
            "prior": prior,
            "prior_error": {
                "position_m": float(np.linalg.norm(np.asarray(prior["position"]) - pose.center)),
                "rotation_deg": float(pose.rotation_error_deg(prior_pose)),
            },
            "view": fractions,
        }
        _write_json(out / f"{name}.truth.json", truth)
        # What a geologist would draw on it: the contacts it sees, by hand.
        drawing = drawing_geojson(visible_stretches(scene, intr, pose, true_lines),
                                  rng_for(seed, _S_DRAWING, k))
        _write_json(out / f"{name}.lines.geojson", drawing, indent=None)
        # What a field team's GNSS survey of targets would give.
        _write_example_pairs(out / f"{name}.pairs.csv", checks, intr, georef,
                             rng_for(seed, _S_PAIRS, k))
        return {"image": f"{name}.jpg", "sensor": f"{name}.json", "truth": f"{name}.truth.json",
                "drawing": f"{name}.lines.geojson", "pairs": f"{name}.pairs.csv"}

    # Two photos at a time keep both cores busy through the numpy stages
    # (the ray casts are threaded already).
    with ThreadPoolExecutor(max(1, min(2, ray_threads(), len(poses)))) as pool:
        photos = list(pool.map(make_photo, range(len(poses))))
    timings["photos"] = time.perf_counter() - t0
    orient_files = write_orientation_example(out / ORIENT_EXAMPLE_DIR,
                                             rng_for(seed, _S_ORIENT_SURVEY))
    examples = {"orient": {key: f"{ORIENT_EXAMPLE_DIR}/{name}"
                           for key, name in orient_files.items()}}

    manifest = {
        "generator": "napari_imgreg.sample",
        "generator_version": GENERATOR_VERSION,
        "size": size if size in SIZES and spec == OutcropSpec.for_size(size) else f"{size} (custom spec)",
        "seed": int(seed),
        "n_triangles": int(len(oc.faces)),
        "n_vertices": int(len(oc.vertices)),
        "grid": list(spec.grid),
        "texture_size": spec.texture_size,
        "files": files,
        "photos": photos,
        "examples": examples,
        "survey_sun": {"azimuth_deg": spec.survey_sun_azimuth_deg,
                       "elevation_deg": spec.survey_sun_elevation_deg,
                       "ambient": spec.survey_ambient},
        "spec": spec.to_dict(),
    }
    _write_json(out / "scene.json", manifest)
    write_survey(out, georef, sun_vector(spec.survey_sun_azimuth_deg, spec.survey_sun_elevation_deg),
                 np.asarray(scene.vertices).mean(axis=0))
    timings["total"] = time.perf_counter() - t_start
    log.info("sample outcrop %s (seed %d) written to %s in %.1f s: %s", size, seed, out,
             timings["total"], {k: round(v, 2) for k, v in timings.items()})
    return out


def _sensor_record(spec: OutcropSpec, intr: Intrinsics, pose: Pose, dem, georef,
                   rng: np.random.Generator) -> tuple[dict[str, Any], dict[str, Any]]:
    """What the phone logs: the true pose plus GNSS and compass/tilt noise.

    Horizontal position: sigma ``sigma_position_m`` per axis; altitude: DEM
    height at the logged position + eye height + ``sigma_altitude_m``;
    heading sigma ``sigma_heading_deg``, tilt (plunge, roll) ``sigma_tilt_deg``.
    Noise is clipped at 3 sigma.
    """
    c = pose.center
    xy = c[:2] + _clipped_normal(rng, spec.sigma_position_m, 2)
    e, n = xy[0] + georef.origin[0], xy[1] + georef.origin[1]
    ground = float(dem.height_at(e, n, strict=False)) - georef.origin[2]
    if not np.isfinite(ground):  # off the DEM: a GNSS altitude instead
        ground = c[2] - spec.height_above_ground_m + float(_clipped_normal(rng, 10.0))
    z = ground + spec.height_above_ground_m + float(_clipped_normal(rng, spec.sigma_altitude_m))
    trend, plunge, roll = pose.attitude
    trend = (trend + float(_clipped_normal(rng, spec.sigma_heading_deg))) % 360.0
    plunge = plunge + float(_clipped_normal(rng, spec.sigma_tilt_deg))
    roll = roll + float(_clipped_normal(rng, spec.sigma_tilt_deg))
    position = [float(xy[0]), float(xy[1]), float(z)]
    record = {
        "camera": {
            "width": intr.width,
            "height": intr.height,
            "focal_length_mm": spec.focal_length_mm,
            "sensor_width_mm": spec.sensor_size_mm[0],
            "sensor_height_mm": spec.sensor_size_mm[1],
        },
        "position": {"x": position[0], "y": position[1], "z": position[2]},
        "orientation": {"trend_deg": trend, "plunge_deg": plunge, "roll_deg": roll},
        "sigma": {
            "position_m": spec.sigma_position_m,
            "altitude_m": spec.sigma_altitude_m,
            "angles_deg": max(spec.sigma_heading_deg, spec.sigma_tilt_deg),
        },
    }
    prior = {"position": position, "trend_deg": trend, "plunge_deg": plunge, "roll_deg": roll}
    return record, prior


def _write_example_pairs(path: Path, checks: list[dict[str, Any]], intr: Intrinsics,
                         georef, rng: np.random.Generator) -> None:
    """A control-point file (``docs/formats.md``) of :data:`EXAMPLE_PAIRS` check
    points spread over the photo: their map coordinates as surveyed (mm) and
    their pixels as clicked (± :data:`EXAMPLE_PAIR_CLICK_PX`).

    The points are picked farthest-first over the photo from the one nearest
    its centre, at least 20 px inside the frame.
    """
    import csv

    px = np.array([c["pixel"] for c in checks], np.float64)
    xyz = np.array([c["xyz"] for c in checks], np.float64)
    inside = np.flatnonzero(np.all((px >= 20) & (px <= [intr.width - 21, intr.height - 21]),
                                   axis=1))
    chosen = [int(inside[np.argmin(np.linalg.norm(px[inside] - [intr.cx, intr.cy], axis=1))])]
    while len(chosen) < min(EXAMPLE_PAIRS, len(inside)):
        gap = np.min(np.linalg.norm(px[inside, None] - px[chosen][None], axis=2), axis=1)
        chosen.append(int(inside[np.argmax(gap)]))
    clicked = px[chosen] + rng.normal(0.0, EXAMPLE_PAIR_CLICK_PX, (len(chosen), 2))
    enh = georef.local_to_crs(xyz[chosen])
    with atomic_write(path, newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh)
        writer.writerow(["name", "photo_x", "photo_y", "easting", "northing", "elevation"])
        for k, ((x, y), (e, n, h)) in enumerate(zip(clicked, enh), start=1):
            writer.writerow([f"GCP{k}", f"{x:.2f}", f"{y:.2f}", f"{e:.3f}", f"{n:.3f}",
                             f"{h:.3f}"])


#: ``write_outcrop_folder``'s ``cached`` default: look the scene up in the cache.
_LOOK_UP = Path("<look up>")


def write_outcrop_folder(out_dir: str | os.PathLike, size: str = "small", seed: int = 0,
                         cached: Path | None = _LOOK_UP) -> Path:
    """Write the sample outcrop into a folder of the user's (``napari-imgreg sample``).

    The scene is generated into a hidden temporary folder beside ``out_dir``
    and moved into place when complete, so an interrupted run leaves no half
    scene. A folder holding anything but this size and seed's scene is
    refused before the generation, so no file of the user's is overwritten;
    an earlier run's scene is replaced by the same files (refused when one
    of them was changed since: the folder's hidden manifest records their
    hashes), and files the user put beside it stay.

    When the cache holds this size and seed's scene (:func:`sample_scene`,
    verified file by file), it is copied instead: generation is
    deterministic, so the files are the same, in a second instead of a
    minute.

    Parameters
    ----------
    out_dir : path-like
        The folder: new, empty, or holding this size and seed's scene.
    size : {"small", "large"}
    seed : int
    cached : Path or None, optional
        :func:`cached_sample_scene`'s answer, when the caller has it already
        (each asking hashes every file of the cached scene); None generates.

    Returns
    -------
    Path
        ``out_dir``.

    Raises
    ------
    InputError
        ``out_dir`` is not a folder, or holds other files.
    """
    out = Path(out_dir)
    target = out.resolve()  # a link to a folder: the folder it points to is written
    earlier = check_outcrop_folder(out, size, seed)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", dir=target.parent))
    try:
        if cached is _LOOK_UP:
            cached = cached_sample_scene(size, seed)
        if cached is not None:
            # The generation is deterministic: the cache holds the same files.
            shutil.copytree(cached, tmp, dirs_exist_ok=True, copy_function=shutil.copyfile,
                            ignore=shutil.ignore_patterns(CACHE_MANIFEST))
        else:
            generate_outcrop(tmp, size=size, seed=seed)
        # The hashes of what was written: the next run into the folder tells
        # the user's edits from the sample's own files by them.
        write_cache_manifest(tmp)
        if earlier:
            _refuse_edited_files(out, target, fresh=tmp)
            # File by file: whatever else the user keeps in the folder stays.
            _move_files_into(tmp, target)
        elif target.is_dir():
            # An empty folder (one made beforehand in the file manager): its
            # files moved in. Windows cannot rename a folder over another.
            _move_files_into(tmp, target)
        else:
            _share(tmp)  # the permissions mkdir would give it
            os.replace(tmp, target)  # a new name
    finally:
        with contextlib.suppress(OSError):
            shutil.rmtree(tmp)
    return out


def _move_files_into(source: Path, target: Path) -> None:
    """Move every file of ``source`` to the same place under ``target``, each
    replacing the file of its name; sub-folders are merged the same way, so
    files ``target`` holds besides (the user's) stay."""
    for path in sorted(source.iterdir()):
        into = target / path.name
        if path.is_dir() and into.is_dir():
            _move_files_into(path, into)
        else:
            os.replace(path, into)


def check_outcrop_folder(out_dir: str | os.PathLike, size: str = "small", seed: int = 0) -> bool:
    """Check that :func:`write_outcrop_folder` may write into a folder.

    Parameters
    ----------
    out_dir : path-like
    size : {"small", "large"}
    seed : int

    Returns
    -------
    bool
        True when the folder holds the scene of an earlier run (same size and
        seed), False when it is new or empty.

    Raises
    ------
    InputError
        ``out_dir`` is not a folder, holds other files, or holds the sample
        with files changed since it was written.
    """
    from ..errors import input_error

    out = Path(out_dir)
    target = out.resolve()
    if target.exists() and not target.is_dir():
        raise input_error(out, "exists and is not a folder")
    earlier = target.is_dir() and any(target.iterdir())
    if earlier and not _is_sample_scene_of(target, size, seed):
        raise input_error(out, f"is not empty and does not hold the {size} sample scene of "
                               f"seed {seed}: choose a new or empty folder")
    if earlier:
        _refuse_edited_files(out, target)  # by the recorded hashes, before generating
    return earlier


def _edited_sample_files(folder: Path, fresh: Path | None = None) -> list[str]:
    """The sample's files in ``folder`` that were changed after it was written.

    Judged by the hashes its :data:`CACHE_MANIFEST` recorded; a folder
    without one (written before napari-imgreg kept it) by the ``fresh``
    generation's files instead, when given: any difference counts. Files
    the sample did not write are not listed (they stay anyway).
    """
    try:
        recorded = json.loads((folder / CACHE_MANIFEST).read_text(encoding="utf-8"))["files"]
        expected = {name: entry["blake2b"] for name, entry in recorded.items()}
    except (OSError, ValueError, KeyError, TypeError):
        if fresh is None:
            return []
        expected = {p.relative_to(fresh).as_posix(): _file_hash(p) for p in _scene_files(fresh)}
    return [name for name, digest in sorted(expected.items())
            if (folder / name).is_file() and _file_hash(folder / name) != digest]


def _refuse_edited_files(out: Path, folder: Path, fresh: Path | None = None) -> None:
    """Refuse to write the sample over files the user changed (:func:`_edited_sample_files`)."""
    from ..errors import input_error

    edited = _edited_sample_files(folder, fresh)
    if edited:
        more = f" and {len(edited) - 3} more" if len(edited) > 3 else ""
        raise input_error(out, f"{', '.join(edited[:3])}{more} changed since the sample wrote "
                          f"{'them' if len(edited) > 1 else 'it'}: refusing to overwrite "
                          "your edits (move them away, or write the sample to a new folder)")


def _is_sample_scene_of(folder: Path, size: str, seed: int) -> bool:
    """True when ``folder/scene.json`` is that of the sample scene of ``size`` and ``seed``."""
    try:
        manifest = json.loads((folder / "scene.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return (isinstance(manifest, dict) and manifest.get("generator") == "napari_imgreg.sample"
            and manifest.get("size") == size and manifest.get("seed") == int(seed))


# ------------------------------------------------------------------ cache
def cache_dir() -> Path:
    """Where generated sample scenes are kept: ``$NAPARI_IMGREG_CACHE``, or
    the system's user cache folder (``~/.cache/napari-imgreg`` on Linux,
    ``~/Library/Caches/napari-imgreg`` on macOS,
    ``%LOCALAPPDATA%\\napari-imgreg\\Cache`` on Windows); see
    :func:`~napari_imgreg._platform.cache_root`."""
    return cache_root()


def write_survey(folder: Path, georef, survey_sun_local: np.ndarray,
                 where: np.ndarray) -> None:
    """Write ``survey.json``: the sun the texture was photographed under.

    Given as true azimuth and elevation (what a survey report states), with
    the survey instant at which the sun stood there (as a photogrammetry
    survey's EXIF would give it).
    """
    from ..solar import meridian_convergence_deg

    sun_time = time_for_sun(survey_sun_local, georef, where)
    d = np.asarray(survey_sun_local, np.float64)
    grid_az = float(np.degrees(np.arctan2(d[0], d[1])) % 360.0)
    true_az = (grid_az + meridian_convergence_deg(georef, where)) % 360.0
    _write_json(folder / "survey.json", {
        "sun": {"azimuth_deg": round(true_az, 4),
                "elevation_deg": round(float(np.degrees(np.arcsin(d[2]))), 4)},
        "time": sun_time.when.isoformat(),
    })


def _cache_entry(size: str, seed: int) -> Path:
    return cache_dir() / f"outcrop-{size}-seed{int(seed)}-v{GENERATOR_VERSION}"


def cached_sample_scene(size: str = "small", seed: int = 0) -> Path | None:
    """The cache's folder of this size and seed's scene, when it is there whole
    (every file as the cache's manifest lists it); None otherwise."""
    target = _cache_entry(size, seed)
    return target if target.is_dir() and verify_sample_scene(target) is None else None


def sample_scene(size: str = "small", seed: int = 0) -> Path:
    """The sample scene's folder, generated on first use and cached.

    The scene is generated into a temporary folder beside the cache entry
    and renamed into place when complete, so a crash or a concurrent caller
    never leaves (or sees) a half-written scene.

    Parameters
    ----------
    size : {"small", "large"}
    seed : int

    Returns
    -------
    Path
        ``<cache>/outcrop-<size>-seed<seed>-v<GENERATOR_VERSION>``.
    """
    if size not in SIZES:
        raise ValueError(f"size must be one of {SIZES}, not {size!r}")
    root = cache_dir()
    target = _cache_entry(size, seed)
    if target.exists():
        problem = verify_sample_scene(target)
        if problem is None:
            return target
        log.warning("cached sample scene %s: %s; generating it again", target, problem)
    root.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", dir=root))
    try:
        generate_outcrop(tmp, size=size, seed=seed)
        write_cache_manifest(tmp)
        _share(tmp)
        if target.exists():
            # Moved aside, not deleted in place: a reader of the old folder
            # never sees it half-removed, and the new one appears at once.
            stale = Path(tempfile.mkdtemp(prefix=f".{target.name}.stale.", dir=root))
            with contextlib.suppress(OSError):
                os.rename(target, stale / "scene")
            shutil.rmtree(stale, ignore_errors=True)
        try:
            os.rename(tmp, target)
        except OSError:
            if verify_sample_scene(target) is not None:
                raise
            # Another process finished first; its scene is identical.
    finally:
        with contextlib.suppress(OSError):
            shutil.rmtree(tmp)
    return target


#: Hidden file of a cached sample scene: the size and BLAKE2 hash of every
#: file (its content key). Hidden so that ``batch`` never takes it for input.
CACHE_MANIFEST = ".cache-manifest.json"


def _file_hash(path: Path) -> str:
    import hashlib

    h = hashlib.blake2b(digest_size=16)
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _scene_files(folder: Path) -> list[Path]:
    """The files of a scene folder and its sub-folders, hidden ones (and those
    in hidden folders) left out, in name order."""
    return sorted(
        p for p in folder.rglob("*")
        if p.is_file() and not any(part.startswith(".") for part in p.relative_to(folder).parts)
    )


def write_cache_manifest(folder: str | os.PathLike) -> dict[str, Any]:
    """Write ``folder/.cache-manifest.json``: size and BLAKE2 hash of each file.

    Files of sub-folders (``orient/cameras.xml``) are listed by their path
    relative to ``folder``, with ``/`` separators.

    Returns
    -------
    dict
        ``{"files": {name: {"size": bytes, "blake2b": hex}}}``.
    """
    folder = Path(folder)
    files = {
        p.relative_to(folder).as_posix(): {"size": p.stat().st_size, "blake2b": _file_hash(p)}
        for p in _scene_files(folder)
    }
    manifest = {"generator_version": GENERATOR_VERSION, "files": files}
    _write_json(folder / CACHE_MANIFEST, manifest)
    return manifest


def verify_sample_scene(folder: str | os.PathLike) -> str | None:
    """What is wrong with a cached sample scene folder, or None when it is whole.

    Every file that ``scene.json`` names (mesh, material, texture, DEM,
    photos and their records, truths and example drawings, the orientation
    example) must exist, and every file of the
    cache manifest must have its recorded size and hash. A folder cached by
    an older version (no manifest) is checked by its structure instead (the
    OBJ holds the vertex and triangle counts ``scene.json`` states) and, if
    whole, given a manifest.

    Returns
    -------
    str or None
        The first problem found, in words.
    """
    folder = Path(folder)
    try:
        manifest = json.loads((folder / "scene.json").read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        return f"scene.json unreadable ({type(exc).__name__})"
    if not isinstance(manifest, dict):
        return "scene.json is not an object"
    named = [v for v in (manifest.get("files") or {}).values() if isinstance(v, str)]
    for photo in manifest.get("photos") or []:
        if isinstance(photo, dict):
            named += [v for v in photo.values() if isinstance(v, str)]
    for example in (manifest.get("examples") or {}).values():
        if isinstance(example, dict):
            named += [v for v in example.values() if isinstance(v, str)]
    for name in named:
        if not (folder / name).is_file():
            return f"{name} is missing"
    try:
        record = json.loads((folder / CACHE_MANIFEST).read_text(encoding="utf-8"))
        files = record["files"]
        assert isinstance(files, dict)
    except FileNotFoundError:
        problem = _check_structure(folder, manifest)
        if problem is None:
            with contextlib.suppress(OSError):
                write_cache_manifest(folder)
        return problem
    except (OSError, ValueError, KeyError, TypeError, AssertionError):
        return f"{CACHE_MANIFEST} unreadable"
    for name, want in files.items():
        path = folder / name
        try:
            size = path.stat().st_size
        except OSError:
            return f"{name} is missing"
        if not isinstance(want, dict) or size != want.get("size"):
            return f"{name} has {size} bytes, {want.get('size') if isinstance(want, dict) else '?'} " \
                   "when it was cached (truncated or changed)"
        if _file_hash(path) != want.get("blake2b"):
            return f"{name} changed since it was cached"
    return None


def _check_structure(folder: Path, manifest: dict[str, Any]) -> str | None:
    """A cache entry without a manifest: every file non-empty, and the OBJ
    complete (its ``v``/``f`` line counts are those of ``scene.json``)."""
    for p in folder.iterdir():
        if p.is_file() and not p.name.startswith(".") and p.stat().st_size == 0:
            return f"{p.name} is empty"
    mesh = (manifest.get("files") or {}).get("mesh")
    if isinstance(mesh, str) and mesh.lower().endswith(".obj"):
        data = (folder / mesh).read_bytes()
        n_v, n_f = data.count(b"\nv "), data.count(b"\nf ")
        if (n_v, n_f) != (manifest.get("n_vertices"), manifest.get("n_triangles")) \
                or not data.endswith(b"\n"):
            return (f"{mesh} holds {n_v} vertices and {n_f} triangles, not the "
                    f"{manifest.get('n_vertices')} and {manifest.get('n_triangles')} of scene.json "
                    "(truncated)")
    return None


def _share(folder: Path) -> None:
    """Give a folder the permissions ``mkdir`` would (mkdtemp: 0700)."""
    folder.chmod(0o777 & ~umask())


# ----------------------------------------------------------------- loading
@dataclass
class PhotoTruth:
    """Ground truth of one sample photo.

    Attributes
    ----------
    photo : Path
        The image file.
    intrinsics : Intrinsics
        The true camera.
    pose : Pose
        The true ``cam_from_world``.
    conditions : PhotoConditions
        Light and camera conditions the photo was made with.
    check_xyz : (N, 3) array
        Surface points seen in the photo, local metres.
    check_pixels : (N, 2) array
        Their true pixel positions (column, row).
    check_surface : list of str
        ``"rock"`` or ``"ground"`` per check point.
    prior : dict
        The logged (noisy) position and attitude.
    raw : dict
        The whole truth file.
    """

    photo: Path
    intrinsics: Intrinsics
    pose: Pose
    conditions: PhotoConditions
    check_xyz: np.ndarray
    check_pixels: np.ndarray
    check_surface: list[str]
    prior: dict[str, Any]
    raw: dict[str, Any] = field(repr=False)


@dataclass
class SceneTruth:
    """Ground truth of a sample scene folder.

    Attributes
    ----------
    folder : Path
    manifest : dict
        ``scene.json``.
    geology : dict
        ``geology.json``.
    lines : dict
        ``truth_lines.geojson`` (FeatureCollection).
    photos : dict of str to PhotoTruth
        By image file name.
    """

    folder: Path
    manifest: dict[str, Any]
    geology: dict[str, Any]
    lines: dict[str, Any]
    photos: dict[str, PhotoTruth]

    @property
    def mesh(self) -> Path:
        return self.folder / self.manifest["files"]["mesh"]


def load_truth(path: str | os.PathLike) -> PhotoTruth | SceneTruth:
    """Load ground truth of a sample scene or of one of its photos.

    Parameters
    ----------
    path : path-like
        A scene folder (→ :class:`SceneTruth`), or a photo ``IMG_0001.jpg``,
        its sensor record ``IMG_0001.json`` or ``IMG_0001.truth.json``
        (→ :class:`PhotoTruth`).
    """
    from ..errors import input_error

    p = Path(path)
    if p.is_dir():
        manifest = _read_json(p / "scene.json")
        files = manifest["files"]
        photos = {ph["image"]: _photo_truth(p / ph["truth"]) for ph in manifest["photos"]}
        return SceneTruth(p, manifest, _read_json(p / files["geology"]),
                          _read_json(p / files["truth_lines"]), photos)
    name = p.name
    stem = name[: -len(".truth.json")] if name.endswith(".truth.json") else p.stem
    truth_path = p.with_name(f"{stem}.truth.json")
    if not truth_path.is_file():
        raise input_error(p, f"no ground truth beside it ({truth_path.name} missing)")
    return _photo_truth(truth_path)


def truth_pairs(truth: PhotoTruth, reference, photo_size: tuple[int, int], n: int = 8,
                margin_px: float = 20.0, max_lift_error_m: float = 0.05
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Control-point pairs as a careful user would click them, from a sample
    photo's ground truth (tests, demos, screenshots of manual registration).

    The photo's check points that a reference render shows (the model point
    under the pixel within ``max_lift_error_m`` of the check point: not
    hidden, not off the model) and that lie at least ``margin_px`` inside
    the photo; ``n`` of them, spread over the list.

    Parameters
    ----------
    truth : PhotoTruth
    reference : RenderResult
        The reference render (its ``cam_from_world``, ``intrinsics``, ``lift``).
    photo_size : (int, int)
        The photo's (width, height), pixels.
    n : int
    margin_px, max_lift_error_m : float

    Returns
    -------
    photo_px, reference_px : (n, 2) float arrays
        Exact pixels (x, y) of each pair: by the true pose in the photo, by
        the reference's own camera in the render.
    xyz : (n, 3) float array
        The check points, model frame, metres.

    Raises
    ------
    ValueError
        Fewer than ``n`` such check points.
    """
    xyz = np.asarray(truth.check_xyz, float)
    ref_px = reference.cam_from_world.project(reference.intrinsics, xyz)
    lifted, valid = reference.lift(ref_px)
    seen = valid & (np.linalg.norm(lifted - xyz, axis=1) < max_lift_error_m)
    photo_px = truth.pose.project(truth.intrinsics, xyz)
    width, height = photo_size
    inside = np.all((photo_px >= margin_px)
                    & (photo_px <= [width - 1 - margin_px, height - 1 - margin_px]), axis=1)
    idx = np.flatnonzero(seen & inside)
    if len(idx) < n:
        raise ValueError(f"{len(idx)} check points in both images, {n} wanted")
    idx = idx[np.linspace(0, len(idx) - 1, n).round().astype(int)]
    return photo_px[idx], ref_px[idx], xyz[idx]


def _read_json(path: Path) -> Any:
    from ..errors import input_error

    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise input_error(path, "no such file") from None
    except json.JSONDecodeError as exc:
        raise input_error(path, f"invalid JSON ({exc})") from None


def _photo_truth(path: Path) -> PhotoTruth:
    d = _read_json(path)
    cps = d.get("check_points", [])
    return PhotoTruth(
        photo=path.with_name(d["photo"]),
        intrinsics=Intrinsics.from_dict(d["camera"]),
        pose=Pose.from_dict(d["pose"]),
        conditions=PhotoConditions.from_dict(d.get("conditions", {})),
        check_xyz=np.array([c["xyz"] for c in cps], np.float64).reshape(-1, 3),
        check_pixels=np.array([c["pixel"] for c in cps], np.float64).reshape(-1, 2),
        check_surface=[c.get("surface", "rock") for c in cps],
        prior=d.get("prior", {}),
        raw=d,
    )

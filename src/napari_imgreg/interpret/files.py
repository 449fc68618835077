"""Interpretation files: pixel GeoJSON in, 3D GeoJSON / CSV / OBJ / PLY out (contract §5, §6).

* Drawn on a photo: GeoJSON ``FeatureCollection`` of ``LineString`` or
  ``Polygon`` with ``[col, row]`` coordinates and ``properties.label`` (and
  optionally ``color``).
* Projected: the same properties plus ``source`` (the photo), ``kind``
  (``trace``/``facet``), ``[x, y, z]`` coordinates in the local frame, or with
  ``georef`` the CRS (``local + origin``). A trace split where it left the
  surface is a ``MultiLineString``; a facet whose ring stays on the surface is
  a ``Polygon`` (else the ring's pieces as a ``MultiLineString``), and carries
  a subsample of its surface patch in ``properties.patch_points`` so
  ``measure`` can fit its plane without the mesh.
* A georeferenced file also names its CRS in the (pre-RFC 7946) ``crs``
  member, which GDAL/QGIS honour; every file records its frame in the foreign
  member ``napari_imgreg`` (``frame``, ``crs``, ``origin``).
* Measurements: ``MEASUREMENTS.csv`` (contract §6 columns first, then
  ``collinearity,source,note``); empty cells where undefined.
* CloudCompare: OBJ ``v``/``l`` polylines (one object per feature, named
  ``id label``) and ASCII PLY with ``vertex`` (coloured) and ``edge`` elements.

* A local-frame file names its frame too, as a local engineering CRS (WKT2
  ``ENGCRS``) in the ``crs`` member, so GDAL/QGIS never take its metres for
  WGS84 degrees.
* GIS: a GeoPackage (``.gpkg``) or a set of 3D shapefiles (``.shp``) through
  pyogrio (GDAL), with layers ``traces``, ``facets``, ``measurements`` and
  ``cameras``; in the georeference's CRS whenever one is known, else in the
  local engineering CRS.
"""

from __future__ import annotations

import contextlib
import csv
import glob
import json
import math
import os
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

from .._atomic import (
    OutputError, atomic_write, fsync_dir, fsync_file, replace_file, resolve_target,
)
from .._json import dump as strict_json_dump
from ..errors import InputError, input_error
from .project import Feature3D, Interpretation
from .structural import Measurement

if TYPE_CHECKING:
    from ..geo import Georef

__all__ = [
    "MEASUREMENT_COLUMNS",
    "EXPORT_SUFFIXES",
    "read_interpretations",
    "interpretations_to_geojson",
    "write_interpretations",
    "features_to_geojson",
    "write_features_geojson",
    "read_features_geojson",
    "write_features_csv",
    "write_polylines_obj",
    "write_polylines_ply",
    "export_features",
    "write_measurements_csv",
    "write_features_gis",
    "gis_output_files",
    "check_gis_outputs",
    "read_gis_layers",
    "local_crs_wkt",
    "azimuth_reference",
    "GIS_LAYERS",
    "PATCH_POINTS_IN_FILE",
]

#: Contract §6 columns, then ours.
MEASUREMENT_COLUMNS = (
    "id", "label", "kind", "x", "y", "z", "n_points", "dip_deg", "dip_direction_deg",
    "plunge_deg", "trend_deg", "rms_m", "planarity", "collinearity", "source", "note",
    "dip_sigma_deg", "dip_direction_sigma_deg", "plunge_sigma_deg", "trend_sigma_deg", "photo",
    "view_spread", "ray_angle_deg", "comment", "above", "below",
)
EXPORT_SUFFIXES = (".geojson", ".json", ".csv", ".obj", ".ply", ".gpkg", ".shp")
#: The layers of a GeoPackage (a shapefile set: ``OUT.shp`` holds the traces,
#: ``OUT_<layer>.shp`` the others).
GIS_LAYERS = ("traces", "facets", "measurements", "cameras")
#: The files of one shapefile layer (``.cpg``: its text encoding).
SHAPEFILE_PARTS = (".shp", ".shx", ".dbf", ".prj", ".cpg")
#: Facet patch points written per feature (an even subsample).
PATCH_POINTS_IN_FILE = 5000
_DECIMALS = 4  # 0.1 mm
#: Decimals of the pixel coordinates a photo's drawings are saved with (1/1000 px).
PIXEL_DECIMALS = 3


# ------------------------------------------------------------- pixel GeoJSON
def _load_json(path: Path) -> Any:
    from ..io.records import read_json

    return read_json(path)


def _features_of(data: Any, path: Path) -> list[dict]:
    if isinstance(data, dict) and data.get("type") == "FeatureCollection":
        feats = data.get("features")
        if not isinstance(feats, list):
            raise input_error(path, "FeatureCollection without a 'features' list")
        return feats
    if isinstance(data, dict) and data.get("type") == "Feature":
        return [data]
    raise input_error(path, "not a GeoJSON FeatureCollection")


def _coords(raw: Any, dims: int, path: Path, where: str) -> np.ndarray:
    # numpy would read "100" as 100: GeoJSON positions are numbers, and text
    # there means the file was written by something that got them wrong.
    if any(isinstance(v, str) for v in np.asarray(raw, dtype=object).ravel()):
        raise input_error(path, f"{where}: coordinates are text, not numbers")
    try:
        arr = np.asarray(raw, dtype=np.float64)
    except (TypeError, ValueError):
        raise input_error(path, f"{where}: coordinates are not numbers") from None
    if arr.ndim != 2 or arr.shape[1] < 2:
        raise input_error(path, f"{where}: coordinates must be a list of positions")
    if arr.shape[1] != dims:
        if dims == 2:
            raise input_error(
                path, f"{where}: expected pixel [col, row] pairs, got {arr.shape[1]} values "
                "per position (a projected 3D file?)")
        raise input_error(
            path, f"{where}: expected [x, y, z] positions, got {arr.shape[1]} values "
            "(a pixel file? project it first)")
    if not np.isfinite(arr).all():
        raise input_error(path, f"{where}: coordinates must be finite numbers")
    return arr


def read_interpretations(path: str | os.PathLike) -> list[Interpretation]:
    """Read interpretations drawn on a photo (pixel GeoJSON, contract §5).

    ``MultiLineString``/``MultiPolygon`` features become one interpretation
    per member with the same properties; polygon holes are ignored.

    Raises
    ------
    InputError
        Not GeoJSON, an unsupported geometry, or not pixel coordinates; the
        message names the file and the feature.
    """
    path = Path(path)
    out: list[Interpretation] = []
    for k, feat in enumerate(_features_of(_load_json(path), path)):
        where = f"feature {k + 1}"
        if not isinstance(feat, dict):
            raise input_error(path, f"{where}: not a GeoJSON Feature")
        geom = feat.get("geometry")
        props = feat.get("properties") or {}
        if not isinstance(props, dict):
            raise input_error(path, f"{where}: 'properties' must be an object")
        props = dict(props)
        if "id" in feat and "id" not in props:
            props["id"] = feat["id"]
        if geom is None:
            continue
        gtype = geom.get("type") if isinstance(geom, dict) else None
        raw = geom.get("coordinates") if isinstance(geom, dict) else None
        nested = gtype in ("MultiLineString", "Polygon", "MultiPolygon")
        if nested and not isinstance(raw, list):
            raise input_error(path, f"{where}: {gtype} 'coordinates' must be an array")
        if gtype == "LineString":
            members = [("LineString", raw)]
        elif gtype == "MultiLineString":
            members = [("LineString", r) for r in raw]
        elif gtype == "Polygon":
            members = [("Polygon", (raw or [None])[0])]
        elif gtype == "MultiPolygon":
            if not all(isinstance(r, list) for r in raw):
                raise input_error(path, f"{where}: MultiPolygon members must be arrays of rings")
            members = [("Polygon", (r or [None])[0]) for r in raw]
        else:
            raise input_error(
                path, f"{where}: geometry {gtype!r} is not supported (LineString or Polygon)")
        for kind, r in members:
            px = _coords(r, 2, path, where)
            need = 3 if kind == "Polygon" else 2
            if len(px) < need:
                raise input_error(path, f"{where}: a {kind} needs at least {need} positions")
            out.append(Interpretation(kind, px, props))
    return out


def interpretations_to_geojson(items: Sequence[Interpretation]) -> dict[str, Any]:
    """A pixel GeoJSON FeatureCollection (contract §5) of drawn interpretations."""
    features = []
    for item in items:
        px = np.round(np.asarray(item.pixels, np.float64), PIXEL_DECIMALS)
        if item.geometry == "Polygon":
            ring = np.vstack([px, px[:1]]).tolist()
            geometry = {"type": "Polygon", "coordinates": [ring]}
        else:
            geometry = {"type": "LineString", "coordinates": px.tolist()}
        props = dict(item.properties)
        props.setdefault("color", item.color)
        features.append({"type": "Feature", "geometry": geometry, "properties": props})
    return {"type": "FeatureCollection", "features": features}


def write_interpretations(path: str | os.PathLike, items: Sequence[Interpretation]) -> None:
    """Write interpretations as pixel GeoJSON (atomically)."""
    with atomic_write(path, encoding="utf-8") as fh:
        strict_json_dump(interpretations_to_geojson(items), fh, indent=1)


# ---------------------------------------------------------------- 3D GeoJSON
def _ogc_crs(crs: str) -> dict | None:
    """The GDAL-read ``crs`` member for an ``EPSG:<code>`` CRS."""
    if crs.upper().startswith("EPSG:"):
        code = crs.split(":", 1)[1]
        return {"type": "name", "properties": {"name": f"urn:ogc:def:crs:EPSG::{code}"}}
    return None


def local_crs_wkt(georef: Georef | None = None) -> str:
    """The model's local frame as a WKT2 local engineering CRS (``ENGCRS``).

    Metres, x east, y north, z up. GDAL reads it from a GeoJSON ``crs``
    member, a GeoPackage or a shapefile's ``.prj`` as a ``LOCAL_CS``, so a GIS
    shows the coordinates as unreferenced metres, never as WGS84 degrees.
    With a georeference the datum's name records where the origin lies.
    """
    if georef is None:
        datum = "napari-imgreg model origin (not georeferenced)"
    else:
        e, n, h = (float(v) for v in georef.origin)
        datum = f"napari-imgreg model origin at E {e:.3f} N {n:.3f} H {h:.3f} of {georef.crs}"
    axes = ",".join(
        f'AXIS["{name}",{direction},ORDER[{k + 1}],LENGTHUNIT["metre",1]]'
        for k, (name, direction) in enumerate(
            (("x (east)", "east"), ("y (north)", "north"), ("z (up)", "up"))))
    return (f'ENGCRS["napari-imgreg local model frame",EDATUM["{datum}"],'
            f"CS[Cartesian,3],{axes}]")


def _xyz(points: np.ndarray, shift: np.ndarray) -> list:
    return np.round(np.asarray(points, np.float64) + shift, _DECIMALS).tolist()


def _positions_in_frame(props: dict[str, Any], shift: np.ndarray) -> None:
    """Move the positions a feature's properties hold (``camera_position``,
    a 3-point plane's ``three_point_xyz``) into the frame of its coordinates
    (local + ``shift``, contract §5), in place."""
    cam = props.get("camera_position")
    if isinstance(cam, (list, tuple, np.ndarray)) and len(cam) == 3:
        props["camera_position"] = _xyz(np.asarray(cam, np.float64).reshape(1, 3), shift)[0]
    try:
        three = np.asarray(props.get("three_point_xyz"), np.float64)
    except (TypeError, ValueError):  # absent (None is NaN), or not a list of points
        return
    if three.shape == (3, 3):
        props["three_point_xyz"] = _xyz(three, shift)


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    return value


def features_to_geojson(
    features: Sequence[Feature3D], georef: Georef | None = None, georeferenced: bool = False
) -> dict[str, Any]:
    """A 3D GeoJSON FeatureCollection of projected interpretations.

    Parameters
    ----------
    features : list of Feature3D
        Coordinates in the local frame, metres.
    georef : Georef, optional
        The model's georeference (recorded in the file either way).
    georeferenced : bool
        Write CRS coordinates, ``local + georef.origin``.

    Raises
    ------
    InputError
        ``georeferenced`` without a georeference.
    """
    if georeferenced and georef is None:
        raise InputError("--georeferenced needs a georeference (georef.json beside the mesh or --georef)")
    shift = georef.origin if georeferenced else np.zeros(3)
    out_features = []
    for f in features:
        props = {k: _jsonable(v) for k, v in f.properties.items()}
        props["label"] = f.label
        props.setdefault("color", f.color)
        props["kind"] = f.kind
        props["n_parts"] = len(f.parts)
        props["length_m"] = round(f.length_m, 4)
        if f.surface_normal is not None:
            props["surface_normal"] = np.round(f.surface_normal, 6).tolist()
        _positions_in_frame(props, shift)
        parts = [p for p in f.parts if len(p) >= 2]
        if f.kind == "facet":
            props["ring_complete"] = bool(f.ring_complete)
            if f.patch_faces is not None:
                props["patch_n_faces"] = int(len(f.patch_faces))
            if f.patch_points is not None and len(f.patch_points):
                pts = f.patch_points
                if len(pts) > PATCH_POINTS_IN_FILE:
                    pts = pts[np.linspace(0, len(pts) - 1, PATCH_POINTS_IN_FILE).astype(int)]
                props["patch_points"] = _xyz(pts, shift)
        if not parts:
            geometry = None
        elif f.kind == "facet" and f.ring_complete and len(parts) == 1:
            ring = parts[0]
            if not np.allclose(ring[0], ring[-1]):
                ring = np.vstack([ring, ring[:1]])
            geometry = {"type": "Polygon", "coordinates": [_xyz(ring, shift)]}
        elif len(parts) == 1:
            geometry = {"type": "LineString", "coordinates": _xyz(parts[0], shift)}
        else:
            geometry = {"type": "MultiLineString", "coordinates": [_xyz(p, shift) for p in parts]}
        out_features.append(
            {"type": "Feature", "id": f.id, "geometry": geometry, "properties": props}
        )
    doc: dict[str, Any] = {"type": "FeatureCollection"}
    meta: dict[str, Any] = {"frame": "crs" if georeferenced else "local"}
    if georef is not None:
        meta.update(crs=georef.crs, origin=[float(v) for v in georef.origin])
    if georeferenced:
        ogc = _ogc_crs(georef.crs)
        if ogc:
            doc["crs"] = ogc
    else:
        # GDAL reads a crs-less GeoJSON as WGS84: name the local frame instead.
        doc["crs"] = {"type": "name", "properties": {"name": local_crs_wkt(georef)}}
    doc["napari_imgreg"] = meta
    doc["features"] = out_features
    return doc


def write_features_geojson(
    path: str | os.PathLike,
    features: Sequence[Feature3D],
    georef: Georef | None = None,
    georeferenced: bool = False,
) -> None:
    """Write projected interpretations as 3D GeoJSON (atomically); see
    :func:`features_to_geojson`."""
    doc = features_to_geojson(features, georef, georeferenced)
    with atomic_write(path, encoding="utf-8") as fh:
        strict_json_dump(doc, fh)


def read_features_geojson(path: str | os.PathLike) -> tuple[list[Feature3D], dict[str, Any]]:
    """Read a projected (3D) interpretation GeoJSON.

    Coordinates stay in the file's frame (local, or the CRS of a
    georeferenced file); measurements made on them are in that frame.

    Returns
    -------
    features : list of Feature3D
    frame : dict
        The file's ``napari_imgreg`` member (``frame``, ``crs``, ``origin``),
        ``{"frame": "local"}`` when absent.

    Raises
    ------
    InputError
        Not GeoJSON, pixel (2D) coordinates, or an unsupported geometry.
    """
    path = Path(path)
    data = _load_json(path)
    feats = _features_of(data, path)
    frame = data.get("napari_imgreg") if isinstance(data, dict) else None
    frame = dict(frame) if isinstance(frame, dict) else {"frame": "local"}
    out: list[Feature3D] = []
    for k, feat in enumerate(feats):
        where = f"feature {k + 1}"
        if not isinstance(feat, dict):
            raise input_error(path, f"{where}: not a GeoJSON Feature")
        props = dict(feat.get("properties") or {})
        geom = feat.get("geometry")
        gtype = geom.get("type") if isinstance(geom, dict) else None
        raw = geom.get("coordinates") if isinstance(geom, dict) else None
        if geom is None:
            rings = []
        elif gtype == "LineString":
            rings = [raw]
        elif gtype == "MultiLineString":
            rings = list(raw or [])
        elif gtype == "Polygon":
            rings = [(raw or [None])[0]]
        else:
            raise input_error(
                path, f"{where}: geometry {gtype!r} is not supported "
                "(LineString, MultiLineString or Polygon)")
        parts = [_coords(r, 3, path, where) for r in rings]
        kind = props.get("kind") or ("facet" if gtype == "Polygon" else "trace")
        if kind not in ("trace", "facet"):
            raise input_error(path, f"{where}: properties.kind must be 'trace' or 'facet'")
        patch = props.pop("patch_points", None)
        patch_pts = _coords(patch, 3, path, f"{where} patch_points") if patch else None
        normal = props.get("surface_normal")
        if normal is not None:
            try:
                normal = np.asarray(normal, np.float64).reshape(3)
            except (TypeError, ValueError):
                normal = None
            if normal is None or isinstance(props["surface_normal"], str) \
                    or not np.isfinite(normal).all():
                raise input_error(path, f"{where}: properties.surface_normal must be "
                                        "[x, y, z], three finite numbers")
        fid = str(feat.get("id", props.get("id", f"f{k + 1}")))
        props.setdefault("label", "unlabelled")
        out.append(Feature3D(
            id=fid, kind=kind, parts=parts, properties=props,
            ring_complete=gtype == "Polygon", patch_points=patch_pts,
            surface_normal=normal,
        ))
    return out, frame


def azimuth_reference(frame: dict[str, Any], points: np.ndarray) -> str:
    """Which north the azimuths measured in a 3D file are from, in words.

    Trend and dip direction are measured clockwise from the frame's +Y axis:
    the model's north, which in a georeferenced model is the **grid** north of
    its CRS. That differs from true north by the meridian convergence
    (:func:`~napari_imgreg.solar.meridian_convergence_deg`, about 1° in the
    sample's UTM zone 30N, up to ~3° at a zone's edge): a geologist comparing
    with compass readings (true north after declination) must add it.

    Parameters
    ----------
    frame : dict
        The file's ``napari_imgreg`` member (:func:`read_features_geojson`):
        ``frame`` (``local``/``crs``), and ``crs``, ``origin`` when the model
        is georeferenced.
    points : (N, 3) array
        Where the azimuths were measured (the centroids), in the file's frame;
        NaN rows are ignored.

    Returns
    -------
    str
        E.g. ``"azimuths (trend, dip direction) from grid north of
        EPSG:32630, 0.95° clockwise of true north here (true azimuth = grid
        azimuth + 0.95°)"``; without a georeference, from the model's +Y axis.
    """
    from ..geo import Georef
    from ..solar import meridian_convergence_deg

    unknown = ("azimuths (trend, dip direction) from the model frame's +Y axis "
               "(no georeference: its relation to true north is not known)")
    try:
        georef = Georef(str(frame["crs"]), np.asarray(frame["origin"], np.float64))
    except Exception:  # no (or an unusable) georeference in the file
        return unknown
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    where = pts.mean(axis=0) if len(pts) else np.zeros(3)
    if frame.get("frame") == "crs":
        where = where - georef.origin
    try:
        convergence = float(meridian_convergence_deg(georef, where))
    except Exception:  # pyproj cannot place it (a CRS without a geodetic datum)
        convergence = math.nan
    if not math.isfinite(convergence):
        return (f"azimuths (trend, dip direction) from grid north of {georef.crs} "
                "(its angle to true north could not be computed)")
    side = "clockwise" if convergence >= 0 else "anticlockwise"
    return (f"azimuths (trend, dip direction) from grid north of {georef.crs}, "
            f"{abs(convergence):.2f}° {side} of true north here (true azimuth = grid azimuth "
            f"{'+' if convergence >= 0 else '−'} {abs(convergence):.2f}°)")


# ----------------------------------------------------------------- other formats
def write_features_csv(
    path: str | os.PathLike,
    features: Sequence[Feature3D],
    georef: Georef | None = None,
    georeferenced: bool = False,
) -> None:
    """One row per vertex: ``id,label,kind,source,part,vertex,x,y,z`` (atomically)."""
    shift = _shift(georef, georeferenced)
    with atomic_write(path, newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["id", "label", "kind", "source", "part", "vertex", "x", "y", "z"])
        for f in features:
            for p, part in enumerate(f.parts):
                for v, xyz in enumerate(np.asarray(part) + shift):
                    w.writerow([f.id, f.label, f.kind, f.source, p, v,
                                *(f"{c:.{_DECIMALS}f}" for c in xyz)])


def _shift(georef: Georef | None, georeferenced: bool) -> np.ndarray:
    if georeferenced:
        if georef is None:
            raise InputError("--georeferenced needs a georeference")
        return georef.origin
    return np.zeros(3)


def _rgb(color: str) -> tuple[int, int, int]:
    from matplotlib.colors import to_rgb

    try:
        r, g, b = to_rgb(color)
    except ValueError:
        r, g, b = 0.5, 0.5, 0.5
    return int(round(r * 255)), int(round(g * 255)), int(round(b * 255))


def write_polylines_obj(
    path: str | os.PathLike,
    features: Sequence[Feature3D],
    georef: Georef | None = None,
    georeferenced: bool = False,
) -> None:
    """Wavefront OBJ polylines (``v`` and ``l``), one object per feature part.

    CloudCompare opens ``l`` elements as polylines; the object names carry the
    feature id and label.
    """
    shift = _shift(georef, georeferenced)
    lines = ["# napari-imgreg interpretations: polylines, metres"
             + (f", {georef.crs}" if georeferenced else ", local frame")]
    n = 0
    for f in features:
        for p, part in enumerate(f.parts):
            if len(part) < 2:
                continue
            name = f"{f.id}_{p + 1}_{f.label}".replace(" ", "_")
            lines.append(f"o {name}")
            lines += [f"v {x:.{_DECIMALS}f} {y:.{_DECIMALS}f} {z:.{_DECIMALS}f}"
                      for x, y, z in np.asarray(part) + shift]
            lines.append("l " + " ".join(str(n + 1 + i) for i in range(len(part))))
            n += len(part)
    with atomic_write(path, encoding="utf-8") as fh:
        fh.write("\n".join(lines) + "\n")


def write_polylines_ply(
    path: str | os.PathLike,
    features: Sequence[Feature3D],
    georef: Georef | None = None,
    georeferenced: bool = False,
) -> None:
    """ASCII PLY polylines: coloured ``vertex`` elements joined by ``edge`` elements.

    Vertices carry the feature's label colour and a ``feature`` index (into
    the order of ``features``).
    """
    shift = _shift(georef, georeferenced)
    verts, edges = [], []
    n = 0
    for i, f in enumerate(features):
        r, g, b = _rgb(f.color)
        for part in f.parts:
            if len(part) < 2:
                continue
            for x, y, z in np.asarray(part) + shift:
                verts.append(f"{x:.{_DECIMALS}f} {y:.{_DECIMALS}f} {z:.{_DECIMALS}f} {r} {g} {b} {i}")
            edges += [f"{n + j} {n + j + 1}" for j in range(len(part) - 1)]
            n += len(part)
    header = [
        "ply", "format ascii 1.0",
        "comment napari-imgreg interpretations, metres"
        + (f", {georef.crs}" if georeferenced else ", local frame"),
        f"element vertex {len(verts)}",
        "property double x", "property double y", "property double z",
        "property uchar red", "property uchar green", "property uchar blue",
        "property int feature",
        f"element edge {len(edges)}", "property int vertex1", "property int vertex2",
        "end_header",
    ]
    with atomic_write(path, encoding="utf-8") as fh:
        fh.write("\n".join(header + verts + edges) + "\n")


# ---------------------------------------------------------------- GIS layers
#: Shapefile field names are at most 10 characters: ours, shortened.
_SHP_NAMES = {
    "dip_direction_deg": "dip_dir", "dip_direction_sigma_deg": "ddir_sig", "dip_sigma_deg": "dip_sig",
    "plunge_sigma_deg": "plg_sig", "trend_sigma_deg": "trd_sig", "plunge_deg": "plunge",
    "trend_deg": "trend", "dip_deg": "dip", "collinearity": "collinear", "planarity": "planarity",
    "n_points": "n_points", "ring_complete": "ring_ok", "surface_normal": "surf_norm",
    "camera_position": "cam_pos", "patch_n_faces": "patch_nf", "n_features": "n_feats",
    "three_point_px": "tp_px", "three_point_xyz": "tp_xyz",
}


def _wkb_z(kind: str, parts: Sequence[np.ndarray]) -> bytes:
    """ISO WKB of a 3D ``Point``, ``LineString``, ``MultiLineString`` or ``Polygon``."""
    import struct

    def ring(p: np.ndarray) -> bytes:
        p = np.ascontiguousarray(p, dtype="<f8").reshape(-1, 3)
        return struct.pack("<I", len(p)) + p.tobytes()

    if kind == "Point":
        return struct.pack("<BI", 1, 1001) + np.asarray(parts, "<f8").reshape(3).tobytes()
    if kind == "LineString":
        return struct.pack("<BI", 1, 1002) + ring(parts[0])
    if kind == "Polygon":
        return struct.pack("<BII", 1, 1003, len(parts)) + b"".join(ring(p) for p in parts)
    if kind == "MultiLineString":
        return struct.pack("<BII", 1, 1005, len(parts)) + b"".join(
            struct.pack("<BI", 1, 1002) + ring(p) for p in parts)
    raise ValueError(kind)


def _columns(rows: list[dict[str, Any]]) -> tuple[list[str], list[np.ndarray]]:
    """Attribute columns from row dicts: bool/int/float kept, text as text,
    lists and objects as JSON text; a missing value is null."""
    names: list[str] = []
    for r in rows:
        names += [k for k in r if k not in names]
    arrays = []
    for name in names:
        vals = [_jsonable(r.get(name)) for r in rows]
        present = [v for v in vals if v is not None]
        if present and all(isinstance(v, bool) for v in present) and len(present) == len(vals):
            arrays.append(np.array(vals, dtype=bool))
        elif present and all(isinstance(v, int) and not isinstance(v, bool) for v in present) \
                and len(present) == len(vals):
            arrays.append(np.array(vals, dtype=np.int64))
        elif present and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                             for v in present):
            # Non-finite numbers are nulls (GDAL writes NaN as null).
            arrays.append(np.array([np.nan if v is None or not math.isfinite(v) else float(v)
                                    for v in vals]))
        else:
            from .._json import dumps as strict_dumps

            # Compact JSON: a shapefile's text field holds only 254 characters.
            arrays.append(np.array(
                [None if v is None else v if isinstance(v, str)
                 else strict_dumps(v, separators=(",", ":")) for v in vals], dtype=object))
    return names, arrays


def _feature_row(f: Feature3D, shift: np.ndarray) -> dict[str, Any]:
    """A feature's attributes for a GIS layer, positions in the layer's frame
    (local + ``shift``), as the GeoJSON writer gives them."""
    props = {k: v for k, v in f.properties.items() if k != "patch_points"}
    row = {"id": f.id, "label": f.label, "kind": f.kind, "source": f.source}
    row.update({k: v for k, v in props.items() if k not in row})
    row.setdefault("color", f.color)
    row["n_parts"] = len(f.parts)
    row["length_m"] = round(float(f.length_m), 4)
    if f.surface_normal is not None:
        row["surface_normal"] = np.round(f.surface_normal, 6).tolist()
    _positions_in_frame(row, shift)  # as in the GeoJSON
    if f.kind == "facet":
        row["ring_complete"] = bool(f.ring_complete)
        if f.patch_faces is not None:
            row["patch_n_faces"] = int(len(f.patch_faces))
    return row


def _gis_layers(
    features: Sequence[Feature3D],
    shift: np.ndarray,
    measurements: Sequence[Measurement] | None,
    cameras: dict[str, np.ndarray] | None,
) -> dict[str, tuple[str, list, list[dict]]]:
    """``{layer: (geometry type, WKB geometries, attribute rows)}``."""
    from dataclasses import fields

    from .project import measure_features

    traces, facets = ([], []), ([], [])
    for f in features:
        parts = [np.asarray(p, np.float64) + shift for p in f.parts if len(p) >= 2]
        row = _feature_row(f, shift)
        if f.kind == "facet":
            if f.ring_complete and len(parts) == 1:
                ring = parts[0]
                if not np.allclose(ring[0], ring[-1]):
                    ring = np.vstack([ring, ring[:1]])
                facets[0].append(_wkb_z("Polygon", [ring]))
            else:  # the outline left the surface: a polygon would be invented
                facets[0].append(None)
                row["outline_parts"] = [np.round(p, _DECIMALS).tolist() for p in parts]
            facets[1].append(row)
        else:
            traces[0].append(_wkb_z("MultiLineString", parts) if parts else None)
            traces[1].append(row)
    if measurements is None:
        measurements = measure_features(features)
    meas = ([], [])
    skip = {"centroid"}
    for m in measurements:
        c = np.asarray(m.centroid, np.float64)
        meas[0].append(_wkb_z("Point", c + shift) if np.isfinite(c).all() else None)
        # An empty cell of MEASUREMENTS.csv is a null, text as numbers (a GIS
        # tells "no note" by IS NULL, not by an empty string).
        meas[1].append({fl.name: None if getattr(m, fl.name) == "" else getattr(m, fl.name)
                        for fl in fields(m) if fl.name not in skip})
    cams: dict[str, list] = {}
    for f in features:
        pos = f.properties.get("camera_position")
        if pos is not None and f.source not in cams:
            cams[f.source] = [np.asarray(pos, np.float64), 0]
        if f.source in cams:
            cams[f.source][1] += 1
    for name, pos in (cameras or {}).items():
        cams.setdefault(name, [np.asarray(pos, np.float64), 0])[0] = np.asarray(pos, np.float64)
    cam = ([_wkb_z("Point", p + shift) for p, _ in cams.values()],
           [{"photo": name, "n_features": n} for name, (_, n) in cams.items()])
    return {"traces": ("MultiLineString Z", *traces), "facets": ("Polygon Z", *facets),
            "measurements": ("Point Z", *meas), "cameras": ("Point Z", *cam)}


def write_features_gis(
    path: str | os.PathLike,
    features: Sequence[Feature3D],
    georef: Georef | None = None,
    measurements: Sequence[Measurement] | None = None,
    cameras: dict[str, np.ndarray] | None = None,
) -> list[str]:
    """Write a GeoPackage (``.gpkg``) or 3D shapefiles (``.shp``) through pyogrio.

    Layers (:data:`GIS_LAYERS`): ``traces`` (``MultiLineString Z``),
    ``facets`` (``Polygon Z``; a facet whose outline left the surface has no
    geometry and its pieces in ``outline_parts``), ``measurements``
    (``Point Z`` at each centroid with every :class:`Measurement` field) and
    ``cameras`` (``Point Z``, one per photo: ``properties.camera_position``
    or ``cameras``). A shapefile set is ``OUT.shp`` (traces) and
    ``OUT_facets.shp``, ``OUT_measurements.shp``, ``OUT_cameras.shp``, field
    names shortened to 10 characters. Lists (normals, camera positions) are
    JSON text. Facet patch points stay in the GeoJSON.

    Parameters
    ----------
    features : list of Feature3D
        Local-frame coordinates, metres.
    georef : Georef, optional
        With it the layers are in its CRS (local + origin); without, in the
        local engineering CRS of :func:`local_crs_wkt`.
    measurements : list of Measurement, optional
        Default: :func:`~napari_imgreg.interpret.project.measure_features`.
    cameras : dict, optional
        ``{photo: (3,) camera centre}``, local frame.

    Returns
    -------
    list of str
        Notes for the user: the shapefile fields whose text was too long for
        the format (:data:`DBF_TEXT_MAX`) and was left empty.

    Notes
    -----
    Written beside the target and renamed into place: an existing file is
    replaced only once the new one is complete. A shapefile set's files are
    all checked first (:func:`check_gis_outputs`) and replaced one right
    after the other once every layer is written; a rename refused half-way
    puts the replaced ones back (see :func:`_replace_together`).

    Raises
    ------
    InputError
        A folder where one of the files goes (nothing written).
    OutputError
        A file could not be replaced (:func:`_replace_together`).
    """
    import tempfile

    try:
        import pyogrio.raw
    except ImportError:  # pragma: no cover - a declared dependency
        raise input_error(path, "GeoPackage/shapefile export needs pyogrio "
                          "(pip install pyogrio)") from None
    path = Path(path)
    suffix = path.suffix.lower()
    shift = georef.origin if georef is not None else np.zeros(3)
    crs = georef.crs if georef is not None else local_crs_wkt(None)
    frame = {"napari_imgreg_frame": "crs" if georef is not None else "local",
             "napari_imgreg_crs": georef.crs if georef is not None else "local",
             "napari_imgreg_origin": json.dumps([float(v) for v in shift])}
    check_gis_outputs(path)  # before the layers are built and written
    layers = _gis_layers(features, shift, measurements, cameras)
    notes: list[str] = []
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=f".{path.name}.", dir=path.parent) as tmp:
        tmp_dir = Path(tmp)
        written: list[tuple[Path, Path]] = []
        for k, (layer, (gtype, geoms, rows)) in enumerate(layers.items()):
            names, arrays = _columns(rows)
            if suffix == ".shp":
                notes += _fit_dbf_text(layer, names, arrays)
                names = _shapefile_names(names)
                stem = path.stem if k == 0 else f"{path.stem}_{layer}"
                out = tmp_dir / f"{stem}.shp"
                kwargs: dict[str, Any] = {"layer": stem, "driver": "ESRI Shapefile",
                                          "encoding": "UTF-8"}
            else:
                out = tmp_dir / path.name
                kwargs = {"layer": layer, "driver": "GPKG", "append": k > 0,
                          "layer_metadata": frame}
            if not names:  # GDAL wants a column
                names, arrays = ["id"], [np.array([], dtype=object)]
            pyogrio.raw.write(
                str(out), np.array(geoms, dtype=object), arrays, names,
                geometry_type=gtype, crs=crs, **kwargs)
            if suffix == ".shp":
                # Escaped: a name like "map[v2]" is no pattern (it matched nothing).
                written += [(p, path.parent / p.name)
                            for p in tmp_dir.glob(f"{glob.escape(stem)}.*")]
        if suffix != ".shp":
            written = [(tmp_dir / path.name, path)]
        _replace_together(written, tmp_dir / ".replaced")
    return notes


def gis_output_files(path: str | os.PathLike) -> list[Path]:
    """Every file :func:`write_features_gis` writes for ``path``.

    Parameters
    ----------
    path : path-like
        ``OUT.gpkg`` or ``OUT.shp``.

    Returns
    -------
    list of Path
        ``[OUT.gpkg]``, or for a shapefile set each of
        :data:`SHAPEFILE_PARTS` of ``OUT`` (traces) and of ``OUT_<layer>``
        for the other :data:`GIS_LAYERS`.
    """
    path = Path(path)
    if path.suffix.lower() != ".shp":
        return [path]
    stems = [path.stem] + [f"{path.stem}_{layer}" for layer in GIS_LAYERS[1:]]
    return [path.with_name(stem + part) for stem in stems for part in SHAPEFILE_PARTS]


def check_gis_outputs(path: str | os.PathLike) -> None:
    """Refuse, before anything is written, a GIS export one of whose files
    cannot be replaced because a folder is in its way.

    Raises
    ------
    InputError
        ``"<file>: cannot write here: it is a folder, not a file"``.
    """
    _refuse_folders(gis_output_files(path))


def _refuse_folders(paths: Sequence[Path]) -> None:
    """Raise an InputError for the first of ``paths`` (followed when a link)
    that is a folder: a rename over it would fail half-way through a set."""
    for p in paths:
        if p.is_dir():  # a link to one too: a link's target is replaced
            raise input_error(p, "cannot write here: it is a folder, not a file "
                                 "(no file of the set was replaced)")


def _replace_together(moves: Sequence[tuple[Path, Path]], backups: Path) -> None:
    """Rename each new file over its destination, one right after the other.

    Every destination is checked first (:func:`_refuse_folders`), so a folder
    in the way replaces nothing. Should a rename still be refused (an
    immutable file, a link to another disk), the files already replaced are
    put back from hard links made in ``backups``: the set stays the old one
    whole, never a mix of old and new layers.

    Parameters
    ----------
    moves : sequence of (Path, Path)
        (new file, destination as named); a symlinked destination is
        followed, as :func:`~napari_imgreg._atomic.atomic_path` does.
    backups : Path
        A new folder on the destinations' file system for the old files.

    Raises
    ------
    InputError
        A folder in the way (nothing replaced).
    OutputError
        A rename was refused; names that file (the set is as it was before).
    """
    _refuse_folders([dst for _, dst in moves])
    for src, _ in moves:  # the new content on the disk before any name points at it
        fsync_file(src)
    backups.mkdir()
    done: list[tuple[Path, Path | None, bool]] = []  # (target, its backup, it existed)
    for k, (src, dst) in enumerate(moves):
        target = resolve_target(dst)
        existed = os.path.lexists(target)
        backup: Path | None = backups / str(k) if existed else None
        if backup is not None:
            try:
                os.link(target, backup, follow_symlinks=False)
            except OSError:  # no hard links here: this one cannot be put back
                backup = None
        try:
            replace_file(src, target)
        except OSError as exc:
            for done_target, done_backup, done_existed in reversed(done):
                with contextlib.suppress(OSError):
                    if done_backup is not None:
                        os.replace(done_backup, done_target)
                    elif not done_existed:
                        os.unlink(done_target)
            raise OutputError(dst, exc) from exc
        done.append((target, backup, existed))
    for folder in {target.parent for target, _, _ in done}:
        fsync_dir(folder)


#: Longest text a shapefile's (dBASE) field holds, characters.
DBF_TEXT_MAX = 254


def _fit_dbf_text(layer: str, names: list[str], arrays: list[np.ndarray]) -> list[str]:
    """Leave empty (in place) the texts a shapefile cannot hold whole: a cut
    JSON list is not a shorter list but broken text. Returns one note per
    field that lost values."""
    notes = []
    for name, values in zip(names, arrays):
        if values.dtype != object:
            continue
        long = [k for k, v in enumerate(values)
                if isinstance(v, str) and len(v.encode("utf-8")) > DBF_TEXT_MAX]
        for k in long:
            values[k] = None
        if long:
            notes.append(f"{layer}: {name} of {len(long)} feature(s) is longer than a shapefile "
                         f"field holds ({DBF_TEXT_MAX} characters) and was left empty; "
                         "the GeoPackage and GeoJSON keep it")
    return notes


def _shapefile_names(names: list[str]) -> list[str]:
    out: list[str] = []
    for n in names:
        short = _SHP_NAMES.get(n, n)[:10]
        k = 1
        while short in out:
            short = f"{short[:8]}_{k}"
            k += 1
        out.append(short)
    return out


def read_gis_layers(path: str | os.PathLike) -> dict[str, tuple[list, dict[str, np.ndarray], str]]:
    """Read back what :func:`write_features_gis` wrote (for checks and scripts).

    Returns
    -------
    dict
        ``{layer: (WKB geometries, {field: values}, CRS as GDAL reports it)}``
        for every layer of a GeoPackage, or of a shapefile set (named by
        :data:`GIS_LAYERS`).
    """
    import pyogrio
    import pyogrio.raw

    path = Path(path)
    if path.suffix.lower() == ".shp":
        sources = {layer: path if k == 0 else path.with_name(f"{path.stem}_{layer}.shp")
                   for k, layer in enumerate(GIS_LAYERS)}
        pairs = [(layer, p, None) for layer, p in sources.items() if p.exists()]
    else:
        pairs = [(str(name), path, str(name)) for name, _ in pyogrio.list_layers(path)]
    out = {}
    for layer, p, lname in pairs:
        with warnings.catch_warnings():
            # GDAL cannot tell an empty PolygonZ shapefile from a PolygonZM one
            # (the shape type is the same); it is read as Polygon Z all the same.
            warnings.filterwarnings("ignore", "Measured \\(M\\) geometry types",
                                    UserWarning)
            meta, _, geoms, data = pyogrio.raw.read(p, layer=lname)
        out[layer] = (list(geoms), dict(zip(meta["fields"], data)), meta["crs"])
    return out


def export_in_crs(path: str | os.PathLike, georef: Georef | None, georeferenced: bool) -> bool:
    """Whether :func:`export_features` writes ``path`` in the georeference's
    CRS: with ``georeferenced``, and a GeoPackage or shapefile whenever the
    model has a georeference."""
    return georef is not None and (
        georeferenced or Path(path).suffix.lower() in (".gpkg", ".shp"))


def measurements_in_frame(measurements: Sequence[Measurement],
                          shift: np.ndarray) -> list[Measurement]:
    """Copies of ``measurements`` with their centroids moved by ``shift``
    (local → CRS: ``georef.origin``); the angles do not change."""
    from dataclasses import replace

    return [replace(m, centroid=np.asarray(m.centroid, np.float64) + shift)
            for m in measurements]


def export_features(
    path: str | os.PathLike,
    features: Sequence[Feature3D],
    georef: Georef | None = None,
    georeferenced: bool = False,
    measurements: Sequence[Measurement] | None = None,
) -> list[str]:
    """Write projected interpretations in the format the suffix names.

    ``.geojson``/``.json`` (3D GeoJSON), ``.csv`` (vertices), ``.obj`` /
    ``.ply`` (polylines for CloudCompare), ``.gpkg`` / ``.shp`` (GIS layers,
    see :func:`write_features_gis`: in the CRS whenever ``georef`` is given;
    ``measurements`` fill their measurements layer, default: measured here).
    Returns notes for the user (:func:`write_features_gis`; none for the
    other formats).

    Raises
    ------
    InputError
        Unknown suffix.
    """
    suffix = Path(path).suffix.lower()
    if suffix in (".geojson", ".json"):
        write_features_geojson(path, features, georef, georeferenced)
    elif suffix == ".csv":
        write_features_csv(path, features, georef, georeferenced)
    elif suffix == ".obj":
        write_polylines_obj(path, features, georef, georeferenced)
    elif suffix == ".ply":
        write_polylines_ply(path, features, georef, georeferenced)
    elif suffix in (".gpkg", ".shp"):
        return write_features_gis(path, features, georef, measurements=measurements)
    else:
        raise input_error(path, f"unknown format; use one of {', '.join(EXPORT_SUFFIXES)}")
    return []


# -------------------------------------------------------------- measurements
def _cell(value: float | None, decimals: int) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return ""
    return f"{value:.{decimals}f}"


def write_measurements_csv(path: str | os.PathLike, measurements: Sequence[Measurement]) -> None:
    """Write ``MEASUREMENTS.csv`` (contract §6; atomically). Empty where undefined."""
    with atomic_write(path, newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(MEASUREMENT_COLUMNS)
        for m in measurements:
            c = np.asarray(m.centroid, np.float64)
            w.writerow([
                m.id, m.label, m.kind,
                _cell(float(c[0]), 4), _cell(float(c[1]), 4), _cell(float(c[2]), 4),
                m.n_points,
                _cell(m.dip_deg, 3), _cell(m.dip_direction_deg, 3),
                _cell(m.plunge_deg, 3), _cell(m.trend_deg, 3),
                _cell(m.rms_m, 4), _cell(m.planarity, 4), _cell(m.collinearity, 4),
                m.source, m.note,
                _cell(m.dip_sigma_deg, 3), _cell(m.dip_direction_sigma_deg, 3),
                _cell(m.plunge_sigma_deg, 3), _cell(m.trend_sigma_deg, 3), m.photo,
                _cell(m.view_spread, 2), _cell(m.ray_angle_deg, 2),
                m.comment, m.above, m.below,
            ])

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

GeoPackage is not written: no GDAL binding (pyogrio/fiona) is a dependency.
``ogr2ogr -f GPKG LINES3D.gpkg LINES3D.geojson`` converts the GeoJSON with
its Z values.
"""

from __future__ import annotations

import csv
import json
import math
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

from napari_imgreg._atomic import atomic_write
from napari_imgreg.errors import InputError, input_error
from napari_imgreg.interpret.project import Feature3D, Interpretation
from napari_imgreg.interpret.structural import Measurement

if TYPE_CHECKING:
    from napari_imgreg.geo import Georef

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
    "PATCH_POINTS_IN_FILE",
]

#: Contract §6 columns, then ours.
MEASUREMENT_COLUMNS = (
    "id", "label", "kind", "x", "y", "z", "n_points", "dip_deg", "dip_direction_deg",
    "plunge_deg", "trend_deg", "rms_m", "planarity", "collinearity", "source", "note",
)
EXPORT_SUFFIXES = (".geojson", ".json", ".csv", ".obj", ".ply")
#: Facet patch points written per feature (an even subsample).
PATCH_POINTS_IN_FILE = 5000
_DECIMALS = 4  # 0.1 mm


# ------------------------------------------------------------- pixel GeoJSON
def _load_json(path: Path) -> Any:
    from napari_imgreg.io.records import read_json

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
        if gtype == "LineString":
            members = [("LineString", raw)]
        elif gtype == "MultiLineString":
            members = [("LineString", r) for r in (raw or [])]
        elif gtype == "Polygon":
            members = [("Polygon", (raw or [None])[0])]
        elif gtype == "MultiPolygon":
            members = [("Polygon", (r or [None])[0]) for r in (raw or [])]
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
        px = np.round(np.asarray(item.pixels, np.float64), 3)
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
        json.dump(interpretations_to_geojson(items), fh, indent=1)


# ---------------------------------------------------------------- 3D GeoJSON
def _ogc_crs(crs: str) -> dict | None:
    """The GDAL-read ``crs`` member for an ``EPSG:<code>`` CRS."""
    if crs.upper().startswith("EPSG:"):
        code = crs.split(":", 1)[1]
        return {"type": "name", "properties": {"name": f"urn:ogc:def:crs:EPSG::{code}"}}
    return None


def _xyz(points: np.ndarray, shift: np.ndarray) -> list:
    return np.round(np.asarray(points, np.float64) + shift, _DECIMALS).tolist()


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
        json.dump(doc, fh)


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
        normal = np.asarray(normal, np.float64) if normal is not None else None
        fid = str(feat.get("id", props.get("id", f"f{k + 1}")))
        props.setdefault("label", "unlabelled")
        out.append(Feature3D(
            id=fid, kind=kind, parts=parts, properties=props,
            ring_complete=gtype == "Polygon", patch_points=patch_pts,
            surface_normal=normal,
        ))
    return out, frame


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


def export_features(
    path: str | os.PathLike,
    features: Sequence[Feature3D],
    georef: Georef | None = None,
    georeferenced: bool = False,
) -> None:
    """Write projected interpretations in the format the suffix names.

    ``.geojson``/``.json`` (3D GeoJSON), ``.csv`` (vertices), ``.obj`` /
    ``.ply`` (polylines for CloudCompare).

    Raises
    ------
    InputError
        Unknown suffix (a ``.gpkg`` is explained: convert the GeoJSON).
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
    elif suffix == ".gpkg":
        raise input_error(
            path, "GeoPackage is not written (no GDAL binding installed); write .geojson and "
            "convert with: ogr2ogr -f GPKG OUT.gpkg IN.geojson")
    else:
        raise input_error(path, f"unknown format; use one of {', '.join(EXPORT_SUFFIXES)}")


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
            ])

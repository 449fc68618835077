"""The GeoPackage of the sample outcrop as a GIS shows it (docs/images/interpretation_gpkg.png).

No GIS is installed on the build machine: the layers are read back with
pyogrio (GDAL, as QGIS reads them) and drawn in map view with matplotlib —
traces coloured by label, facets, measurement points with their dip, the
camera positions — with the CRS GDAL reports in the title::

    .venv/bin/python docs/gis_figure.py
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parents[1] / "benchmarks"))

OUT = Path(__file__).parent / "images" / "interpretation_gpkg.png"


def main() -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import shapely
    from bench_interpret import drawn_lines

    from napari_imgreg import Scene
    from napari_imgreg.interpret.files import export_features, read_gis_layers
    from napari_imgreg.interpret.project import label_color, project_interpretations
    from napari_imgreg.sample import load_truth, sample_scene

    folder = sample_scene("small")
    truth = load_truth(folder)
    scene = Scene.load(folder / "outcrop.obj", dem=folder / "dem.tif")
    features = []
    for name in sorted(truth.photos)[:2]:
        pt = truth.photos[name]
        items = [d for d, _ in drawn_lines(scene, pt.intrinsics, pt.pose, truth.lines)][::3]
        features += project_interpretations(scene, pt.intrinsics, pt.pose, items, source=name)
    for k, f in enumerate(features):
        f.id = f"{f.source.split('.')[0]}:{k + 1}"
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "LINES3D.gpkg"
        export_features(path, features, scene.georef)
        layers = read_gis_layers(path)
    fig, ax = plt.subplots(figsize=(9, 7.5))
    geoms, data, crs = layers["traces"]
    for g, label in zip(geoms, data["label"]):
        if g is None:
            continue
        for part in shapely.get_parts(shapely.from_wkb(g)):
            xy = shapely.get_coordinates(part)
            ax.plot(xy[:, 0], xy[:, 1], color=label_color(label), lw=1.6)
    geoms, data, _ = layers["measurements"]
    pts = np.array([shapely.get_coordinates(shapely.from_wkb(g), include_z=True)[0]
                    for g in geoms if g is not None])
    dips = [d for g, d in zip(geoms, data["dip_deg"]) if g is not None]
    ax.scatter(pts[:, 0], pts[:, 1], s=14, c="k", zorder=3, label="measurements (centroids)")
    for (x, y, _), dip in zip(pts, dips):
        if dip is not None and np.isfinite(dip):
            ax.annotate(f"{dip:.0f}°", (x, y), fontsize=7, xytext=(3, 3),
                        textcoords="offset points")
    geoms, data, _ = layers["cameras"]
    cams = np.array([shapely.get_coordinates(shapely.from_wkb(g))[0] for g in geoms])
    if len(cams):
        ax.scatter(cams[:, 0], cams[:, 1], marker="^", s=90, c="tab:blue", zorder=4,
                   label="cameras")
        for (x, y), name in zip(cams, data["photo"]):
            ax.annotate(name, (x, y), fontsize=8, xytext=(5, -10), textcoords="offset points")
    for label in sorted(set(layers["traces"][1]["label"])):
        ax.plot([], [], color=label_color(label), lw=2, label=f"traces: {label}")
    ax.set_aspect("equal")
    ax.set_xlabel("easting (m)")
    ax.set_ylabel("northing (m)")
    ax.ticklabel_format(useOffset=False, style="plain")
    ax.legend(loc="lower left", fontsize=8)
    z = np.concatenate([shapely.get_coordinates(shapely.from_wkb(g), include_z=True)[:, 2]
                        for g in layers["traces"][0] if g is not None])
    ax.set_title(f"LINES3D.gpkg read back with pyogrio: layers {', '.join(layers)}\n"
                 f"CRS {crs}; Z {z.min():.1f}–{z.max():.1f} m", fontsize=10)
    fig.tight_layout()
    fig.savefig(OUT, dpi=110)
    print("wrote", OUT)


if __name__ == "__main__":
    main()

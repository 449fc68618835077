"""``napari-imgreg workspace`` refusing bad input: one line, exit code 2, and
nothing already saved in the workspace folder lost or overwritten.

One small campaign (the sample's three photos, two of them drawn on and
projected, none registered: projecting from the prior pose is enough here) is
made once; each test works on a copy of it.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from napari_imgreg.sample import sample_scene

#: Files a refused command must leave exactly as they were.
SAVED = ("workspace.json", "LINES3D.geojson", "MEASUREMENTS.csv", "measurements.json",
         "photos/IMG_0001/LINES.geojson", "photos/IMG_0002/LINES.geojson")


def _lines_file(path: Path, coordinates: list) -> Path:
    """A pixel GeoJSON with one bed trace per list of vertices."""
    path.write_text(json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {"label": "bed"},
         "geometry": {"type": "LineString", "coordinates": c}} for c in coordinates]}))
    return path


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    """A workspace folder of the sample's photos, IMG_0001 and IMG_0002 drawn
    on (two traces each) and projected; IMG_0003 not drawn on."""
    from napari_imgreg.cli import main

    root = tmp_path_factory.mktemp("campaign")
    scene = root / "scene"
    shutil.copytree(sample_scene("small"), scene,
                    ignore=shutil.ignore_patterns("truth*", "orient", "*.lines.geojson"))
    folder = root / "W.imgreg"
    assert main(["workspace", "create", str(folder), str(scene)]) == 0
    for photo, y in (("IMG_0001.jpg", 300), ("IMG_0002.jpg", 350)):
        lines = _lines_file(root / f"{photo}.geojson",
                            [[[200, y], [700, y + 30]], [[150, y + 150], [850, y + 170]]])
        assert main(["workspace", "lines", str(folder), photo, str(lines)]) == 0
    assert main(["workspace", "project", str(folder)]) == 0
    return folder


@pytest.fixture
def ws(campaign, tmp_path) -> Path:
    """A copy of the campaign to change (its scene and photos stay where they are)."""
    return Path(shutil.copytree(campaign, tmp_path / "W.imgreg"))


def _saved(folder: Path) -> dict[str, bytes]:
    return {name: (folder / name).read_bytes() for name in SAVED}


def _n_features(path: Path) -> int:
    return len(json.loads(path.read_text())["features"])


# ------------------------------------------------- drawings outside the photo
OUTSIDE = [[[5000, 200], [6000, 300]]]  # the audit's file, on a 1024×768 photo


def test_lines_far_outside_the_photo_are_refused_and_nothing_is_saved(ws, tmp_path, run_cli):
    """Refused as 'project' would refuse them (it used to save them and then
    block every 'workspace project' with a line naming neither file nor photo)."""
    before = _saved(ws)
    bad = _lines_file(tmp_path / "gj_outside.geojson", OUTSIDE)
    run = run_cli(["workspace", "lines", ws, "IMG_0002.jpg", bad])
    assert run.code == 2
    assert run.line.startswith(f"napari-imgreg workspace lines: error: {bad}: feature 1 on "
                               "IMG_0002.jpg: vertex 1 at (5000, 200) px is far outside the "
                               "1024×768 photo"), run.line
    assert _saved(ws) == before


def test_project_names_the_file_and_photo_of_a_drawing_far_outside(ws, run_cli):
    """A drawing saved before 'lines' checked them (or written by hand)."""
    before = _saved(ws)
    saved_lines = ws / "photos" / "IMG_0002" / "LINES.geojson"
    _lines_file(saved_lines, OUTSIDE)
    run = run_cli(["workspace", "project", ws])
    assert run.code == 2
    assert f"error: {saved_lines}: feature 1 on IMG_0002.jpg: vertex 1 at (5000, 200)" \
        in run.line, run.line
    assert "'workspace lines'" in run.line
    assert {k: v for k, v in _saved(ws).items() if k != "photos/IMG_0002/LINES.geojson"} == \
        {k: v for k, v in before.items() if k != "photos/IMG_0002/LINES.geojson"}


# ------------------------------------------------ exports into the workspace
@pytest.mark.parametrize("out, extra", [
    ("LINES3D.geojson", ["--georeferenced"]),
    ("photos/lines.gpkg", []),
    ("../W.imgreg/MEASUREMENTS.csv", []),
    (None, ["--measurements", "MEASUREMENTS.csv"]),
])
def test_export_into_the_workspace_folder_is_refused(ws, tmp_path, run_cli, out, extra):
    """Its own LINES3D.geojson overwritten in the CRS made every later
    'local frame' export wrong."""
    before = _saved(ws)
    extra = [str(ws / a) if a.endswith(".csv") else a for a in extra]
    target = ws / out if out else tmp_path / "out.geojson"
    run = run_cli(["workspace", "export", ws, "--out", target, *extra])
    assert run.code == 2
    named = target if out else extra[-1]
    assert f"error: {named}: is inside the workspace folder {ws}" in run.line, run.line
    assert _saved(ws) == before
    assert not (ws / "photos" / "lines.gpkg").exists()


# ------------------------------------------------- a photo that cannot be opened
def _damage(folder: Path, key: str) -> Path:
    """The photo's photo.json cut short, as the audit did (head -c 300)."""
    state = folder / "photos" / key / "photo.json"
    state.write_bytes(state.read_bytes()[:300])
    return state


def test_project_keeps_the_projection_while_a_drawn_photo_cannot_be_opened(ws, tmp_path,
                                                                            run_cli):
    """It used to say 'not opened' and exit 0 with that photo's features
    gone from LINES3D and the measurements."""
    n = _n_features(ws / "LINES3D.geojson")
    assert n == 4
    state = _damage(ws, "IMG_0002")
    before = _saved(ws)
    run = run_cli(["workspace", "project", ws])
    assert run.code == 2
    assert "not opened: IMG_0002: " in run.out
    assert f"error: {ws}: IMG_0002.jpg could not be opened (IMG_0002: {state}: invalid JSON" \
        in run.line, run.line
    assert "the saved projection is kept" in run.line
    assert _saved(ws) == before
    # What was projected before can still be exported, all of it.
    out = tmp_path / "out.geojson"
    assert run_cli(["workspace", "export", ws, "--out", out]).code == 0
    assert _n_features(out) == n


def test_a_photo_not_drawn_on_that_cannot_be_opened_does_not_block_project(ws, run_cli):
    _damage(ws, "IMG_0003")
    run = run_cli(["workspace", "project", ws], max_seconds=None)
    assert run.code == 0, run.err
    assert "not opened: IMG_0003: " in run.out and "4 feature(s) projected" in run.out
    assert _n_features(ws / "LINES3D.geojson") == 4


def test_the_only_drawn_photo_not_opened_is_said_not_nothing_to_project(ws, tmp_path,
                                                                       run_cli):
    empty = _lines_file(tmp_path / "none.geojson", [])
    assert run_cli(["workspace", "lines", ws, "IMG_0001.jpg", empty]).code == 0
    _damage(ws, "IMG_0002")
    run = run_cli(["workspace", "project", ws])
    assert run.code == 2
    assert "IMG_0002.jpg could not be opened" in run.line and "Nothing" not in run.line, run.line


# ------------------------------------------------------------ create, info
@pytest.fixture
def model_only(tmp_path) -> Path:
    """A scene folder with a model, its material and texture, and a georeference: no photos."""
    folder = tmp_path / "model"
    folder.mkdir()
    src = sample_scene("small")
    for name in ("outcrop.obj", "outcrop.mtl", "outcrop_texture.jpg", "georef.json"):
        shutil.copy(src / name, folder / name)
    return folder


def test_create_no_photos_from_a_folder_without_photos(model_only, tmp_path, run_cli):
    run = run_cli(["workspace", "create", tmp_path / "M", model_only, "--no-photos"],
                  max_seconds=None)
    assert run.code == 0, run.err
    assert f"{tmp_path / 'M.imgreg'}: workspace with outcrop.obj and 0 photo(s)" in run.out
    run = run_cli(["workspace", "info", tmp_path / "M.imgreg"])
    assert run.code == 0 and "0 photo(s)" in run.out, run.err
    assert "georef" in json.loads((tmp_path / "M.imgreg" / "workspace.json").read_text())[
        "scene"]
    # Without --no-photos: refused, saying how to make it.
    run = run_cli(["workspace", "create", tmp_path / "M2", model_only])
    assert run.code == 2 and "no photos in the folder" in run.line and "--no-photos" in run.line
    assert not (tmp_path / "M2.imgreg").exists()


def test_a_file_given_for_a_folder_is_said_to_be_a_file(campaign, tmp_path, run_cli):
    scene = sample_scene("small")
    run = run_cli(["workspace", "create", tmp_path / "X", scene / "outcrop.obj"])
    assert run.code == 2 and "batch" not in run.line, run.line
    assert f"{scene / 'outcrop.obj'}: is a file, not a scene folder" in run.line
    assert not (tmp_path / "X.imgreg").exists()
    record = scene / "IMG_0001.json"
    for argv in (["info", record], ["project", record],
                 ["export", record, "--out", tmp_path / "o.geojson"]):
        run = run_cli(["workspace", *argv])
        assert run.code == 2
        assert run.line.endswith(f"error: {record}: is a file, not a workspace folder"), run.line


def test_a_damaged_projection_is_reported_when_the_workspace_opens(ws):
    """LINES3D.geojson cut short: opening says so among its problems (it was
    read after the problems were listed, and never reported)."""
    from napari_imgreg.workspace import Workspace

    lines3d = ws / "LINES3D.geojson"
    lines3d.write_bytes(lines3d.read_bytes()[:200])
    opened = Workspace.open(ws, autosave=False)
    assert any(p.startswith("projected interpretations: ") for p in opened.open_problems), \
        opened.open_problems

"""A campaign of hundreds of photos: it round-trips whole, and the work per
photo does not grow with the campaign (counted, never timed)."""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from napari_imgreg.interpret.project import Interpretation
from napari_imgreg.io import workspace_files as wsfiles
from napari_imgreg.sample import sample_scene
from napari_imgreg.workspace import Workspace
from widgets._workbench import registered_on_truth  # (the photos' poses: copies, no truth)

N_PHOTOS = 300


@pytest.fixture(scope="module")
def campaign_scene(tmp_path_factory) -> Path:
    """The sample's model with N_PHOTOS photos: one photo under many names
    (hard links where the file system has them), each with its own record."""
    src = sample_scene("small")
    out = tmp_path_factory.mktemp("campaign") / "scene"
    out.mkdir()
    for name in ("outcrop.obj", "outcrop.mtl", "outcrop_texture.jpg", "dem.tif", "georef.json"):
        shutil.copy(src / name, out / name)
    for k in range(1, N_PHOTOS + 1):
        photo = out / f"IMG_{k:04d}.jpg"
        try:
            os.link(src / "IMG_0001.jpg", photo)
        except OSError:
            shutil.copy(src / "IMG_0001.jpg", photo)
        shutil.copy(src / "IMG_0001.json", photo.with_suffix(".json"))
    return out


def _campaign(scene: Path) -> Workspace:
    ws = Workspace()
    ws.open_scene(scene / "outcrop.obj", dem=scene / "dem.tif")
    assert ws.add_photos(sorted(scene.glob("IMG_*.jpg"))) == []
    return ws


def test_a_300_photo_workspace_round_trips(campaign_scene, tmp_path, monkeypatch):
    ws = _campaign(campaign_scene)
    folder = tmp_path / "campaign.imgreg"
    # The photos folder is listed once for the whole save, not once per photo
    # (which grew with the square of the photos).
    listed = []
    iterdir = Path.iterdir

    def counting_iterdir(self):
        if self.name == wsfiles.PHOTOS_DIR:
            listed.append(self)
        return iterdir(self)

    monkeypatch.setattr(Path, "iterdir", counting_iterdir)
    ws.save(folder)
    assert len(listed) <= 1
    monkeypatch.setattr(Path, "iterdir", iterdir)

    line = Interpretation("LineString", np.array([[10.0, 20.0], [200.0, 40.0]]), {"label": "bed"})
    for k, ps in enumerate(ws.photos):
        if k % 10 == 0:
            ws.record_registration(registered_on_truth(ps, pose=ps.pose), "Auto", ps, pose_if_not_current=True)
        if k % 50 == 0:
            ws.set_interpretations([line], ps=ps)
    ws.select_photo(N_PHOTOS - 7)
    ws.accept(ws.photos[3])
    keys = [ws.photo_key(ps) for ps in ws.photos]
    ws.detach()

    again = Workspace.open(folder, autosave=False)
    assert again.open_problems == []
    assert [ps.name for ps in again.photos] == [f"IMG_{k:04d}.jpg" for k in range(1, N_PHOTOS + 1)]
    assert [again.photo_key(ps) for ps in again.photos] == keys
    assert len(set(keys)) == N_PHOTOS
    assert again.current_index == N_PHOTOS - 7
    assert [k for k, ps in enumerate(again.photos) if ps.registration is not None] == \
        list(range(0, N_PHOTOS, 10))
    assert [k for k, ps in enumerate(again.photos) if ps.interpretations] == \
        list(range(0, N_PHOTOS, 50))
    assert [k for k, ps in enumerate(again.photos) if ps.accepted] == [3]
    statuses = [again.photo_status(ps) for ps in again.photos]
    assert statuses.count("registered") == N_PHOTOS // 10 and statuses[3] == "accepted"
    assert len(wsfiles.read_manifest(folder)[0]["photos"]) == N_PHOTOS


def test_the_photos_table_summaries_count_the_projection_once(campaign_scene):
    ws = _campaign(campaign_scene)

    class CountedList(list):
        iterations = 0

        def __iter__(self):
            CountedList.iterations += 1
            return super().__iter__()

    names = [ps.name for ps in ws.photos]
    ws.features_3d = CountedList(SimpleNamespace(source=names[k % 30]) for k in range(3000))
    summaries = [ws.photo_summary(ps) for ps in ws.photos]
    assert CountedList.iterations == 1  # not once per photo: photos × features
    assert [s.mapped for s in summaries[:31]] == [100] * 30 + [0]
    # A new projection (a new list), or one grown in place, is counted again.
    ws.features_3d = [SimpleNamespace(source=names[40])]
    assert ws.photo_summary(ws.photos[40]).mapped == 1
    assert ws.photo_summary(ws.photos[0]).mapped == 0
    ws.features_3d.append(SimpleNamespace(source=names[40]))
    assert ws.photo_summary(ws.photos[40]).mapped == 2

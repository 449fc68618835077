"""Photos read from files decode their pixels when asked for and let them go:
a workspace of hundreds of photos does not hold them all in memory."""

from __future__ import annotations

import io
import pickle
import shutil
import threading

import numpy as np
import pytest
from PIL import Image

from napari_imgreg.errors import InputError
from napari_imgreg.io import photos as photos_mod
from napari_imgreg.io.photos import Photo, load_photo


def _jpeg(path, image, orientation=None, **kw):
    exif = Image.Exif()
    if orientation is not None:
        exif[0x0112] = orientation
    Image.fromarray(image).save(path, exif=exif.tobytes(), quality=95, **kw)
    return path


def _pattern(h=60, w=80):
    rng = np.random.default_rng(0)
    image = rng.integers(0, 255, (h, w, 3), np.uint8)
    image[:6, :6] = 255  # the stored top-left
    return image


def test_header_only_until_image_is_asked_for(tmp_path):
    path = _jpeg(tmp_path / "a.jpg", _pattern())
    photo = load_photo(path)
    assert photo.size == (80, 60) and photo.from_file and not photo.decoded
    assert "Photo('a.jpg', 80×60" in repr(photo) and not photo.decoded
    image = photo.image
    assert photo.decoded and image.shape == (60, 80, 3) and image.dtype == np.uint8
    assert photo.image is image  # decoded once
    assert photo.release() and not photo.decoded
    again = photo.image
    assert again is not image and np.array_equal(again, image)
    assert image.shape == (60, 80, 3)  # an array handed out before stays valid


@pytest.mark.parametrize("orientation", [1, 2, 3, 4, 5, 6, 7, 8])
def test_size_from_the_header_is_the_decoded_size(tmp_path, orientation):
    path = _jpeg(tmp_path / f"o{orientation}.jpg", _pattern(), orientation)
    photo = load_photo(path)
    assert not photo.decoded
    turned = orientation in (5, 6, 7, 8)
    assert photo.size == ((60, 80) if turned else (80, 60))
    assert (photo.image.shape[1], photo.image.shape[0]) == photo.size
    assert photo.exif.get("Orientation", 1) == orientation


def test_in_memory_photo_is_unchanged(tmp_path):
    image = np.zeros((30, 40), np.uint8)
    photo = Photo(image, {}, tmp_path / "IMG_0001.jpg")  # a path, but not read from it
    assert photo.decoded and not photo.from_file and photo.image.shape == (30, 40, 3)
    assert photo.size == (40, 30) and photo.sidecar == tmp_path / "IMG_0001.json"
    assert not photo.release() and photo.decoded
    with pytest.raises(InputError, match="8-bit"):
        Photo(image.astype(float))
    with pytest.raises(InputError, match=r"\(H, W, 3\) RGB"):
        Photo(np.zeros((3, 4, 5), np.uint8))
    assert Photo(np.zeros((5, 6, 4), np.uint8)).image.shape == (5, 6, 3)


@pytest.mark.parametrize("fmt, suffix", [("JPEG", ".jpg"), ("JPEG-progressive", ".jpg"),
                                         ("PNG", ".png"), ("TIFF", ".tif")])
def test_a_cut_file_is_refused_at_load_time(tmp_path, fmt, suffix):
    buf = io.BytesIO()
    kind, _, extra = fmt.partition("-")
    Image.fromarray(_pattern(200, 300)).save(buf, kind, **({"progressive": True} if extra else {}))
    whole = buf.getvalue()
    good = tmp_path / f"good{suffix}"
    good.write_bytes(whole)
    assert load_photo(good).size == (300, 200)
    for cut in (len(whole) // 2, len(whole) - 30):
        bad = tmp_path / f"cut{cut}{suffix}"
        bad.write_bytes(whole[:cut])
        with pytest.raises(InputError, match="cannot read image") as err:
            load_photo(bad)
        assert str(bad) in str(err.value) and "\n" not in str(err.value)


def test_a_whole_file_is_not_decoded_at_load_time(tmp_path, monkeypatch):
    """JPEG and PNG: a quick look at the file's structure, no decode."""
    decoded = []
    real = photos_mod._read_rgb
    monkeypatch.setattr(photos_mod, "_read_rgb", lambda *a, **k: decoded.append(a) or real(*a, **k))
    from napari_imgreg.io.exif import ensure_heif_opener

    ensure_heif_opener()
    for name in ("a.jpg", "b.png", "d.heic"):
        Image.fromarray(_pattern()).save(tmp_path / name)
        assert not load_photo(tmp_path / name).decoded
    assert decoded == []
    # A JPEG with bytes after its end (a phone's trailer) is whole too.
    data = (tmp_path / "a.jpg").read_bytes()
    (tmp_path / "c.jpg").write_bytes(data + b"\x00trailer" * 100)
    assert load_photo(tmp_path / "c.jpg").size == (80, 60) and decoded == []


def test_a_file_changed_since_it_was_read(tmp_path):
    path = _jpeg(tmp_path / "a.jpg", _pattern())
    photo = load_photo(path)
    _jpeg(path, _pattern(40, 50))
    with pytest.raises(InputError, match=r"a.jpg: the file has changed since it was read: "
                                         r"it was 80×60 px, it is now 50×40 px"):
        photo.image
    path.unlink()
    with pytest.raises(InputError, match="cannot read image"):
        photo.image


def test_one_decode_for_threads_asking_at_once(tmp_path, monkeypatch):
    path = _jpeg(tmp_path / "a.jpg", _pattern())
    photo = load_photo(path)
    calls, gate = [], threading.Barrier(4)
    real = photos_mod._read_rgb

    def slow(*a, **k):
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(photos_mod, "_read_rgb", slow)
    seen = []

    def ask():
        gate.wait()
        seen.append(photo.image)

    threads = [threading.Thread(target=ask) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(calls) == 1 and all(s is seen[0] for s in seen)


def test_at_most_max_decoded_photos_keep_their_pixels(tmp_path, monkeypatch):
    monkeypatch.setattr(photos_mod, "MAX_DECODED", 2)
    paths = [_jpeg(tmp_path / f"p{k}.jpg", _pattern()) for k in range(5)]
    photos = [load_photo(p) for p in paths]
    photos[0].keep_decoded = True  # the current photo
    for p in photos:
        p.image
    assert [p.decoded for p in photos] == [True, False, False, True, True]
    # A photo made from an array is never let go.
    mem = Photo(_pattern())
    for p in photos[1:3]:
        p.image
    assert mem.decoded and photos[0].decoded and sum(p.decoded for p in photos[1:]) == 2


def test_thumbnail_does_not_keep_the_pixels(tmp_path):
    path = _jpeg(tmp_path / "a.jpg", _pattern(600, 800), orientation=6)
    photo = load_photo(path)
    small = photo.thumbnail(40)
    assert small.shape == (53, 40, 3) and small.dtype == np.uint8 and not photo.decoded
    assert photo.thumbnail(40).shape == Photo(photo.image).thumbnail(40).shape


def test_pickled_photo_decodes_where_it_is_unpickled(tmp_path):
    photo = load_photo(_jpeg(tmp_path / "a.jpg", _pattern()))
    back = pickle.loads(pickle.dumps(photo))
    assert not back.decoded and back.size == (80, 60)
    assert np.array_equal(back.image, photo.image)
    mem = pickle.loads(pickle.dumps(Photo(_pattern())))
    assert mem.decoded and not mem.from_file


def test_workspace_keeps_only_the_current_photo_decoded(tmp_path):
    from napari_imgreg.sample import sample_scene
    from napari_imgreg.workspace import Workspace

    src = sample_scene("small")
    scene = tmp_path / "scene"
    scene.mkdir()
    for f in src.iterdir():
        if f.is_file() and f.suffix in (".obj", ".mtl", ".jpg", ".json", ".tif", ".png"):
            shutil.copy(f, scene / f.name)
    ws = Workspace()
    ws.open_scene(scene / "outcrop.obj")
    errors = ws.add_photos(sorted(scene.glob("IMG_*.jpg")))
    assert errors == [] and len(ws.photos) == 3
    assert not any(ps.photo.decoded for ps in ws.photos)
    ws.current.photo.image
    ws.select_photo(1)
    assert not ws.photos[0].photo.decoded and ws.current.photo.keep_decoded
    ws.current.photo.image
    ws.select_photo(2)
    assert [ps.photo.decoded for ps in ws.photos] == [False, False, False]
    folder = tmp_path / "w.imgreg"
    ws.save(folder)
    ws.detach()
    again = Workspace.open(folder, scene=ws.scene, terrain=ws.terrain, autosave=False)
    assert len(again.photos) == 3 and again.open_problems == []
    assert not any(ps.photo.decoded for ps in again.photos)


def test_register_all_decodes_one_photo_at_a_time(tmp_path, monkeypatch):
    from napari_imgreg.registration import pipeline
    from napari_imgreg.sample import sample_scene
    from napari_imgreg.workspace import Workspace

    src = sample_scene("small")
    ws = Workspace()
    ws.open_scene(src / "outcrop.obj")
    ws.add_photos(sorted(src.glob("IMG_*.jpg")))
    seen = []

    def register_photo(scene, image, prior, params, photo_name="", cancelled=None):
        seen.append((photo_name, [ps.photo.decoded for ps in ws.photos]))
        raise RuntimeError("stand-in")
        yield  # a generator, as the pipeline's

    monkeypatch.setattr(pipeline, "register_photo", register_photo)
    summary = ws.register_all(auto=False)
    assert summary.done == 3 and len(summary.failed) == 3
    # Photo k is decoded while it registers; the photos before it let theirs
    # go, but the current one (photo 0, shown).
    assert ws.current is ws.photos[0]
    assert [decoded[:k] for k, (_, decoded) in enumerate(seen)] == [[], [True], [True, False]]
    assert [decoded[k] for k, (_, decoded) in enumerate(seen)] == [True, True, True]
    assert [ps.photo.decoded for ps in ws.photos[1:]] == [False, False]

"""The unknown-focal benchmark's prior (``benchmarks/bench_unknown_focal.py``):
built from a photo read from its file, it drops the focal length and keeps the
pixels. (It once stopped working unnoticed when photos became lazily decoded.)"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from napari_imgreg import Scene
from napari_imgreg.io.photos import load_photo
from napari_imgreg.sample import sample_scene

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"
if not (BENCH / "bench_unknown_focal.py").is_file():
    pytest.skip("benchmarks/bench_unknown_focal.py not present", allow_module_level=True)
sys.path.insert(0, str(BENCH))
import bench_unknown_focal as buf  # noqa: E402


def test_the_unknown_mode_prior_has_no_focal_length_and_the_photos_pixels(tmp_path):
    folder = sample_scene("small")
    scene = Scene.load(folder / "outcrop.obj", dem=folder / "dem.tif")
    photo = load_photo(folder / "IMG_0001.jpg")
    prior = buf.prior_of(photo, scene, "unknown", tmp_path)
    assert not prior.intrinsics.focal_known and set(prior.intrinsics.estimated) >= {"fx", "fy"}
    assert (prior.intrinsics.width, prior.intrinsics.height) == photo.size
    # The photo itself is untouched: its EXIF and pixels as read.
    assert load_photo(folder / "IMG_0001.jpg").exif == photo.exif
    np.testing.assert_array_equal(photo.image, load_photo(folder / "IMG_0001.jpg").image)

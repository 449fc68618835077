"""Read field photographs (JPEG, PNG, TIFF) with their EXIF tags.

The pixels are read here; the tags are read and interpreted by
:mod:`napari_imgreg.io.exif`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from napari_imgreg.errors import input_error
from napari_imgreg.io.exif import exif_of_image

__all__ = ["Photo", "load_photo", "PHOTO_SUFFIXES", "save_image"]

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff")


@dataclass
class Photo:
    """A photograph as an RGB array with its metadata.

    Attributes
    ----------
    image : (H, W, 3) uint8 array
        RGB, row 0 at the top, EXIF orientation already applied.
    exif : dict
        EXIF tags by name (``FocalLength``, ``Model``, ...), GPS tags under
        ``"GPSInfo"`` as a dict by name.
    path : Path
    """

    image: np.ndarray
    exif: dict[str, Any] = field(default_factory=dict)
    path: Path | None = None

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return self.image.shape[1], self.image.shape[0]

    @property
    def sidecar(self) -> Path | None:
        """The sensor record beside the photo (``IMG_0001.json``)."""
        return None if self.path is None else self.path.with_suffix(".json")


def load_photo(path: str | os.PathLike) -> Photo:
    """Read a photo and its EXIF (tags by name, see :func:`napari_imgreg.io.exif.exif_of_image`).

    Raises
    ------
    InputError
        Missing file, unsupported format or unreadable image.
    """
    from PIL import Image, ImageOps, UnidentifiedImageError

    path = Path(path)
    if not path.exists():
        raise input_error(path, "no such file")
    if path.suffix.lower() not in PHOTO_SUFFIXES:
        raise input_error(path, f"not a photo format (expected {', '.join(PHOTO_SUFFIXES)})")
    try:
        with Image.open(path) as im:
            exif = exif_of_image(im)
            im = ImageOps.exif_transpose(im)
            image = np.asarray(im.convert("RGB"))
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        raise input_error(path, f"cannot read image ({exc})") from None
    return Photo(np.ascontiguousarray(image), exif, path)


def save_image(path: str | os.PathLike, rgb: np.ndarray, quality: int = 92) -> None:
    """Write an RGB (or grey) uint8 image atomically; format from the extension."""
    import cv2

    from napari_imgreg._atomic import atomic_path

    arr = np.asarray(rgb)
    if arr.ndim == 3:
        arr = cv2.cvtColor(arr, cv2.COLOR_RGB2BGR)
    with atomic_path(path) as tmp:
        params = [cv2.IMWRITE_JPEG_QUALITY, quality] if tmp.suffix.lower() in (".jpg", ".jpeg") else []
        if not cv2.imwrite(str(tmp), arr, params):
            raise input_error(path, "cannot write image (unsupported extension?)")

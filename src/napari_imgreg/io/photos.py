"""Read field photographs (JPEG, PNG, TIFF, HEIC/HEIF) with their EXIF tags.

The pixels are read here; the tags are read and interpreted by
:mod:`napari_imgreg.io.exif`.
"""

from __future__ import annotations

import os
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError, input_error
from .exif import HEIF_SUFFIXES, ensure_heif_opener, exif_of_image
from ..validate import MAX_IMAGE_SIDE_PX, MAX_PHOTO_PIXELS

__all__ = ["Photo", "load_photo", "PHOTO_SUFFIXES", "save_image"]

#: Photo files read by :func:`load_photo`. HEIC/HEIF is what iPhones (and many
#: Android phones) save by default; read through pillow-heif (libheif in its wheel).
PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", *HEIF_SUFFIXES)


@dataclass(repr=False)
class Photo:
    """A photograph as an RGB array with its metadata.

    ``Photo(image)`` wraps an image already in memory (no EXIF, no sensor
    record beside it: pass the prior).

    Attributes
    ----------
    image : (H, W, 3) uint8 array
        RGB, row 0 at the top, EXIF orientation already applied (HEIC/HEIF:
        the file's rotation, which the decoder applies). A grey (H, W) or an
        RGBA (H, W, 4) uint8 array is taken as RGB; any other shape or type
        is refused (:class:`~napari_imgreg.errors.InputError`).
    exif : dict
        EXIF tags by name (``FocalLength``, ``Model``, ...), GPS tags under
        ``"GPSInfo"`` as a dict by name.
    path : Path
    """

    image: np.ndarray
    exif: dict[str, Any] = field(default_factory=dict)
    path: Path | None = None

    def __post_init__(self) -> None:
        image = self.image
        where = self.path if self.path is not None else "photo"
        if not isinstance(image, np.ndarray):
            raise input_error(where, f"the image must be a numpy array, not "
                              f"{type(image).__name__}")
        if image.dtype != np.uint8:
            raise input_error(where, f"the image must be 8-bit (uint8, 0–255), not {image.dtype}"
                              " (e.g. (image * 255).round().astype(np.uint8) for 0–1 floats)")
        if image.ndim == 2:
            image = np.repeat(image[..., None], 3, axis=2)
        elif image.ndim == 3 and image.shape[2] == 4:
            image = image[..., :3]
        if image.ndim != 3 or image.shape[2] != 3 or min(image.shape[:2]) < 1:
            raise input_error(where, f"the image must be (H, W, 3) RGB, got shape "
                              f"{self.image.shape}")
        self.image = np.ascontiguousarray(image)
        if self.path is not None:
            self.path = Path(self.path)

    def __repr__(self) -> str:
        name = self.path.name if self.path is not None else "in memory"
        return f"Photo({name!r}, {self.size[0]}×{self.size[1]}, {len(self.exif)} EXIF tags)"

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

    Any mode is converted to 8-bit RGB: 16-bit photos by their full range
    (not clipped), grey ones repeated in the three channels. The EXIF
    orientation is applied to the pixels, all eight of them, so the photo
    looks as its viewer shows it (``exif["Orientation"]`` keeps the tag, for
    :func:`~napari_imgreg.prior.prior_for_photo` to turn the camera with
    them: 3, 6 and 8 are turned, the mirrored 2, 4, 5 and 7 refused there).

    Raises
    ------
    InputError
        Missing file, unsupported format, unreadable image, or an image larger
        than :data:`~napari_imgreg.validate.MAX_PHOTO_PIXELS` (checked from the
        header, before the pixels are decoded: a decompression bomb).
    """
    from PIL import Image, ImageOps, UnidentifiedImageError

    path = Path(path)
    if path.suffix.lower() in HEIF_SUFFIXES:
        ensure_heif_opener()
    if not path.exists():
        raise input_error(path, "no such file")
    if path.suffix.lower() not in PHOTO_SUFFIXES:
        raise input_error(path, f"not a photo format (expected {', '.join(PHOTO_SUFFIXES)})")
    try:
        with warnings.catch_warnings():
            # Our own limit (below) replaces Pillow's decompression-bomb warning.
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(path) as im:
                # Image.open reads the header only: refuse a bomb before decoding.
                width, height = im.size
                if width * height > MAX_PHOTO_PIXELS or max(width, height) > MAX_IMAGE_SIDE_PX:
                    raise input_error(
                        path, f"image is {width}×{height} px ({width * height / 1e6:,.0f} MP); "
                              f"the limit is {MAX_PHOTO_PIXELS / 1e6:g} MP and "
                              f"{MAX_IMAGE_SIDE_PX} px a side")
                exif = exif_of_image(im)
                if im.format == "HEIF":
                    # libheif has already turned the pixels by the file's own
                    # rotation and pillow-heif reset the tag to 1 so they are
                    # not turned twice; the tag as written is what the prior
                    # needs to turn the camera with them.
                    written = im.info.get("original_orientation")
                    if written:
                        exif["Orientation"] = int(written)
                im = ImageOps.exif_transpose(im)
                image = _to_rgb8(im)
    except Image.DecompressionBombError as exc:
        # Pillow refuses above 179 MP while reading the header: same answer as ours.
        claimed = re.search(r"\((\d+) pixels\)", str(exc))
        size = f"{int(claimed.group(1)) / 1e6:,.0f} MP" if claimed else "too many pixels"
        raise input_error(path, f"image header claims {size}; the limit is "
                                f"{MAX_PHOTO_PIXELS / 1e6:g} MP") from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        if isinstance(exc, InputError):
            raise
        raise input_error(path, f"cannot read image ({' '.join(str(exc).split())})") from None
    return Photo(np.ascontiguousarray(image), exif, path)


def _to_rgb8(im) -> np.ndarray:
    """An RGB uint8 array of a decoded PIL image of any mode.

    Pillow's ``convert("RGB")`` clips 16- and 32-bit grey to 255 (a 16-bit
    PNG turns white): those are scaled to 8 bits here, 16-bit by their full
    range (÷ 257), float images by [0, 1] when they lie within it.
    """
    mode = im.mode
    if mode in ("RGB", "L", "P", "PA", "RGBA", "RGBX", "LA", "CMYK", "YCbCr", "1", "La", "RGBa",
                "LAB", "HSV"):
        return np.asarray(im.convert("RGB"))
    arr = np.asarray(im)
    if arr.ndim == 3:  # multi-channel wide modes: keep the first three channels
        arr = arr[..., :3]
    if mode.startswith("I;16") or arr.dtype in (np.uint16, np.int16) or (
            mode == "I" and arr.size and arr.max() > 255):
        grey = np.clip(arr.astype(np.float64) / 257.0, 0, 255)
    elif mode == "F" or arr.dtype.kind == "f":
        a = np.nan_to_num(arr.astype(np.float64), nan=0.0, posinf=0.0, neginf=0.0)
        top = float(a.max()) if a.size else 1.0
        grey = np.clip(a * (255.0 if top <= 1.0 else 1.0), 0, 255)
    else:
        grey = np.clip(arr.astype(np.float64), 0, 255)
    grey = np.round(grey).astype(np.uint8)
    return np.repeat(grey[..., None], 3, axis=-1) if grey.ndim == 2 else grey


def save_image(path: str | os.PathLike, rgb: np.ndarray, quality: int = 92) -> None:
    """Write an RGB (or grey) uint8 image atomically; format from the extension."""
    import cv2

    from .._atomic import atomic_path

    arr = np.asarray(rgb)
    if arr.ndim == 3:
        arr = cv2.cvtColor(arr, cv2.COLOR_RGB2BGR)
    with atomic_path(path) as tmp:
        params = [cv2.IMWRITE_JPEG_QUALITY, quality] if tmp.suffix.lower() in (".jpg", ".jpeg") else []
        if not cv2.imwrite(str(tmp), arr, params):
            raise input_error(path, "cannot write image (unsupported extension?)")

"""Read field photographs (JPEG, PNG, TIFF, HEIC/HEIF) with their EXIF tags.

The pixels are read here; the tags are read and interpreted by
:mod:`napari_imgreg.io.exif`.

A photo read from a file (:func:`load_photo`) knows its size and tags from
the file's header and decodes its pixels when :attr:`Photo.image` is first
asked for: a campaign of hundreds of 12–50 MP photos does not sit in memory.
At most :data:`MAX_DECODED` of them keep their decoded pixels at a time
(besides those kept with :attr:`Photo.keep_decoded`); the others decode again
when asked (0.1–0.3 s for a phone JPEG).
"""

from __future__ import annotations

import mmap
import os
import re
import struct
import threading
import warnings
import weakref
from collections import OrderedDict
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..errors import InputError, input_error
from .exif import HEIF_SUFFIXES, ensure_heif_opener, exif_of_image
from ..validate import MAX_IMAGE_SIDE_PX, MAX_PHOTO_PIXELS

__all__ = ["Photo", "load_photo", "PHOTO_SUFFIXES", "save_image", "MAX_DECODED"]

#: Photo files read by :func:`load_photo`. HEIC/HEIF is what iPhones (and many
#: Android phones) save by default; read through pillow-heif (libheif in its wheel).
PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", *HEIF_SUFFIXES)

#: Photos read from files that keep their decoded pixels at a time (the least
#: recently decoded others let them go); photos with ``keep_decoded`` set and
#: photos made from an array in memory do not count.
MAX_DECODED = 2

#: EXIF orientations that turn the stored image by a quarter (width and height swap).
_QUARTER_TURNS = (5, 6, 7, 8)


class Photo:
    """A photograph as an RGB array with its metadata.

    ``Photo(image)`` wraps an image already in memory (no EXIF, no sensor
    record beside it: pass the prior). A photo read by :func:`load_photo`
    decodes its pixels when ``image`` is first read, and can let them go
    (:meth:`release`).

    Attributes
    ----------
    image : (H, W, 3) uint8 array
        RGB, row 0 at the top, EXIF orientation already applied (HEIC/HEIF:
        the file's rotation, which the decoder applies). A grey (H, W) or an
        RGBA (H, W, 4) uint8 array is taken as RGB; any other shape or type
        is refused (:class:`~napari_imgreg.errors.InputError`). Read from
        the file when first asked for (a photo of :func:`load_photo`): a file
        that can no longer be read, or whose size changed since, is an
        :class:`~napari_imgreg.errors.InputError` then.
    exif : dict
        EXIF tags by name (``FocalLength``, ``Model``, ...), GPS tags under
        ``"GPSInfo"`` as a dict by name.
    path : Path
    keep_decoded : bool
        Keep the decoded pixels however many other photos are decoded (the
        workspace's current photo); :meth:`release` still lets them go.
    """

    def __init__(self, image: np.ndarray, exif: dict[str, Any] | None = None,
                 path: str | os.PathLike | None = None) -> None:
        self.exif = exif if exif is not None else {}
        self.path = Path(path) if path is not None else None
        self.keep_decoded = False
        self._lock = threading.Lock()
        self._decode: Callable[[], np.ndarray] | None = None  # None: in memory only
        self._image = _rgb_array(image, self.path if self.path is not None else "photo")
        self._size = (int(self._image.shape[1]), int(self._image.shape[0]))

    @classmethod
    def _from_file(cls, path: Path, exif: dict[str, Any], size: tuple[int, int]) -> Photo:
        """A photo whose pixels are decoded from ``path`` when asked for."""
        photo = cls.__new__(cls)
        photo.exif, photo.path, photo.keep_decoded = exif, Path(path), False
        photo._lock = threading.Lock()
        photo._image, photo._size = None, (int(size[0]), int(size[1]))
        photo._decode = photo._read_pixels
        return photo

    @property
    def image(self) -> np.ndarray:
        image = self._image
        if image is not None:
            return image
        with self._lock:  # one decode, whichever thread asks first
            image = self._image
            if image is None:
                image = self._image = self._decode()
        _decoded(self)
        return image

    @image.setter
    def image(self, value: np.ndarray) -> None:
        image = _rgb_array(value, self.path if self.path is not None else "photo")
        with self._lock:  # the array given is the photo now: kept, not decoded again
            self._image, self._decode = image, None
            self._size = (int(image.shape[1]), int(image.shape[0]))

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels (from the header: nothing is decoded)."""
        return self._size

    @property
    def decoded(self) -> bool:
        """The pixels are in memory (always, for a photo made from an array)."""
        return self._image is not None

    @property
    def from_file(self) -> bool:
        """Read from a file by :func:`load_photo`: its pixels can be let go."""
        return self._decode is not None

    def release(self) -> bool:
        """Let the decoded pixels go, if the photo was read from a file (they
        are decoded again when ``image`` is next read); a photo made from an
        array keeps them. Arrays handed out before stay valid.

        Returns
        -------
        bool
            Pixels were let go.
        """
        if self._decode is None or self._image is None:
            return False
        with self._lock:
            if self._decode is None or self._image is None:
                return False
            self._image = None
        _forget(self)
        return True

    def thumbnail(self, width: int) -> np.ndarray:
        """A small RGB copy, ``width`` pixels wide, without keeping the full
        pixels of a photo read from a file (a JPEG is decoded at a reduced
        scale: much faster than ``image``).

        The last one made is kept (a few kB): a campaign's photos table asks
        for each photo's, and a worker can make them ahead of it.
        """
        import cv2

        width = max(1, int(width))
        kept = getattr(self, "_thumbnail", None)  # (absent in a photo pickled before)
        if kept is not None and kept[0] == width and kept[1] is self._image_source():
            return kept[2]
        w, h = self._size
        height = max(1, int(round(h * width / max(w, 1))))
        image = self._image
        source = self._image_source()
        if image is None and self._decode is not None:
            image = _read_rgb(self.path, reduce_to=(width, height))
        if image is None:
            image = self.image
        small = np.ascontiguousarray(cv2.resize(np.ascontiguousarray(image), (width, height),
                                                interpolation=cv2.INTER_AREA), np.uint8)
        small.setflags(write=False)  # shared by every caller
        self._thumbnail = (width, source, small)
        return small

    def _image_source(self):
        """What the pixels come from: the file's decoder, or the array given
        (a thumbnail kept is made again when the photo is given another array)."""
        return self._decode if self._decode is not None else self._image

    def _read_pixels(self) -> np.ndarray:
        image = _read_rgb(self.path)
        got = (int(image.shape[1]), int(image.shape[0]))
        if got != self._size:
            raise input_error(self.path, f"the file has changed since it was read: it was "
                                         f"{self._size[0]}×{self._size[1]} px, it is now "
                                         f"{got[0]}×{got[1]} px; read it again")
        return image

    def __repr__(self) -> str:
        name = self.path.name if self.path is not None else "in memory"
        return f"Photo({name!r}, {self.size[0]}×{self.size[1]}, {len(self.exif)} EXIF tags)"

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state.pop("_lock", None)
        state.pop("__weakref__", None)
        state.pop("_thumbnail", None)  # holds the decoder, a bound method; made again
        if state.get("_decode") is not None:
            state["_decode"] = True  # a bound method: made again when unpickled
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._lock = threading.Lock()
        if self._decode is not None:
            self._decode = self._read_pixels

    @property
    def sidecar(self) -> Path | None:
        """The sensor record beside the photo (``IMG_0001.json``)."""
        return None if self.path is None else self.path.with_suffix(".json")


def _rgb_array(image: Any, where: Any) -> np.ndarray:
    """The (H, W, 3) uint8 array of an image given as a photo (grey and RGBA
    taken as RGB); anything else is refused."""
    if not isinstance(image, np.ndarray):
        raise input_error(where, f"the image must be a numpy array, not "
                                 f"{type(image).__name__}")
    if image.dtype != np.uint8:
        raise input_error(where, f"the image must be 8-bit (uint8, 0–255), not {image.dtype}"
                          " (e.g. (image * 255).round().astype(np.uint8) for 0–1 floats)")
    given = image
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    elif image.ndim == 3 and image.shape[2] == 4:
        image = image[..., :3]
    if image.ndim != 3 or image.shape[2] != 3 or min(image.shape[:2]) < 1:
        raise input_error(where, f"the image must be (H, W, 3) RGB, got shape {given.shape}")
    return np.ascontiguousarray(image)


# Photos read from files whose pixels are decoded, least recently decoded
# first (weakly held: a photo nobody holds is not kept for this).
_DECODED: OrderedDict[int, weakref.ref] = OrderedDict()
_DECODED_LOCK = threading.Lock()


def _decoded(photo: Photo) -> None:
    """Note a photo read from a file as decoded; let the least recently
    decoded others go beyond :data:`MAX_DECODED`."""
    if photo._decode is None:
        return
    victims = []
    with _DECODED_LOCK:
        _DECODED[id(photo)] = weakref.ref(photo)
        _DECODED.move_to_end(id(photo))
        counted = []
        for key, ref in list(_DECODED.items()):
            other = ref()
            if other is None or other._image is None:
                del _DECODED[key]
            elif not other.keep_decoded:
                counted.append(other)
        victims = counted[:max(0, len(counted) - max(int(MAX_DECODED), 0))]
    for other in victims:  # outside the list's lock: release takes the photo's own
        if other is not photo:
            other.release()


def _forget(photo: Photo) -> None:
    with _DECODED_LOCK:
        _DECODED.pop(id(photo), None)


def load_photo(path: str | os.PathLike) -> Photo:
    """Read a photo's header and EXIF (tags by name, see
    :func:`napari_imgreg.io.exif.exif_of_image`); its pixels are decoded
    when first asked for (:attr:`Photo.image`).

    Any mode is converted to 8-bit RGB: 16-bit photos by their full range
    (not clipped), grey ones repeated in the three channels. The EXIF
    orientation is applied to the pixels, all eight of them, so the photo
    looks as its viewer shows it (``exif["Orientation"]`` keeps the tag, for
    :func:`~napari_imgreg.prior.prior_for_photo` to turn the camera with
    them: 3, 6 and 8 are turned, the mirrored 2, 4, 5 and 7 refused there).

    A file that is not whole (a JPEG without its end, a PNG without its last
    chunk, a HEIC whose boxes run past its end) is decoded here, and refused
    when that fails, as is a TIFF (no quick check of it): the pixels of a
    photo returned decode.

    Raises
    ------
    InputError
        Missing file, unsupported format, unreadable image, or an image larger
        than :data:`~napari_imgreg.validate.MAX_PHOTO_PIXELS` (checked from the
        header, before the pixels are decoded: a decompression bomb).
    """
    path = Path(path)
    if path.suffix.lower() in HEIF_SUFFIXES:
        ensure_heif_opener()
    if not path.exists():
        raise input_error(path, "no such file")
    if path.suffix.lower() not in PHOTO_SUFFIXES:
        raise input_error(path, f"not a photo format (expected {', '.join(PHOTO_SUFFIXES)})")
    size, exif, fmt = _read_header(path)
    if not _looks_whole(path, fmt):
        # Truncated or of a format without a quick check: the decoder decides,
        # as it did when every photo was decoded here.
        image = _read_rgb(path)
        size = (int(image.shape[1]), int(image.shape[0]))
        del image
    return Photo._from_file(path, exif, size)


class _Reading:
    """Open a photo file with Pillow, its errors as one-line InputErrors."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __enter__(self):
        from PIL import Image

        self._warnings = warnings.catch_warnings()
        self._warnings.__enter__()
        # Our own limit (below) replaces Pillow's decompression-bomb warning.
        warnings.simplefilter("ignore", Image.DecompressionBombWarning)
        try:
            self.im = Image.open(self.path)
        except BaseException as exc:
            self.__exit__(type(exc), exc, exc.__traceback__)
            raise
        # Image.open reads the header only: refuse a bomb before decoding.
        width, height = self.im.size
        if width * height > MAX_PHOTO_PIXELS or max(width, height) > MAX_IMAGE_SIDE_PX:
            self.im.close()
            self._warnings.__exit__(None, None, None)
            raise input_error(
                self.path, f"image is {width}×{height} px ({width * height / 1e6:,.0f} MP); "
                           f"the limit is {MAX_PHOTO_PIXELS / 1e6:g} MP and "
                           f"{MAX_IMAGE_SIDE_PX} px a side")
        return self.im

    def __exit__(self, kind, exc, tb) -> None:
        im = getattr(self, "im", None)
        if im is not None:
            im.close()
        self._warnings.__exit__(None, None, None)


def _reading_errors(path: Path, action: Callable[[], Any]) -> Any:
    """``action()``, Pillow's and the decoders' errors as one-line InputErrors."""
    from PIL import Image, UnidentifiedImageError

    try:
        return action()
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


def _read_header(path: Path) -> tuple[tuple[int, int], dict[str, Any], str]:
    """The photo's (width, height) as shown (EXIF orientation applied), its
    EXIF tags and its format, from the header (the pixels are not decoded)."""
    from PIL import ExifTags

    def read():
        with _Reading(path) as im:
            width, height = im.size
            exif = exif_of_image(im)
            if im.format == "HEIF":
                # libheif has already turned the pixels by the file's own
                # rotation and pillow-heif reset the tag to 1 so they are
                # not turned twice; the tag as written is what the prior
                # needs to turn the camera with them.
                written = im.info.get("original_orientation")
                if written:
                    exif["Orientation"] = int(written)
            # The tag ImageOps.exif_transpose turns the pixels by (_read_rgb).
            orientation = im.getexif().get(ExifTags.Base.Orientation, 1)
            if isinstance(orientation, int) and orientation in _QUARTER_TURNS:
                width, height = height, width
            return (int(width), int(height)), exif, str(im.format or "")

    return _reading_errors(path, read)


def _read_rgb(path: Path, reduce_to: tuple[int, int] | None = None) -> np.ndarray:
    """Decode a photo file to RGB uint8, EXIF orientation applied
    (``reduce_to``: (width, height) wanted at least, a JPEG decoded at a
    reduced scale)."""
    from PIL import ImageOps

    if path.suffix.lower() in HEIF_SUFFIXES:
        ensure_heif_opener()

    def read():
        with _Reading(path) as im:
            if reduce_to is not None and im.format == "JPEG":
                w, h = reduce_to
                im.draft("RGB", (max(w, h), max(w, h)))  # the orientation may swap them
            # In place: no copy of the pixels when the photo is not turned.
            ImageOps.exif_transpose(im, in_place=True)
            return np.ascontiguousarray(_to_rgb8(im))

    return _reading_errors(path, read)


def _looks_whole(path: Path, fmt: str) -> bool:
    """The file holds all of its image (a quick look at its structure, not a
    decode); False also when the format has no quick check (TIFF) or the
    structure is not understood: the decoder is asked then."""
    check = {"JPEG": _jpeg_whole, "MPO": _jpeg_whole, "PNG": _png_whole,
             "HEIF": _isobmff_whole}.get(fmt)
    if check is None:
        return False
    try:
        with open(path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as data:
            return bool(check(data))
    except (OSError, ValueError, struct.error):
        return False


def _jpeg_whole(data) -> bool:
    """The segments up to the first scan are whole and an end-of-image marker
    follows it (entropy-coded data cannot hold one: a file cut within its
    scans has none after the first, its EXIF thumbnail's comes before)."""
    n = len(data)
    if n < 4 or data[0:2] != b"\xff\xd8":
        return False
    pos = 2
    while pos + 4 <= n:
        if data[pos] != 0xFF:
            return False
        marker = data[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker == 0x01 or 0xD0 <= marker <= 0xD7:  # no length
            pos += 2
            continue
        if marker == 0xD9:
            return False  # an end before any scan
        (length,) = struct.unpack(">H", data[pos + 2:pos + 4])
        if marker == 0xDA:
            return data.find(b"\xff\xd9", pos + 2 + length) != -1
        pos += 2 + length
    return False


def _png_whole(data) -> bool:
    """Every chunk lies within the file, up to an IEND chunk."""
    n = len(data)
    if data[0:8] != b"\x89PNG\r\n\x1a\n":
        return False
    pos = 8
    while pos + 8 <= n:
        (length,) = struct.unpack(">I", data[pos:pos + 4])
        kind = data[pos + 4:pos + 8]
        if pos + 12 + length > n:
            return False
        if kind == b"IEND":
            return True
        pos += 12 + length
    return False


def _isobmff_whole(data) -> bool:
    """HEIC/HEIF: the top-level boxes tile the file exactly (a cut file's
    last box, its media data, runs past its end)."""
    n = len(data)
    pos = 0
    while pos < n:
        if pos + 8 > n:
            return False
        (size,) = struct.unpack(">I", data[pos:pos + 4])
        if size == 1:
            if pos + 16 > n:
                return False
            (size,) = struct.unpack(">Q", data[pos + 8:pos + 16])
        elif size == 0:
            size = n - pos
        if size < 8 or pos + size > n:
            return False
        pos += size
    return pos == n and n > 0


def _to_rgb8(im) -> np.ndarray:
    """An RGB uint8 array of a decoded PIL image of any mode.

    Pillow's ``convert("RGB")`` clips 16- and 32-bit grey to 255 (a 16-bit
    PNG turns white): those are scaled to 8 bits here, 16-bit by their full
    range (÷ 257), float images by [0, 1] when they lie within it.
    """
    mode = im.mode
    if mode == "RGB":
        return np.asarray(im)  # (convert would copy the pixels once more)
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
        try:
            written = cv2.imwrite(str(tmp), arr, params)
        except cv2.error:  # OpenCV 4.x raises for an extension it has no writer for
            written = False
        if not written:
            raise input_error(path, "cannot write image (unsupported extension?)")

"""Property-based tests of the point-cloud readers (io/pointclouds.py: LAS/LAZ,
E57, vertex-only PLY, PTS/XYZ): any file gives a cloud or one ``InputError``
naming the file (exit 2 on the command line), never another exception, and
each read stays within the time and memory bounds of hypothesis_bounds.

Each suite starts from a small valid file written by ``write_point_cloud``
and mutates what its format's reader trusts: the LAS public header's counts,
offsets, scales and bounding box; bytes changed or inserted anywhere in a
LAS/LAZ; the E57 XML section and binary pages (with the pages' CRC-32C
checksums recomputed, so that the mutation reaches libE57's parser rather
than its checksum test); PLY headers; the lines of PTS/XYZ text. A cloud that is returned must be
sound: finite coordinates, at least one point, no more than ``max_points``,
intensities in [0, 1], one colour per point.

Four suites of :data:`~hypothesis_bounds.EXAMPLES` examples (500 in CI), one
per reader (LAS/LAZ, E57, PLY, PTS/XYZ); each example is one of its kinds of
mutation or arbitrary content under that reader's suffix. The five gaps of
the LAS/LAZ reader these suites found are closed and tested one by one
(test_las_known_gap_*).
"""

from __future__ import annotations

import atexit
import math
import re
import shutil
import struct
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis_bounds import SUITE, call_bounded, nasty_numbers

pytestmark = pytest.mark.filterwarnings("ignore")

_TMP = Path(tempfile.mkdtemp(prefix="imgreg-hypothesis-clouds-"))
atexit.register(shutil.rmtree, _TMP, True)  # the scratch folder goes with the run

SUFFIXES = (".las", ".laz", ".e57", ".ply", ".pts", ".xyz")


def _valid_files() -> dict[str, bytes]:
    """The bytes of one small valid cloud (40 points, intensity and colour) per format."""
    from napari_imgreg.io.pointclouds import PointCloud, write_point_cloud

    rng = np.random.default_rng(0)
    n = 40
    xyz = np.column_stack([rng.uniform(0, 10, n), rng.normal(0, 0.1, n), rng.uniform(0, 5, n)])
    cloud = PointCloud(xyz, rng.uniform(0, 1, n).astype(np.float32),
                       rng.integers(0, 256, (n, 3)).astype(np.uint8))
    return {s: write_point_cloud(_TMP / f"valid{s}", cloud).read_bytes() for s in SUFFIXES}


VALID = _valid_files()


def _read(name: str, content: bytes, **kwargs):
    """Write one example's file (the same path each time) and read it, bounded;
    a cloud that comes back is checked for soundness."""
    from napari_imgreg.errors import InputError
    from napari_imgreg.io.pointclouds import PointCloud, read_point_cloud

    path = _TMP / name
    path.write_bytes(content)
    out = call_bounded(read_point_cloud, path, **kwargs)
    if isinstance(out, InputError):
        message = str(out)
        assert message.startswith(f"{path}: ") and "\n" not in message, message
        return out
    assert isinstance(out, PointCloud)
    n = len(out.xyz)
    assert n >= 1 and np.isfinite(out.xyz).all(), "a cloud with no points or non-finite ones"
    cap = kwargs.get("max_points", 10_000_000)
    assert cap is None or n <= cap, f"{n} points kept, more than max_points={cap}"
    if out.intensity is not None:
        assert out.intensity.shape == (n,)
        assert np.isfinite(out.intensity).all() and out.intensity.min() >= 0 and out.intensity.max() <= 1
    if out.rgb is not None:
        assert out.rgb.shape == (n, 3) and out.rgb.dtype == np.uint8
    assert out.n_points_file >= n
    return out


#: Arbitrary content, as bytes or as text.
_content = st.one_of(st.binary(max_size=300),
                     st.text(max_size=300).map(lambda s: s.encode("utf-8", "surrogatepass")))


def _any_bytes(suffix, content):
    _read(f"any{suffix}", content)


def _any_bytes_args(*suffixes):
    """Arbitrary content under one of these suffixes (each suite's third kind)."""
    return st.tuples(st.sampled_from(suffixes), _content)


# --------------------------------------------------------------- LAS / LAZ
#: Fields of the LAS 1.4 public header block: (offset, struct format).
LAS_FIELDS = {
    "version_minor": (25, "B"),
    "header_size": (94, "H"),
    "offset_to_points": (96, "I"),
    "n_vlrs": (100, "I"),
    "point_format": (104, "B"),
    "record_length": (105, "H"),
    "legacy_point_count": (107, "I"),
    "scale_x": (131, "d"),
    "scale_z": (147, "d"),
    "offset_y": (163, "d"),
    "max_x": (179, "d"),
    "min_x": (187, "d"),
    "min_z": (219, "d"),
    "evlr_start": (235, "Q"),
    "n_evlrs": (243, "I"),
    "point_count": (247, "Q"),
}

#: Gaps these suites found in the LAS/LAZ reader, now closed by
#: io/pointclouds.py checking the header against the file's size before
#: laspy reads (``_check_las_header``) and turning lazrs's panics into one
#: line; each has its reproduction below (test_las_known_gap_*):
#: 1. the number of VLRs (offset 100): 2**32 − 1 of them in a 2 kB file ran
#:    laspy for hours (each VLR takes ≥ 54 bytes before the point data);
#: 2. the extended VLRs (1.4: start 235, count 243): laspy allocated each
#:    one's declared length (a uint64) before reading it;
#: 3. the offset to the point data (96) beyond the file: read in one piece;
#: 4. bytes inserted into a LAS's points (the count × record length beyond
#:    the file) or into a LAZ (a declared count no chunk can hold, a chunk
#:    table read from the wrong place);
#: 5. bytes changed in a LAZ's chunks: lazrs's ``PanicException`` (a
#:    BaseException that ``except Exception`` let through).


def _packed(fmt: str, value) -> bytes:
    """``value`` packed as ``fmt``: floats as they come (NaN, ±inf, 1e308),
    integers wrapped into the field's width (2**63 in a uint32 is 0)."""
    if fmt == "d":
        try:
            return struct.pack("<d", float(value))
        except OverflowError:  # an integer beyond float's range
            return struct.pack("<d", math.inf)
    bits = struct.calcsize(fmt) * 8
    if isinstance(value, float):
        value = int(value) if math.isfinite(value) else 2**bits - 1
    return struct.pack(f"<{fmt}", int(value) % 2**bits)


#: Values for a header field: the hostile numbers, and the edges of its width.
_field_values = st.one_of(
    nasty_numbers,
    st.sampled_from([2**8 - 1, 2**16 - 1, 2**32 - 1, 2**64 - 1, 0x80 | 6, 0x80 | 7, 3, 10, 11,
                     227, 375, 1e-300, -1e-9, 1e-4, 0.001]),
    st.integers(0, 4000),
)


_las_header_fields_args = st.tuples(st.sampled_from([".las", ".laz"]),
       st.lists(st.tuples(st.sampled_from(sorted(LAS_FIELDS)), _field_values), min_size=1,
                max_size=3))


def _las_header_fields(suffix, edits):
    data = bytearray(VALID[suffix])
    for name, value in edits:
        offset, fmt = LAS_FIELDS[name]
        data[offset:offset + struct.calcsize(fmt)] = _packed(fmt, value)
    _read(f"header{suffix}", bytes(data))


_las_bytes_args = st.tuples(st.sampled_from([".las", ".laz"]),
       st.lists(st.tuples(st.integers(0, 4000), st.integers(0, 255)), max_size=6),
       st.one_of(st.none(), st.integers(0, 4000)))


def _las_bytes(suffix, flips, cut):
    """Bytes anywhere: the header, the VLRs (CRS, LASzip record), the chunk
    table and the points; or cut short."""
    data = bytearray(VALID[suffix])
    for pos, value in flips:
        data[pos % len(data)] = value
    if cut is not None:
        del data[cut % len(data):]
    _read(f"bytes{suffix}", bytes(data))


_las_insert_args = st.tuples(st.sampled_from([".las", ".laz"]), st.integers(0, 4000),
                             st.binary(min_size=1, max_size=8))


def _las_insert(suffix, pos, inserted):
    """Bytes inserted anywhere: every offset after them is shifted."""
    data = VALID[suffix]
    at = pos % len(data)
    _read(f"insert{suffix}", data[:at] + inserted + data[at:])


def _cases(*helpers):
    """One suite over several mutation kinds: each example draws one kind and its arguments."""
    return st.one_of(*[args.map(lambda a, fn=fn: (fn, a)) for fn, args in helpers])


@SUITE
@given(_cases((_las_header_fields, _las_header_fields_args), (_las_bytes, _las_bytes_args),
               (_las_insert, _las_insert_args), (_any_bytes, _any_bytes_args(".las", ".laz"))))
def test_las_laz(case):
    fn, args = case
    fn(*args)


def _las_with(suffix: str, **fields) -> bytes:
    data = bytearray(VALID[suffix])
    for name, value in fields.items():
        offset, fmt = LAS_FIELDS[name]
        data[offset:offset + struct.calcsize(fmt)] = _packed(fmt, value)
    return bytes(data)


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_las_known_gap_1_vlr_count_beyond_the_room_is_refused(suffix):
    err = _read(f"vlrs{suffix}", _las_with(suffix, n_vlrs=2**32 - 1))
    assert "number of VLRs, 4294967295" in str(err), err


def test_las_known_gap_2_evlr_beyond_the_file_is_refused_at_once():
    err = _read("evlr.las", _las_with(".las", evlr_start=0, n_evlrs=1))  # one EVLR, "at" the file's start
    assert "EVLR" in str(err), err
    err = _read("evlrs.las", _las_with(".las", evlr_start=375, n_evlrs=2**32 - 1))
    assert "4294967295 EVLRs" in str(err), err


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_las_known_gap_3_offset_to_points_beyond_the_file_is_refused(suffix):
    err = _read(f"offset{suffix}", _las_with(suffix, offset_to_points=2**32 - 1))
    assert "offset to the point data, 4294967295" in str(err), err


def test_las_known_gap_4_inserted_bytes_are_refused_or_read():
    """The audit's cases (3 bytes at 1824 of the LAS, b"\\x86\\x17" at 1340
    of the LAZ), then the same bytes at every 61st offset of each file: a
    cloud or one line, within the bounds."""
    for suffix, inserted, first in ((".las", b"\0\0\0", 1824), (".laz", b"\x86\x17", 1340)):
        data = VALID[suffix]
        for at in (first, *range(0, len(data), 61)):
            _read(f"insert{suffix}", data[:at] + inserted + data[at:])
    err = _read("count.laz", _las_with(".laz", point_count=2**40))
    assert "point count 1099511627776" in str(err), err


def test_las_known_gap_5_lazrs_panic_is_one_line():
    data = bytearray(VALID[".laz"])
    for pos, value in zip((1206, 1703, 2595, 3348, 3560, 3899), (83, 6, 148, 129, 156, 249)):
        data[pos % len(data)] = value
    _read("panic.laz", bytes(data))


def _laz_table(data: bytearray) -> int:
    """Where the chunk table of a LAZ starts (the 64-bit offset before its points)."""
    offset = struct.unpack_from("<I", data, 96)[0]
    return struct.unpack_from("<q", data, offset)[0]


def test_las_known_gap_6_a_chunk_table_that_misses_points_is_refused():
    """A LAZ whose chunk table no longer describes its chunks (bytes inserted
    in the points moved the table; CI's fuzz found it): the decompressor read
    the first chunk anyway, and a layer size of 2.9 GB in it aborted the
    process (Rust's failed allocation) instead of giving one line."""
    data = bytearray(VALID[".laz"])
    table = _laz_table(data)
    start = struct.unpack_from("<I", data, 96)[0] + 8  # the first chunk
    point_size = struct.unpack_from("<H", data, 105)[0]
    struct.pack_into("<I", data, start + point_size + 4 + 6 * 4, 2_914_812_416)  # layer 7
    moved = bytearray(data)
    struct.pack_into("<I", moved, table, 8_491_171)  # the table's version
    err = _read("table_version.laz", bytes(moved))
    assert "chunk table has version 8491171" in str(err), err
    emptied = bytearray(data)
    struct.pack_into("<I", emptied, table + 4, 0)  # no chunks
    err = _read("table_empty.laz", bytes(emptied))
    assert "chunk table holds 0 of its 40 points" in str(err), err
    # The 6 bytes at 548 that CI's fuzz drew.
    raw = bytes(VALID[".laz"])
    _read("insert.laz", raw[:548] + bytes.fromhex("82bcadae3a95") + raw[548:])


def test_las_known_gap_7_a_laszip_record_named_with_trailing_bytes_is_checked():
    """laspy reads a VLR's user id up to its first NUL, so "laszip encoded\\0\\x9f"
    is the LASzip record to it; the size checks skipped it and a layer size
    of 1.66 GB aborted the process (CI's fuzz, one byte flipped in the name)."""
    data = bytearray(VALID[".laz"])
    header_size = struct.unpack_from("<H", data, 94)[0]
    data[header_size + 2 + 15] = 159  # the user id's last byte (the LASzip record is the first VLR)
    start = struct.unpack_from("<I", data, 96)[0] + 8
    point_size = struct.unpack_from("<H", data, 105)[0]
    struct.pack_into("<I", data, start + point_size + 4 + 2 * 4, 1_660_944_384)  # layer 3
    err = _read("laszip_name.laz", bytes(data))
    assert "layers larger than itself" in str(err), err


def test_a_bound_the_reader_swallows_still_fails():
    """A reader's ``except Exception`` turned the bound's exception into
    ``InputError("… cannot read LAS (BoundExceeded: …)")``: call_bounded
    still reports the bound (this is how the LAS gaps above were found)."""
    import hypothesis_bounds

    from napari_imgreg.errors import input_error

    def swallowing_spin():
        try:
            while True:
                pass
        except Exception as exc:  # noqa: BLE001 - the reader's habit under test
            raise input_error("x.las", f"cannot read LAS ({type(exc).__name__}: {exc})") from None

    def swallowing_then_returns():
        try:
            while True:
                pass
        except Exception:  # noqa: BLE001 - the reader's habit under test
            return

    limit, hypothesis_bounds.TIME_LIMIT_S = hypothesis_bounds.TIME_LIMIT_S, 0.2
    try:
        for fn in (swallowing_spin, swallowing_then_returns):
            with pytest.raises(hypothesis_bounds.BoundExceeded):
                call_bounded(fn)
    finally:
        hypothesis_bounds.TIME_LIMIT_S = limit
    with pytest.raises(hypothesis_bounds.BoundExceeded, match="MemoryError"):
        call_bounded(lambda: (_ for _ in ()).throw(input_error("x.las", "cannot read (MemoryError)")))


# --------------------------------------------------------------------- E57
_PAGE, _PAYLOAD = 1024, 1020  # an E57 page: 1020 bytes and their CRC-32C


def _crc32c_table() -> list[int]:
    table = []
    for i in range(256):
        c = i
        for _ in range(8):
            c = (c >> 1) ^ 0x82F63B78 if c & 1 else c >> 1
        table.append(c)
    return table


_CRC_TABLE = _crc32c_table()


def _crc32c(data: bytes) -> int:
    c = 0xFFFFFFFF
    for byte in data:
        c = _CRC_TABLE[(c ^ byte) & 0xFF] ^ (c >> 8)
    return c ^ 0xFFFFFFFF


def _e57_logical(data: bytes) -> bytearray:
    """The file's bytes without the page checksums."""
    return bytearray(b"".join(data[k:k + _PAYLOAD] for k in range(0, len(data), _PAGE)))


def _e57_pages(logical: bytearray, xml_length: int | None = None) -> bytes:
    """Logical bytes laid out in checksummed pages, the physical header
    (file length, XML length) made to agree with them."""
    logical = bytearray(logical)
    logical += b"\0" * (-len(logical) % _PAYLOAD)
    struct.pack_into("<Q", logical, 16, len(logical) // _PAYLOAD * _PAGE)
    if xml_length is not None:
        struct.pack_into("<Q", logical, 32, xml_length)
    out = bytearray()
    for k in range(0, len(logical), _PAYLOAD):
        page = bytes(logical[k:k + _PAYLOAD])
        out += page + struct.pack(">I", _crc32c(page))
    return bytes(out)


def _e57_xml() -> tuple[int, str]:
    """The valid E57's XML section: its logical offset and its text."""
    data = VALID[".e57"]
    physical, length = struct.unpack_from("<QQ", data, 24)
    start = physical // _PAGE * _PAYLOAD + physical % _PAGE
    return start, bytes(_e57_logical(data)[start:start + length]).decode("utf-8")


XML_START, XML = _e57_xml()
#: The XML's numbers, element text and attribute values (``recordCount``,
#: ``fileOffset``, the pose, the limits): what a reader sizes and places from.
_XML_NUMBERS = [m.span() for m in re.finditer(r'(?<=>)-?[0-9][0-9.eE+-]*(?=<)|(?<==")-?[0-9][0-9.eE+-]*(?=")',
                                              XML)]
_XML_TAGS = sorted(set(re.findall(r"<([A-Za-z]+)", XML)))


_e57_xml_args = st.tuples(st.lists(st.tuples(st.integers(0, len(_XML_NUMBERS) - 1),
                          st.one_of(nasty_numbers.map(repr), st.sampled_from(
                              ["", "x", "-1", "1e400", "99999999999999999999", "0", "40.5"]))),
                min_size=0, max_size=3),
       st.lists(st.tuples(st.integers(0, len(XML)), st.integers(0, 12),
                          st.one_of(st.text(max_size=8), st.sampled_from(_XML_TAGS).map(
                              lambda t: f"<{t}>"))), max_size=2))


def _e57_xml(numbers, splices):
    """The XML section: record counts, binary section offsets, the pose,
    the intensity and colour limits replaced; text spliced in or cut out."""
    text = XML
    for index, value in sorted(numbers, key=lambda e: -_XML_NUMBERS[e[0]][0]):
        a, b = _XML_NUMBERS[index]
        text = text[:a] + value + text[b:]  # from the end: earlier spans stay valid
    for pos, n_cut, insert in splices:
        pos = min(pos, len(text))
        text = text[:pos] + insert + text[pos + n_cut:]
    xml = text.encode("utf-8", "surrogatepass")
    logical = _e57_logical(VALID[".e57"])[:XML_START] + xml
    _read("xml.e57", _e57_pages(logical, xml_length=len(xml)))


_e57_binary_args = st.tuples(st.lists(st.tuples(st.integers(48, 5000), st.integers(0, 255)),
                                      min_size=1, max_size=6),
       st.one_of(st.none(), st.integers(48, 5000)))


def _e57_binary(flips, cut):
    """Bytes past the physical header (binary sections, their headers, the
    XML) changed or cut, the checksums and the recorded length kept right."""
    logical = _e57_logical(VALID[".e57"])
    for pos, value in flips:
        logical[pos % len(logical)] = value
    if cut is not None:
        del logical[max(48, cut % len(logical)):]
    _read("binary.e57", _e57_pages(logical))


@SUITE
@given(_cases((_e57_xml, _e57_xml_args), (_e57_binary, _e57_binary_args),
               (_any_bytes, _any_bytes_args(".e57"))))
def test_e57(case):
    fn, args = case
    fn(*args)


def test_e57_mutations_reach_libe57():
    """The suites above are only as good as their files: re-paging the valid
    file unchanged gives the same bytes (checksums, lengths), and an E57 with
    a valid header and checksums but a broken XML is refused by libE57's
    parser, in one line, not by the header check."""
    assert _e57_pages(_e57_logical(VALID[".e57"])) == VALID[".e57"]
    assert len(_XML_NUMBERS) >= 30 and "cartesianX" in _XML_TAGS
    assert 'recordCount="40"' in XML and 'fileOffset="48"' in XML
    logical = _e57_logical(VALID[".e57"])[:XML_START] + b"<e57Root"
    err = _read("broken.e57", _e57_pages(logical, xml_length=8))
    assert "cannot read E57" in str(err) and "signature" not in str(err), err


# --------------------------------------------------------------------- PLY
_ply_properties = st.lists(
    st.tuples(st.sampled_from(["float", "double", "uchar", "int", "ushort", "char", "list uchar int",
                               "float32", "junk"]),
              st.sampled_from(["x", "y", "z", "intensity", "scalar_Intensity", "red", "green",
                               "blue", "nx", "X"])),
    max_size=8).map(lambda props: [f"property {t} {n}" for t, n in props])


_ply_cloud_header_args = st.tuples(st.one_of(nasty_numbers, st.text(max_size=6)),
       st.sampled_from(["ascii", "binary_little_endian", "binary_big_endian", "utf8"]),
       st.one_of(st.just(["property float x", "property float y", "property float z",
                          "property float intensity"]), _ply_properties),
       st.one_of(st.none(), st.sampled_from(["element face 0", "element face 1",
                                             "element normal 3", "element vertex 2"])),
       st.binary(max_size=120))


def _ply_cloud_header(n_vertex, fmt, properties, extra_element, body):
    lines = ["ply", f"format {fmt} 1.0", f"element vertex {n_vertex}", *properties]
    if extra_element:
        lines.append(extra_element)
    lines.append("end_header")
    header = "\n".join(lines).replace("\r", " ") + "\n"
    if fmt == "ascii" and not body:
        body = b"0 0 0 1\n1 0 0 2\n0 1 0 3\n"
    _read("cloud.ply", header.encode("utf-8", "surrogatepass") + body)


_ply_binary_bytes_args = st.tuples(st.lists(st.tuples(st.integers(0, 1500), st.integers(0, 255)),
                                            min_size=1, max_size=6),
       st.one_of(st.none(), st.integers(0, 1500)))


def _ply_binary_bytes(flips, cut):
    data = bytearray(VALID[".ply"])
    for pos, value in flips:
        data[pos % len(data)] = value
    if cut is not None:
        del data[cut % len(data):]
    _read("bytes.ply", bytes(data))


@SUITE
@given(_cases((_ply_cloud_header, _ply_cloud_header_args),
               (_ply_binary_bytes, _ply_binary_bytes_args), (_any_bytes, _any_bytes_args(".ply"))))
def test_ply(case):
    fn, args = case
    fn(*args)


# ----------------------------------------------------------------- PTS / XYZ
_text_cell = st.one_of(nasty_numbers.map(repr), st.sampled_from(["", "x", "1,5", "nan", "-", "1e",
                                                               "0x10", "255", "65536", "-0"]))
_text_line = st.one_of(
    st.lists(_text_cell, min_size=1, max_size=8).map(" ".join),
    st.lists(_text_cell, min_size=3, max_size=7).map(",".join),
    st.sampled_from(["//X,Y,Z,R,G,B,Intensity", "# comment", "x y z intensity", "X Y Z Nx Ny Nz",
                     "40", "3", "0", "-1", "1e12", ""]),
    st.text(max_size=20).map(lambda s: s.replace("\n", " ")),
)


_text_lines_args = st.tuples(st.sampled_from([".pts", ".xyz"]),
       st.lists(st.tuples(st.integers(0, 45), _text_line), min_size=1, max_size=5),
       st.booleans(),
       st.sampled_from([(10_000_000, None), (1, None), (7, None), (None, None), (10_000_000, 1e-9),
                        (10_000_000, 0.5), (10_000_000, 1e9), (3, 1e-6)]))


def _text_lines(suffix, edits, replace, limits):
    """A valid PTS/XYZ file with lines replaced or inserted; read whole or
    decimated (``max_points``, ``voxel_m``) so the voxel grid meets the
    hostile coordinates too."""
    lines = VALID[suffix].decode("ascii").splitlines()
    for index, line in edits:
        index = min(index, len(lines))
        if replace and index < len(lines):
            lines[index] = line
        else:
            lines.insert(index, line)
    max_points, voxel_m = limits
    _read(f"lines{suffix}", ("\n".join(lines) + "\n").encode("utf-8", "surrogatepass"),
          max_points=max_points, voxel_m=voxel_m)


_text_numbers_args = st.tuples(st.sampled_from([".pts", ".xyz"]),
       st.lists(st.lists(nasty_numbers, min_size=3, max_size=7), min_size=1, max_size=6),
       st.sampled_from([(10_000_000, None), (2, None), (10_000_000, 0.01)]))


def _text_numbers(suffix, rows, limits):
    """Rows of hostile numbers only (1e308 and −1e308 span more than a
    float can: the decimation's voxel grid must still hold)."""
    width = len(rows[0])
    text = "\n".join(" ".join(repr(float(v)) if isinstance(v, float) else str(v)
                              for v in (row + row * 7)[:width]) for row in rows) + "\n"
    max_points, voxel_m = limits
    _read(f"numbers{suffix}", text.encode(), max_points=max_points, voxel_m=voxel_m)


@SUITE
@given(_cases((_text_lines, _text_lines_args), (_text_numbers, _text_numbers_args),
               (_any_bytes, _any_bytes_args(".pts", ".xyz"))))
def test_pts_xyz(case):
    fn, args = case
    fn(*args)

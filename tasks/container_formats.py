"""Headers of two image containers of measured BTFs, parsed from bytes: Radiance RGBE and BIG.

**Radiance RGBE** (``.hdr``, Bonn's ATRIUM HDR archives): a text header starting ``#?``,
``KEY=value`` lines, an empty line, a resolution line, then the pixel stream. The standard
resolution line ``-Y H +X W`` means H rows stored top to bottom, each W pixels left to right;
``+Y`` stores the bottom row first, ``-X`` right to left. ATRIUM writes ``+X 256 -Y 256``,
which in Radiance's own terms would store columns; every reader of ATRIUM data treats it as
256 rows of 256 pixels instead, and so does this one. Which way up those rows go is the
caller's choice (``atrium_rows``, see docs/formats.md).

**BIG** (UTIA): little-endian; the magic ``42 49 47 00 00 00 00 00``; then chunks of ``u64 id``,
``u64 length`` and a payload padded to a multiple of 8 bytes. The chunk walk needs the file (see
:mod:`pipeline.sources`); :func:`big_layout` interprets what it found.
"""

from __future__ import annotations

import dataclasses
import math
import re

import numpy as np


class FormatError(ValueError):
    """Bytes that do not follow their format; the message says what is wrong (not where)."""


# --- Radiance RGBE -------------------------------------------------------------------------

ATRIUM_ROWS = ("bottom-up", "top-down")
_RESOLUTION = re.compile(rb"([+-])([XY]) (\d+) ([+-])([XY]) (\d+)")
_HEADER_LIMIT = 1 << 16  # a header longer than this is not an RGBE header


@dataclasses.dataclass(frozen=True)
class RgbeHeader:
    """What the text header of an RGBE file says about its pixels."""

    height: int
    width: int
    offset: int  # byte where the pixel stream starts
    flip_rows: bool  # the stream's first row is the picture's bottom row
    flip_columns: bool  # each row is stored right to left
    resolution: str  # the resolution line as written, for messages and attrs


def parse_rgbe_header(data: bytes, *, atrium_rows: str = "bottom-up") -> RgbeHeader:
    """The header of a Radiance RGBE (``.hdr``) file from its first bytes.

    Parameters
    ----------
    data
        The file's bytes (at least the header and the resolution line).
    atrium_rows
        Row order taken for ATRIUM's non-standard resolution line ``+X W -Y H``:
        ``"bottom-up"`` (the stream's first row is the bottom one, as btf-extractor reads
        ATRIUM HDR files) or ``"top-down"``.

    Raises
    ------
    FormatError
        No ``#?`` signature, no end of header, a pixel format other than ``32-bit_rle_rgbe``
        (XYZE is refused by name), or a resolution line that is not row-major.
    """
    if atrium_rows not in ATRIUM_ROWS:
        raise ValueError(f"atrium_rows must be one of {ATRIUM_ROWS}, got {atrium_rows!r}")
    if not data.startswith(b"#?"):
        raise FormatError("not a Radiance RGBE file (it does not start with '#?')")
    end = data.find(b"\n\n", 0, _HEADER_LIMIT)
    if end < 0:
        raise FormatError("no end of the RGBE header (an empty line) in its first 64 KiB")
    for line in data[:end].split(b"\n")[1:]:
        if line.startswith(b"FORMAT="):
            fmt = line[7:].strip().decode("latin-1")
            if fmt != "32-bit_rle_rgbe":
                raise FormatError(f"pixel format {fmt!r} is not supported (only "
                                  "32-bit_rle_rgbe; XYZE files are not read)")
    stop = data.find(b"\n", end + 2, end + 2 + 64)
    line = data[end + 2: stop if stop >= 0 else end + 2]
    match = _RESOLUTION.fullmatch(line.strip())
    if stop < 0 or match is None:
        raise FormatError(f"bad resolution line {line[:40]!r} after the RGBE header")
    sign1, axis1, n1, sign2, axis2, n2 = (g.decode() for g in match.groups())
    text = line.strip().decode()
    if {axis1, axis2} != {"X", "Y"}:
        raise FormatError(f"bad resolution line {text!r}: needs one X and one Y")
    if axis1 == "Y":  # row-major: the standard orientations
        return RgbeHeader(int(n1), int(n2), stop + 1, sign1 == "+", sign2 == "-", text)
    if (sign1, sign2) == ("+", "-"):  # ATRIUM's "+X W -Y H": rows after all (see above)
        return RgbeHeader(int(n2), int(n1), stop + 1, atrium_rows == "bottom-up", False, text)
    raise FormatError(f"resolution line {text!r} stores columns, not rows; only row-major "
                      "files (-Y H +X W and its flips) and ATRIUM's '+X W -Y H' are read")


# --- BIG ------------------------------------------------------------------------------------

BIG_MAGIC = b"BIG\0\0\0\0\0"
BIG_DATA = 8  # the chunk id of the image data
BIG_CHUNK_NAMES = {1: "number of images", 2: "number of tiles", 3: "image height",
                   4: "image width", 5: "number of planes", 6: "data order", 7: "data type",
                   8: "data", 9: "colour space", 10: "illuminant", 16: "list of directions"}
_BIG_TYPES = {1: ("half", "<f2"), 2: ("float", "<f4"), 3: ("double", "<f8")}
_BIG_OTHER_TYPES = {4: "signed char", 5: "unsigned char", 6: "short", 7: "unsigned short",
                    8: "int", 9: "unsigned int", 10: "long long", 11: "unsigned long long",
                    12: "bool"}
# data order: chunk ids from the outermost loop to the innermost
_ORDER_NAMES = {1: "image", 2: "tile", 3: "row", 4: "pixel", 5: "plane"}
_DEFAULT_ORDERS = ((1, 2, 3, 4, 5), (1, 3, 4, 5))  # with and without the tile loop
# direction lists, by the id a list may start with; spherical angles preferred
_DIRECTION_LISTS = {1: "ideal device angles", 2: "real device angles",
                    3: "ideal spherical angles", 4: "real spherical angles",
                    5: "ideal half-difference angles", 6: "real half-difference angles"}
_PREFERRED_LISTS = (3, 4, None, 1, 2)


@dataclasses.dataclass(frozen=True, eq=False)
class BigLayout:
    """Where a BIG file's images are and what they hold.

    ``directions`` has one row per image, ``(theta_light, phi_light, theta_view, phi_view)``
    in degrees: the order of UTIA's file names (``tl pl tv pv``). BIG's description says only
    "four doubles per image", so that order is an assumption; the unit is detected
    (:func:`angles_in_degrees`).
    """

    images: int
    height: int
    width: int
    planes: int
    type_name: str  # "half", "float" or "double"
    dtype: str  # its numpy dtype, little-endian
    data_offset: int
    directions: np.ndarray
    angle_unit: str  # the unit the file's directions were written in
    direction_list: str  # which of BIG's direction lists they came from
    colour_space: str  # the colour space chunk's text, "" without one
    illuminant: str

    @property
    def image_bytes(self) -> int:
        """Bytes of one image in the data chunk."""
        return self.height * self.width * self.planes * np.dtype(self.dtype).itemsize


def _u64s(payload: bytes, name: str) -> list[int]:
    if len(payload) < 8:
        raise FormatError(f"chunk '{name}' holds {len(payload)} bytes, less than one number")
    return np.frombuffer(payload[: len(payload) // 8 * 8], "<u8").tolist()


def _text(payload: bytes) -> str:
    return payload.split(b"\0", 1)[0].decode("latin-1").strip()


def _number(chunks: dict[int, list[bytes]], cid: int, default: int | None = None) -> int:
    name = BIG_CHUNK_NAMES[cid]
    if cid not in chunks:
        if default is None:
            raise FormatError(f"no chunk '{name}' (id {cid})")
        return default
    value = _u64s(chunks[cid][-1], name)[0]  # a chunk defined again replaces the earlier one
    if value < 1:
        raise FormatError(f"chunk '{name}' (id {cid}) is {value}")
    return value


def _data_type(chunks: dict[int, list[bytes]]) -> tuple[str, str]:
    types = _u64s(chunks[7][-1], "data type") if 7 in chunks else [2]  # float by default
    if types[0] == 0:
        raise FormatError("mixed data types (a type per image) are not supported")
    if types[0] not in _BIG_TYPES:
        name = _BIG_OTHER_TYPES.get(types[0], "unknown")
        raise FormatError(f"data type {types[0]} ({name}) is not supported; BIG images are "
                          "read as half, float or double")
    return _BIG_TYPES[types[0]]


def _check_order(chunks: dict[int, list[bytes]]) -> None:
    if 6 not in chunks:
        return
    order = tuple(v for v in _u64s(chunks[6][-1], "data order") if v)  # zeros pad the chunk
    if order not in _DEFAULT_ORDERS:
        names = ", ".join(_ORDER_NAMES.get(v, f"unknown ({v})") for v in order)
        raise FormatError(f"data order {names} is not supported; only the default order "
                          "image, tile, row, pixel, plane")


def angles_in_degrees(values: np.ndarray) -> tuple[np.ndarray, str]:
    """Angles in degrees, and the unit they were found in.

    BIG does not say which unit its directions use. Radians are assumed when every value is
    within ``[-2 pi, 2 pi]``: a hemisphere sampled in degrees has phi up to 300 or more and theta
    up to 75, so only a sampling confined to a few degrees around the pole could be mistaken.
    Degrees are rounded to 1e-6 so that converted radians give the grid's whole degrees back.
    """
    values = np.asarray(values, np.float64)
    if not np.isfinite(values).all():
        raise FormatError("the list of directions holds non-finite values")
    if values.size and np.abs(values).max() <= 2 * math.pi + 1e-9:
        return np.round(np.degrees(values), 6), "radians"
    return values, "degrees"


def _directions(chunks: dict[int, list[bytes]], images: int) -> tuple[np.ndarray, str, str]:
    lists: dict[int | None, np.ndarray] = {}
    for payload in chunks.get(16, []):
        size = images * 32
        if len(payload) == size:
            lists.setdefault(None, np.frombuffer(payload, "<f8"))
        elif len(payload) == size + 8:
            kind = int(np.frombuffer(payload[:8], "<u8")[0])
            lists.setdefault(kind, np.frombuffer(payload[8:], "<f8"))
        else:
            raise FormatError(f"the list of directions holds {len(payload)} bytes, not four "
                              f"doubles for each of the {images} images ({size} bytes, or "
                              f"{size + 8} with the list's kind first)")
    if not lists:
        raise FormatError("no list of directions (chunk 16): the images' directions are "
                          "unknown")
    kind = next((k for k in _PREFERRED_LISTS if k in lists), next(iter(lists)))
    degrees, unit = angles_in_degrees(lists[kind].reshape(images, 4))
    label = _DIRECTION_LISTS.get(kind, "unnamed" if kind is None else f"list {kind}")
    return degrees, unit, label


def big_layout(chunks: dict[int, list[bytes]], data: tuple[int, int] | None) -> BigLayout:
    """Interpret the chunks of a BIG file.

    Parameters
    ----------
    chunks
        The payload of every chunk but the data, by chunk id, in file order.
    data
        ``(offset, length)`` of the data chunk's payload, ``None`` without one.

    Raises
    ------
    FormatError
        A missing or zero size, an unsupported data order, data type or tile count, a
        direction list of the wrong length, or a data chunk whose length disagrees with the
        number and size of the images.
    """
    images = _number(chunks, 1)
    height, width = _number(chunks, 3), _number(chunks, 4)
    planes = _number(chunks, 5, default=1)
    tiles = _number(chunks, 2, default=1)
    if tiles != 1:
        raise FormatError(f"images of {tiles} tiles each are not supported (one tile per "
                          "image)")
    _check_order(chunks)
    type_name, dtype = _data_type(chunks)
    if data is None:
        raise FormatError("no data chunk (id 8)")
    offset, length = data
    need = images * height * width * planes * np.dtype(dtype).itemsize
    if not need <= length < need + 8:  # the payload may be padded to 8 bytes
        raise FormatError(f"the data chunk holds {length} bytes, but {images} images of "
                          f"{height} x {width} x {planes} {type_name} values are {need} bytes: "
                          "the number of images or their size disagrees with the data")
    directions, unit, label = _directions(chunks, images)
    return BigLayout(images, height, width, planes, type_name, dtype, offset, directions, unit,
                     label, _text(chunks[9][-1]) if 9 in chunks else "",
                     _text(chunks[10][-1]) if 10 in chunks else "")

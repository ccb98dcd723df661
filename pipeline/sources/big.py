"""UTIA's BIG files: one container of every image, read image by image at its offset.

Little-endian chunks after an 8-byte magic (:mod:`tasks.container_formats`): the image count,
size, planes and data type, a list of directions, an optional colour space, and the images
(image, row, pixel, plane order). Only the chunk headers and the small metadata chunks are
read when the file is opened; an image when ingest reads it.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.errors import BTFError
from pipeline.images import ImageInfo
from pipeline.layer_sources import (
    AS_NAMED,
    LINEAR_SRGB,
    XYZ,
    Entry,
    LayerSource,
    ReadOptions,
    check_angles,
    layer_grid,
    plane_channels,
    refuse_manifest,
    xyz_note,
)
from pipeline.source_report import layers_lines, layers_report
from pipeline.sources import SourceFormat
from tasks.colour import xyz_to_linear_srgb
from tasks.container_formats import (
    BIG_CHUNK_NAMES,
    BIG_DATA,
    BIG_MAGIC,
    FormatError,
    big_layout,
)

_METADATA_LIMIT = 1 << 28  # bytes: larger chunks other than the data are not metadata


def read_big_chunks(path: Path) -> tuple[dict[int, list[bytes]], tuple[int, int] | None]:
    """Walk the chunks of a BIG file: payloads of the metadata chunks, and the data's place.

    Reads the chunk headers and the known metadata payloads only; the data is not read.

    Raises
    ------
    BTFError
        Not a BIG file (wrong magic), a chunk cut off by the end of the file, two data chunks.
    """
    size = path.stat().st_size
    chunks: dict[int, list[bytes]] = {}
    data = None
    with path.open("rb") as f:
        magic = f.read(8)
        if magic != BIG_MAGIC:
            raise BTFError(f"{path}: not a BIG file: it starts with {magic.hex(' ')}, not "
                           f"{BIG_MAGIC.hex(' ')}")
        pos = 8
        while pos < size:
            head = f.read(16)
            if len(head) < 16:
                raise BTFError(f"{path}: truncated: a chunk header at byte {pos} is cut off "
                               f"by the end of the file ({size} bytes)")
            cid, length = struct.unpack("<QQ", head)
            name = BIG_CHUNK_NAMES.get(cid, f"unknown chunk {cid}")
            start = pos + 16
            if start + length > size:
                raise BTFError(f"{path}: truncated: chunk '{name}' at byte {pos} declares "
                               f"{length} bytes, but the file ends {size - start} bytes after "
                               "its header")
            if cid == BIG_DATA:
                if data is not None:
                    raise BTFError(f"{path}: two data chunks (at bytes {data[0] - 16} and "
                                   f"{pos}); one is expected")
                data = (start, length)
            elif cid in BIG_CHUNK_NAMES and length <= _METADATA_LIMIT:
                chunks.setdefault(cid, []).append(f.read(length))
            pos = start + -(-length // 8) * 8  # payloads are padded to 8 bytes
            f.seek(pos)
    return chunks, data


@dataclass(frozen=True)
class BigReader:
    """Reads image ``index`` of a BIG file at its offset (image, row, pixel, plane order).

    ``xyz``: the planes are CIE XYZ, converted to linear sRGB unless ``keep``.
    """

    path: str
    offset: int
    image_bytes: int
    dtype: str
    shape: tuple[int, int, int]
    xyz: bool = False
    keep: bool = False

    def where(self, index: int) -> str:
        """The file and image number, for messages."""
        return f"{self.path}: image {index}"

    def __call__(self, index: int) -> np.ndarray:
        """Float32 ``(height, width, planes)`` values of image ``index``."""
        with open(self.path, "rb") as f:
            f.seek(self.offset + index * self.image_bytes)
            raw = f.read(self.image_bytes)
        if len(raw) != self.image_bytes:
            raise BTFError(f"{self.where(index)}: truncated: {len(raw)} of its "
                           f"{self.image_bytes} bytes")
        values = np.frombuffer(raw, self.dtype).reshape(self.shape).astype(np.float32)
        return xyz_to_linear_srgb(values) if self.xyz and not self.keep else values


def big_source(path: str | Path, *, xyz: str = "srgb") -> LayerSource:
    """The layers of a UTIA BIG file.

    Directions come from its list of directions (chunk 16, four doubles per image, taken as
    theta_light, phi_light, theta_view, phi_view; radians or degrees, see
    :func:`tasks.container_formats.angles_in_degrees`) and must form a full view x light grid.
    A colour space chunk naming XYZ makes 3-plane images XYZ, converted to linear sRGB unless
    ``xyz`` is ``"keep"`` (``"none"``: planes as stored).

    Raises
    ------
    BTFError
        Naming the file: wrong magic, truncation, an unsupported data order or type, an image
        count that disagrees with the data, directions missing, twice or off the hemisphere.
    """
    path = Path(path)
    chunks, data = read_big_chunks(path)
    try:
        layout = big_layout(chunks, data)
    except FormatError as exc:
        raise BTFError(f"{path}: {exc}") from None
    entries = [Entry(i, check_angles(angles, f"{path}: image {i}"), f"{path}: image {i}",
                     f"image {i}") for i, angles in enumerate(layout.directions.tolist())]
    directions, grid = layer_grid(entries, str(path), ordered=False)
    is_xyz = layout.planes == 3 and "XYZ" in layout.colour_space.upper() and xyz != "none"
    keep = xyz == "keep"
    channels = ("X", "Y", "Z") if is_xyz and keep else plane_channels(layout.planes)
    reader = BigReader(str(path.resolve()), layout.data_offset, layout.image_bytes,
                       layout.dtype, (layout.height, layout.width, layout.planes), is_xyz, keep)
    colour = ((XYZ if keep else f"{LINEAR_SRGB} (converted from {XYZ})") if is_xyz
              else f"as stored ({layout.colour_space or 'no colour space given'})")
    attrs = {"format": "UTIA BIG", "data_type": layout.type_name, "colour": colour,
             "directions": f"{layout.direction_list}, in {layout.angle_unit} (order assumed: "
                           "theta_light, phi_light, theta_view, phi_view)"}
    if layout.illuminant:
        attrs["illuminant"] = layout.illuminant
    if is_xyz:
        note = xyz_note("CIE XYZ (the file's colour space)", keep)
    elif xyz == "none" and "XYZ" in colour.upper():
        note = f"BIG values {AS_NAMED} ({colour})"
    else:
        note = f"BIG values {colour.replace('as stored', 'stored as they are')}"
    info = ImageInfo(layout.height, layout.width, channels, layout.type_name)
    return LayerSource(directions, grid, info, reader, attrs, note)


# --- the entry ------------------------------------------------------------------------------

def guess_can_open(path: Path) -> bool:
    """Whether ``path`` is a BIG file: by its magic or its suffix."""
    if not path.is_file():
        return False
    with path.open("rb") as f:
        magic = f.read(len(BIG_MAGIC))
    return magic == BIG_MAGIC or path.suffix.lower() == ".big"


def _open(path: Path, options: ReadOptions) -> LayerSource:
    refuse_manifest(path, options)
    return big_source(path, xyz=options.xyz)


def describe(path: Path) -> dict[str, Any]:
    """What ``btf inspect`` says of a BIG file: from its chunk table."""
    source = _open(path, ReadOptions())
    return layers_report(
        source, kind=f"{source.attrs.get('data_type', '?')}, {len(source.info.channels)} "
                     "plane(s)",
        file_bytes=path.stat().st_size,
        directions_from=f"its list of directions: {source.attrs['directions']}")


FORMAT = SourceFormat(
    "big",
    "FILE.big, a UTIA BIG file, read image by image at its offset (directions from its list "
    "of directions); becomes a radiance store",
    "a BIG file (UTIA)",
    suffixes=(".big",), guess_can_open=guess_can_open,
    describe=describe, lines=layers_lines, open=_open)

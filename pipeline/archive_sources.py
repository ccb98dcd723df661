"""Layers from single-file measurements: Bonn's UBO2003/ATRIUM zip archives and UTIA's BIG files.

Nothing is unpacked or read whole: a zip is read member by member with :mod:`zipfile` (the
archive is opened once per process and shared by its threads), a BIG file image by image at
its offset. Parsing of names and headers is pure (:mod:`tasks.archive_names`,
:mod:`tasks.container_formats`); this module does the reading.
"""

from __future__ import annotations

import functools
import os
import struct
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.errors import BTFError
from pipeline.images import ImageInfo
from pipeline.layer_sources import LINEAR_SRGB, XYZ, Entry, LayerSource, check_angles, layer_grid
from tasks.archive_names import BONN_SUFFIXES, bonn_angles
from tasks.colour import decode_display, xyz_to_linear_srgb
from tasks.container_formats import (
    BIG_CHUNK_NAMES,
    BIG_DATA,
    BIG_MAGIC,
    FormatError,
    big_layout,
    parse_rgbe_header,
)

ZIP_MAGICS = (b"PK\x03\x04", b"PK\x05\x06")  # a local file header; an empty archive's end


def _channels(planes: int) -> tuple[str, ...]:
    return {1: ("Y",), 3: ("R", "G", "B")}.get(planes, tuple(f"c{k}" for k in range(planes)))


# --- Bonn's zip archives --------------------------------------------------------------------

@functools.lru_cache(maxsize=4)
def _open_zip(path: str, stamp: tuple[int, int, int]) -> zipfile.ZipFile:
    # Parsing the central directory of 6561 members takes longer than decoding one JPEG, so
    # the open archive is kept; ZipFile reads members from several threads safely (it seeks
    # and reads under a lock). ``stamp`` reopens it when the file changes.
    return zipfile.ZipFile(path)


def read_member(path: str, member: str) -> bytes:
    """The bytes of one zip member (CRC-checked), from the process's open archive."""
    try:
        stat = os.stat(path)
        archive = _open_zip(path, (stat.st_ino, stat.st_size, stat.st_mtime_ns))
        return archive.read(member)
    except (zipfile.BadZipFile, KeyError, OSError, EOFError, ValueError) as exc:
        raise BTFError(f"{path}:{member}: cannot read the member ({exc})") from None


@dataclass(frozen=True)
class ZipReader:
    """Reads a JPEG or RGBE member of a zip archive as linear float32 values.

    ``decode``: the transfer curve of JPEG values (:data:`tasks.colour.DECODINGS`);
    ``hdr_rows``: row order of ATRIUM's ``+X W -Y H`` RGBE files
    (:func:`tasks.container_formats.parse_rgbe_header`).
    """

    path: str
    decode: str
    hdr_rows: str = "bottom-up"

    def where(self, member: str) -> str:
        """The archive and member, for messages."""
        return f"{self.path}:{member}"

    def __call__(self, member: str) -> np.ndarray:
        """Linear float32 ``(height, width, channels)`` values of ``member``."""
        data = read_member(self.path, member)
        if member.lower().endswith(".hdr"):
            return self._rgbe(member, data)
        import imagecodecs

        try:
            pixels = imagecodecs.jpeg8_decode(data)
        except Exception as exc:
            raise BTFError(f"{self.where(member)}: corrupt JPEG ({exc})") from None
        return decode_display(pixels.reshape(*pixels.shape[:2], -1), self.decode)

    def _rgbe(self, member: str, data: bytes) -> np.ndarray:
        import imagecodecs

        try:
            header = parse_rgbe_header(data, atrium_rows=self.hdr_rows)
            out = np.empty((header.height, header.width, 3), np.float32)
            imagecodecs.rgbe_decode(data[header.offset:], header=False, out=out)
        except FormatError as exc:
            raise BTFError(f"{self.where(member)}: {exc}") from None
        except Exception as exc:
            raise BTFError(f"{self.where(member)}: corrupt RGBE pixels ({exc})") from None
        if header.flip_rows:
            out = out[::-1]
        if header.flip_columns:
            out = out[:, ::-1]
        return np.ascontiguousarray(out)


def _zip_entries(path: Path) -> list[Entry]:
    try:
        with zipfile.ZipFile(path) as archive:
            # macOS's zip keeps resource forks as __MACOSX/.../._NAME: not images
            members = [i.filename for i in archive.infolist() if not i.is_dir()
                       and not i.filename.startswith("__MACOSX/")
                       and not i.filename.rsplit("/", 1)[-1].startswith("._")]
    except (zipfile.BadZipFile, OSError) as exc:
        raise BTFError(f"{path}: not a readable zip archive ({exc})") from None
    images = [m for m in members if m.lower().endswith(BONN_SUFFIXES)]
    if not images:
        raise BTFError(f"{path}: no .jpg or .hdr images among its {len(members)} members")
    kinds = {m.lower().endswith(".hdr") for m in images}
    if len(kinds) > 1:
        raise BTFError(f"{path}: holds both .jpg and .hdr images; an archive must hold one kind "
                       "(UBO2003/ATRIUM JPEGs or ATRIUM HDR)")
    entries = []
    for member in images:
        where = f"{path}:{member}"
        angles = bonn_angles(member)
        if angles is None:
            raise BTFError(f"{where}: name does not end in 'tl{{ddd}} pl{{ddd}} tv{{ddd}} "
                           "pv{ddd}.jpg' (or .hdr), the naming of UBO2003/ATRIUM archives")
        entries.append(Entry(member, check_angles(angles, where), str(path), member))
    return entries


def zip_source(path: str | Path, *, decode: str = "srgb", hdr_rows: str = "bottom-up"
               ) -> LayerSource:
    """The layers of a UBO2003 or ATRIUM zip archive (JPEG or Radiance RGBE members).

    The directions come from the member names and must form a full view x light grid; the
    first image gives the size and channels every other image must have (checked as each is
    read). JPEG values are decoded with ``decode``; RGBE values are linear already.

    Raises
    ------
    BTFError
        Naming the archive or member: not a zip, no images, both JPEG and HDR members, a name
        that does not parse, a direction twice or missing, an unreadable first image.
    """
    path = Path(path)
    entries = _zip_entries(path)
    directions, grid = layer_grid(entries, str(path), ordered=False)
    reader = ZipReader(str(path.resolve()), decode, hdr_rows)
    pixels = reader(grid[0][0].key)
    info = ImageInfo(pixels.shape[0], pixels.shape[1], _channels(pixels.shape[2]))
    hdr = grid[0][0].key.lower().endswith(".hdr")
    attrs = {"format": "ATRIUM HDR zip" if hdr else "UBO2003/ATRIUM JPEG zip",
             "decoding": "linear (Radiance RGBE)" if hdr else decode,
             "colour": "as stored (the camera's RGB)"}
    if hdr:
        attrs["hdr_rows"] = hdr_rows
    return LayerSource(directions, grid, info, reader, attrs)


# --- UTIA's BIG files ------------------------------------------------------------------------

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
    channels = ("X", "Y", "Z") if is_xyz and keep else _channels(layout.planes)
    reader = BigReader(str(path.resolve()), layout.data_offset, layout.image_bytes,
                       layout.dtype, (layout.height, layout.width, layout.planes), is_xyz, keep)
    colour = ((XYZ if keep else f"{LINEAR_SRGB} (converted from {XYZ})") if is_xyz
              else f"as stored ({layout.colour_space or 'no colour space given'})")
    attrs = {"format": "UTIA BIG", "data_type": layout.type_name, "colour": colour,
             "directions": f"{layout.direction_list}, in {layout.angle_unit} (order assumed: "
                           "theta_light, phi_light, theta_view, phi_view)"}
    if layout.illuminant:
        attrs["illuminant"] = layout.illuminant
    return LayerSource(directions, grid, ImageInfo(layout.height, layout.width, channels),
                       reader, attrs)

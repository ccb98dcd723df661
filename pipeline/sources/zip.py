"""Bonn's UBO2003 and ATRIUM zip archives: JPEG or Radiance RGBE members, one per view and light.

Members are named ``... tl{ddd} pl{ddd} tv{ddd} pv{ddd}.jpg`` (or ``.hdr``): the directions
come from the names. Nothing is unpacked or read whole: the archive is read member by member
with :mod:`zipfile` (opened once per process and shared by its threads). Parsing of names and
RGBE headers is pure (:mod:`tasks.archive_names`, :mod:`tasks.container_formats`); this module
does the reading.
"""

from __future__ import annotations

import functools
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.errors import BTFError
from pipeline.images import ImageInfo
from pipeline.layer_sources import (
    Entry,
    LayerSource,
    ReadOptions,
    check_angles,
    display_note,
    layer_grid,
    plane_channels,
    refuse_manifest,
)
from pipeline.source_report import layers_lines, layers_report
from pipeline.sources import SourceFormat
from tasks.archive_names import BONN_SUFFIXES, bonn_angles
from tasks.colour import decode_display
from tasks.container_formats import FormatError, parse_rgbe_header

ZIP_MAGICS = (b"PK\x03\x04", b"PK\x05\x06")  # a local file header; an empty archive's end


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
    hdr = grid[0][0].key.lower().endswith(".hdr")
    info = ImageInfo(pixels.shape[0], pixels.shape[1], plane_channels(pixels.shape[2]),
                     "rgbe" if hdr else "uint8")
    attrs = {"format": "ATRIUM HDR zip" if hdr else "UBO2003/ATRIUM JPEG zip",
             "decoding": "linear (Radiance RGBE)" if hdr else decode,
             "colour": "as stored (the camera's RGB)"}
    if hdr:
        attrs["hdr_rows"] = hdr_rows
    note = ("Radiance RGBE values stored as they are (linear, the camera's RGB)" if hdr
            else display_note("JPEG", reader.decode))
    return LayerSource(directions, grid, info, reader, attrs, note)


# --- the entry ------------------------------------------------------------------------------

def guess_can_open(path: Path) -> bool:
    """Whether ``path`` is a zip archive: by its first bytes or its suffix."""
    if not path.is_file():
        return False
    with path.open("rb") as f:
        magic = f.read(4)
    return magic.startswith(ZIP_MAGICS) or path.suffix.lower() == ".zip"


def _open(path: Path, options: ReadOptions) -> LayerSource:
    refuse_manifest(path, options)
    return zip_source(path, decode="srgb" if options.decode == "auto" else options.decode,
                      hdr_rows=options.hdr_rows)


def describe(path: Path) -> dict[str, Any]:
    """What ``btf inspect`` says of an archive: from its central directory and first image."""
    source = _open(path, ReadOptions())
    hdr = str(source.first.key).lower().endswith(".hdr")
    return layers_report(source, kind="RGBE (.hdr)" if hdr else "JPEG",
                         file_bytes=path.stat().st_size, directions_from="the member names")


FORMAT = SourceFormat(
    "zip",
    "FILE.zip, a Bonn UBO2003/ATRIUM archive of JPEG or Radiance RGBE images, read from the "
    "zip; becomes a radiance store",
    "a zip archive (UBO2003/ATRIUM)",
    suffixes=(".zip",), guess_can_open=guess_can_open,
    describe=describe, lines=layers_lines, open=_open)

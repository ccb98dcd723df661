"""A folder of EXR or PNG layers, one image per view and light (UTIA's database folders too).

The directions come from a manifest CSV (``file,theta_light,phi_light,theta_view,phi_view``;
``SRC/manifest.csv`` is used when present) or from UTIA file names
``tl{theta}_pl{phi}_tv{theta}_pv{phi}.{exr,png}``, in the folder or, if it holds no images, in
its subfolders (UTIA's folder per view). UTIA database folders (three-digit names) hold sRGB
PNGs and XYZ EXRs. Every image's header is read when the folder is opened; the pixels when
ingest reads the image.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.errors import BTFError
from pipeline.images import IMAGE_SUFFIXES, ImageInfo, image_info, read_image
from pipeline.layer_files import MANIFEST, MANIFEST_COLUMNS, UTIA_NAME
from pipeline.layer_sources import (
    AS_NAMED,
    LINEAR_SRGB,
    XYZ,
    Entry,
    LayerSource,
    ReadOptions,
    check_angles,
    display_note,
    layer_grid,
    xyz_note,
)
from pipeline.source_report import layers_lines, layers_report
from pipeline.sources import SourceFormat
from tasks.archive_names import utia_angles
from tasks.colour import decode_values, xyz_to_linear_srgb


def _from_manifest(src: Path, manifest: Path) -> list[Entry]:
    if not manifest.is_file():
        raise BTFError(f"{manifest}: manifest not found")
    with manifest.open(newline="") as f:
        reader = csv.DictReader(f)
        missing = set(MANIFEST_COLUMNS) - set(reader.fieldnames or ())
        if missing:
            raise BTFError(f"{manifest}: missing column(s) {', '.join(sorted(missing))}; "
                           f"expected {','.join(MANIFEST_COLUMNS)}")
        entries = []
        for row in reader:
            where = f"{manifest}:{reader.line_num}"
            path = Path(row["file"]) if Path(row["file"]).is_absolute() else src / row["file"]
            if not path.is_file():
                raise BTFError(f"{where}: file {row['file']!r} not found in {src}")
            angles = check_angles([row[c] for c in MANIFEST_COLUMNS[1:]], where)
            entries.append(Entry(path, angles, where, path.name))
    return entries


def _image_files(src: Path) -> list[Path]:
    """Images in ``src``, or if it holds none, in its subfolders (UTIA: a folder per view)."""
    def images(folder: Path) -> list[Path]:
        return sorted(p for p in folder.iterdir()
                      if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())

    found = images(src)
    if not found:
        found = [p for d in sorted(src.iterdir()) if d.is_dir() for p in images(d)]
    return found


def _from_names(files: list[Path]) -> list[Entry]:
    entries = []
    for path in files:
        match = UTIA_NAME.fullmatch(path.name)
        if match is None:
            raise BTFError(f"{path}: name does not follow tl{{theta}}_pl{{phi}}_tv{{theta}}_"
                           "pv{phi}.exr|png; name the files so or give a --manifest")
        entries.append(Entry(path, check_angles(match.groups()[:4], str(path)), str(path),
                             path.name))
    return entries


def check_headers(grid: list[list[Entry]]) -> ImageInfo:
    """Read every header; all images must have the first one's size and channels."""
    first = None
    for entry in (e for row in grid for e in row):
        info = image_info(entry.key)
        if first is None:
            first, first_path = info, entry.key
        elif info.same_size(first):
            first = first.widest(info)
        else:
            raise BTFError(f"{entry.key}: {info.height}x{info.width} with channels "
                           f"{','.join(info.channels)}, but {first_path.name} is "
                           f"{first.height}x{first.width} with {','.join(first.channels)}")
    return first


def exr_channel_names(path: str | Path) -> tuple[str, ...]:
    """All channel names of an EXR file, from its header."""
    import OpenEXR

    try:
        with OpenEXR.File(str(path), header_only=True) as f:
            return tuple(str(c.name) for c in f.header()["channels"])
    except Exception as exc:  # the bindings raise RuntimeError with a short text
        raise BTFError(f"{path}: corrupt or unreadable EXR file ({exc})") from None


def _xyz_planes(path: Path, *, utia: bool) -> tuple[str, str, str] | None:
    """The channels holding X, Y, Z in the EXR at ``path``, or None if it is not XYZ.

    Channels named X, Y, Z are XYZ anywhere; UTIA's database documents its EXRs as XYZ, so
    in a UTIA folder R, G, B channels are taken as holding X, Y, Z.
    """
    names = set(exr_channel_names(path))
    if {"X", "Y", "Z"} <= names:
        return ("X", "Y", "Z")
    if utia and {"R", "G", "B"} <= names:
        return ("R", "G", "B")
    return None


@dataclass(frozen=True)
class FolderReader:
    """Reads an image file of a folder: PNG decoded by ``decode``, EXR as is or from XYZ.

    ``xyz``: the EXR channels holding X, Y, Z (``None``: EXRs are read as named); ``keep``:
    XYZ stays XYZ rather than becoming linear sRGB.
    """

    decode: str
    xyz: tuple[str, str, str] | None = None
    keep: bool = False

    def where(self, key) -> str:
        """The file, for messages."""
        return str(key)

    def __call__(self, key) -> np.ndarray:
        """Linear float32 ``(height, width, channels)`` values of the file ``key``."""
        path = Path(key)
        if path.suffix.lower() == ".exr" and self.xyz is not None:
            return self._xyz(path)
        pixels, _ = read_image(path, srgb=self.decode == "srgb")
        if path.suffix.lower() == ".png" and self.decode == "gamma2.2":
            pixels = decode_values(pixels, "gamma2.2")
        return pixels

    def _xyz(self, path: Path) -> np.ndarray:
        import OpenEXR

        try:
            with OpenEXR.File(str(path), separate_channels=True) as f:
                channels = f.channels()
                planes = [np.asarray(channels[name].pixels) for name in self.xyz]
        except KeyError as exc:
            raise BTFError(f"{path}: no EXR channel {exc} (XYZ expected in channels "
                           f"{','.join(self.xyz)})") from None
        except Exception as exc:
            raise BTFError(f"{path}: corrupt or unreadable EXR file ({exc})") from None
        if any(p.dtype.kind != "f" for p in planes):
            raise BTFError(f"{path}: EXR channels must be half or float, not integer")
        xyz = np.stack(planes, axis=-1).astype(np.float32)
        return xyz if self.keep else xyz_to_linear_srgb(xyz)


def folder_source(src: str | Path, manifest: str | Path | None = None, *, decode: str = "auto",
                  xyz: str = "srgb") -> LayerSource:
    """The layers of a folder of EXR/PNG images.

    Directions come from a manifest (``SRC/manifest.csv`` if present) or from the names.
    Without images in ``src`` itself, its subfolders are searched (a folder per view). A
    folder whose images all have UTIA's database names (``tl000_pl000_tv000_pv000``, three
    digits) is a UTIA folder: ``decode="auto"`` decodes its PNGs from sRGB, and its EXRs are
    XYZ. Elsewhere ``auto`` reads PNG values linearly (``v / max``) and only EXRs with X, Y, Z
    channels are XYZ. XYZ becomes linear sRGB unless ``xyz`` is ``"keep"`` (or ``"none"``:
    read EXR channels as named).

    Raises
    ------
    BTFError
        Naming the file: no images, a manifest row naming a missing file, an unparsable name,
        two images with the same directions, a missing view x light combination, or images
        of different sizes or channels.
    """
    src = Path(src)
    if not src.is_dir():
        raise BTFError(f"{src}: not a folder")
    if manifest is None and (src / MANIFEST).is_file():
        manifest = src / MANIFEST
    utia = False
    if manifest:
        entries = _from_manifest(src, Path(manifest))
    else:
        files = _image_files(src)
        utia = bool(files) and all(utia_angles(p.name) is not None for p in files)
        entries = _from_names(files)
    if not entries:
        raise BTFError(f"{src}: no .exr or .png images found")
    directions, grid = layer_grid(entries, str(src), ordered=manifest is not None)
    info = check_headers(grid)
    if decode == "auto":
        decode = "srgb" if utia else "none"
    first = grid[0][0].key
    planes = (_xyz_planes(first, utia=utia)
              if xyz != "none" and Path(first).suffix.lower() == ".exr" else None)
    keep = xyz == "keep"
    if planes is not None:
        info = ImageInfo(info.height, info.width, ("X", "Y", "Z") if keep else ("R", "G", "B"),
                         info.sample)
    attrs = {"format": "UTIA image folder" if utia else "image folder",
             "decoding": decode,
             "colour": (XYZ if keep else f"{LINEAR_SRGB} (converted from {XYZ})")
             if planes is not None else "as stored"}
    reader = FolderReader(decode, planes, keep)
    suffixes = {Path(e.key).suffix.lower() for row in grid for e in row}
    note = "; ".join(([display_note("PNG", decode)] if ".png" in suffixes else []) + (
        [_exr_note(reader, utia, info.channels, xyz)] if ".exr" in suffixes else []))
    return LayerSource(directions, grid, info, reader, attrs, note)


def _exr_note(reader: FolderReader, utia: bool, channels: tuple[str, ...], xyz: str) -> str:
    """The colour line of a folder's EXRs, from what ``reader`` does to them."""
    if reader.xyz == ("X", "Y", "Z"):
        return xyz_note("CIE XYZ (D65)", reader.keep)
    if reader.xyz is not None:
        return xyz_note(f"EXR channels {','.join(reader.xyz)} read as CIE XYZ (D65), as UTIA's "
                        "database stores them,", reader.keep)
    if xyz == "none" and (utia or set(channels) == {"X", "Y", "Z"}):
        return f"EXR values {AS_NAMED}"
    return "EXR values stored as they are (linear)"


# --- the entry ------------------------------------------------------------------------------

def _open(path: Path, options: ReadOptions) -> LayerSource:
    return folder_source(path, options.manifest, decode=options.decode, xyz=options.xyz)


def describe(path: Path) -> dict[str, Any]:
    """What ``btf inspect`` says of a folder: from its listing and image headers."""
    source = _open(path, ReadOptions())
    keys = [e.key for row in source.grid for e in row]
    origin = (MANIFEST if (path / MANIFEST).is_file()
              else "the file names" + (", a folder per view"
                                       if Path(keys[0]).parent != path else ""))
    return layers_report(source,
                         kind="/".join(sorted({Path(k).suffix.lstrip(".").upper()
                                               for k in keys})),
                         file_bytes=sum(Path(k).stat().st_size for k in keys),
                         directions_from=origin)


FORMAT = SourceFormat(
    "folder",
    "FOLDER of EXR or PNG layers, directions from a manifest CSV (--manifest, or "
    "FOLDER/manifest.csv) or UTIA names tl{theta}_pl{phi}_tv{theta}_pv{phi}.exr|png, also a "
    "folder per view (UTIA's database folders: sRGB PNGs, XYZ EXRs); becomes a radiance store",
    "a folder of images",
    guess_can_open=Path.is_dir, describe=describe, lines=layers_lines, open=_open)

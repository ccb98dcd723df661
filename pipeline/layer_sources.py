"""Where ``btf ingest`` finds a measurement's layers: their directions and how to read each one.

A :class:`LayerSource` is what every input format becomes: the view and light directions, a
``[view][light]`` grid of :class:`Entry` (one image each), the size and channels of the layers,
and a reader that turns one entry's key into float32 ``(height, width, channels)`` linear
values. Readers are small frozen dataclasses, so tasks on any scheduler can carry them.

This module holds the common part and the folders of images (EXR/PNG with a manifest or
UTIA-style names, and UTIA's database folders); :mod:`pipeline.archive_sources` holds Bonn's
zip archives and UTIA's BIG files.
"""

from __future__ import annotations

import csv
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.errors import BTFError
from pipeline.images import IMAGE_SUFFIXES, ImageInfo, image_info, read_image
from pipeline.layer_files import MANIFEST, MANIFEST_COLUMNS, UTIA_NAME
from pipeline.stores.base import Directions
from tasks.archive_names import utia_angles
from tasks.colour import decode_values, xyz_to_linear_srgb
from tasks.sampling import canonical_direction

XYZ_MODES = ("srgb", "keep", "none")
LINEAR_SRGB = "linear sRGB primaries, D65 white"
XYZ = "CIE XYZ, D65 white"


@dataclass(frozen=True)
class Entry:
    """One image: the key its reader reads, its directions, and names for messages.

    ``angles`` are ``(theta_light, phi_light, theta_view, phi_view)`` in degrees.
    """

    key: Any  # a path, a zip member, an image index
    angles: tuple[float, float, float, float]
    origin: str  # where the directions came from
    name: str  # the image's own name


@dataclass(frozen=True, eq=False)
class LayerSource:
    """A measurement's layers: directions, images on a ``[view][light]`` grid, a reader.

    ``reader(key)`` returns float32 ``(height, width, channels)`` linear values of ``info``'s
    size and channels; ``reader.where(key)`` names the image in messages. ``attrs`` says how
    the values were decoded and converted, for the store's attrs.
    """

    directions: Directions
    grid: list[list[Entry]]
    info: ImageInfo
    reader: Callable[[Any], np.ndarray]
    attrs: dict[str, Any] = field(default_factory=dict)

    @property
    def first(self) -> Entry:
        """The image whose size and channels every other image must have."""
        return self.grid[0][0]


def check_angle(value: float | str, where: str, column: str) -> float:
    """An angle in degrees, refused (naming ``where`` and ``column``) if not on the hemisphere."""
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise BTFError(f"{where}: {column} {value!r} is not a number") from None
    if not np.isfinite(value):
        raise BTFError(f"{where}: {column} {value!r} is not finite")
    if column.startswith("theta") and not 0 <= value <= 90:
        raise BTFError(f"{where}: {column} {value:g} is outside 0-90 degrees (the hemisphere)")
    return value


def check_angles(angles, where: str) -> tuple[float, float, float, float]:
    """:func:`check_angle` on ``(theta_light, phi_light, theta_view, phi_view)``."""
    return tuple(check_angle(a, where, c)
                 for a, c in zip(angles, MANIFEST_COLUMNS[1:], strict=True))


def _axis(values: list[tuple[float, float]], *, ordered: bool) -> list[tuple[float, float]]:
    unique = list(dict.fromkeys(values))
    return unique if ordered else sorted(unique)


def layer_grid(entries: list[Entry], where: str, *, ordered: bool
               ) -> tuple[Directions, list[list[Entry]]]:
    """Directions of ``entries`` and the entries as a ``[view][light]`` grid.

    Views and lights keep the entries' order with ``ordered`` (a manifest), else are sorted
    by (theta, phi).

    Raises
    ------
    BTFError
        Two images with the same directions (naming both), or a view x light combination
        without an image (naming ``where``, the directions and how many are present).
    """
    seen: dict[tuple[float, ...], Entry] = {}
    for e in entries:
        key = (*canonical_direction(*e.angles[:2]), *canonical_direction(*e.angles[2:]))
        if key in seen:
            raise BTFError(f"{e.origin}: {e.name} has the same directions as "
                           f"{seen[key].name} (light {key[0]:g}/{key[1]:g}, "
                           f"view {key[2]:g}/{key[3]:g} degrees)")
        seen[key] = e
    lights = _axis([k[:2] for k in seen], ordered=ordered)
    views = _axis([k[2:] for k in seen], ordered=ordered)
    grid = []
    for v in views:
        row = []
        for light in lights:
            entry = seen.get((*light, *v))
            if entry is None:
                raise BTFError(f"{where}: no image for light {light[0]:g}/{light[1]:g} and view "
                               f"{v[0]:g}/{v[1]:g} degrees (theta/phi); a BTF needs every view "
                               f"x light combination ({len(seen)} of "
                               f"{len(views) * len(lights)} present)")
            row.append(entry)
        grid.append(row)
    directions = Directions(*(np.array(a, np.float64) for a in
                              ([v[0] for v in views], [v[1] for v in views],
                               [light[0] for light in lights], [light[1] for light in lights])))
    return directions, grid


# --- folders of images ----------------------------------------------------------------------

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
        elif info != first:
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
        info = ImageInfo(info.height, info.width, ("X", "Y", "Z") if keep else ("R", "G", "B"))
    attrs = {"format": "UTIA image folder" if utia else "image folder",
             "decoding": decode,
             "colour": (XYZ if keep else f"{LINEAR_SRGB} (converted from {XYZ})")
             if planes is not None else "as stored"}
    return LayerSource(directions, grid, info, FolderReader(decode, planes, keep), attrs)

"""What every image format of ``btf ingest`` becomes: directions, a grid of images, a reader.

A :class:`LayerSource` is what an image format's entry (:mod:`pipeline.sources`) opens a path
as: the view and light directions, a ``[view][light]`` grid of :class:`Entry` (one image
each), the size and channels of the layers, a reader that turns one entry's key into float32
``(height, width, channels)`` linear values, and one line saying how the values were read.
Readers are small frozen dataclasses, so tasks on any scheduler can carry them.

This module holds what the formats share: the options they are opened with
(:class:`ReadOptions`), the checks of angles, the view x light grid, and the words of the
colour line (:func:`display_note`, :func:`xyz_note`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.errors import BTFError
from pipeline.images import ImageInfo
from pipeline.layer_files import MANIFEST_COLUMNS
from pipeline.stores.base import Directions
from tasks.sampling import canonical_direction

XYZ_MODES = ("srgb", "keep", "none")
LINEAR_SRGB = "linear sRGB primaries, D65 white"
XYZ = "CIE XYZ, D65 white"


@dataclass(frozen=True)
class ReadOptions:
    """The options of ``btf ingest`` that say how a source's values are read, with its defaults.

    ``manifest``: a folder's directions (a CSV); ``decode``: the transfer curve of 8/16-bit
    values (``"auto"``: the format's own); ``xyz``: what becomes of CIE XYZ images
    (:data:`XYZ_MODES`); ``hdr_rows``: the row order of ATRIUM's ``.hdr`` images. A format
    uses the ones that apply to it.
    """

    manifest: str | Path | None = None
    decode: str = "auto"
    xyz: str = "srgb"
    hdr_rows: str = "bottom-up"


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
    the values were decoded and converted, for the store's attrs; ``colour_note`` says it in
    one line with the option that changes it (``btf ingest`` prints it, ``btf inspect`` shows
    it), written by the format from the reader it made: what was done, not what was asked.
    """

    directions: Directions
    grid: list[list[Entry]]
    info: ImageInfo
    reader: Callable[[Any], np.ndarray]
    attrs: dict[str, Any] = field(default_factory=dict)
    colour_note: str = ""

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


def refuse_manifest(path: Path, options: ReadOptions) -> None:
    """Refuse ``--manifest`` for a single-file format, whose directions are its own."""
    if options.manifest is not None:
        raise BTFError(f"{path}: --manifest is for folders of images; an archive's directions "
                       "come from its member names or its list of directions")


def plane_channels(planes: int) -> tuple[str, ...]:
    """Channel names of images with ``planes`` planes: Y, R,G,B, else c0, c1, ..."""
    return {1: ("Y",), 3: ("R", "G", "B")}.get(planes, tuple(f"c{k}" for k in range(planes)))


# --- the colour line ------------------------------------------------------------------------

_DECODED = {"srgb": "decoded from sRGB to linear",
            "gamma2.2": "decoded as (v/max)^2.2 to linear (the Mitsuba BTF plugin's curve)",
            "none": "taken as linear, v/max, not decoded"}
AS_NAMED = "stored as they are (linear), channels as named (--xyz none: no XYZ conversion; " \
           "--xyz srgb converts XYZ to linear sRGB primaries)"


def display_note(kind: str, decoding: str) -> str:
    """The colour line of display-encoded ``kind`` values (JPEG, PNG) decoded by ``decoding``."""
    others = " or ".join(d for d in ("srgb", "gamma2.2", "none") if d != decoding)
    return f"{kind} values {_DECODED[decoding]} (--decode {decoding}; --decode {others} to change)"


def xyz_note(origin: str, keep: bool) -> str:
    """The colour line of CIE XYZ values from ``origin``, kept or converted to linear sRGB."""
    if keep:
        return (f"{origin} stored as X,Y,Z (--xyz keep; --xyz srgb converts them to linear sRGB "
                "primaries, --xyz none reads the channels as named)")
    return (f"{origin} converted to linear sRGB primaries (--xyz keep stores X,Y,Z; --xyz none "
            "reads the channels as named)")

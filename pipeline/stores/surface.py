"""Surface stores (``btf_kind: surface``): one layer of a surface rendered from a tile set.

``radiance`` ``(y, x, channel)`` float32 and the ``channel`` labels; the direction coordinates
hold the one view and one light the layer shows; attrs name the tile set, layer, origin, seed
and provenance (``btf render OUT.zarr``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pipeline.stores.base import (
    RADIANCE,
    Directions,
    Store,
    add_array,
    check_variables,
    create_store,
)

NAME = "surface"


def create_surface_store(path, shape: tuple[int, int, int], channels: tuple[str, ...], *,
                         directions: Directions, chunk: int, attrs: dict[str, Any]):
    """Create an empty surface store and return its ``radiance`` array."""
    group = create_store(path, kind=NAME, attrs=attrs, directions=directions, channels=channels)
    h, w, nc = shape
    return add_array(group, RADIANCE, shape=shape, dims=("y", "x", "channel"),
                     chunks=(min(chunk, h), min(chunk, w), nc))


def check_surface(group, path: str | Path) -> None:
    """Raise :class:`pipeline.errors.BTFError` unless ``group`` holds a surface's radiance."""
    check_variables(group, path, {RADIANCE: ("y", "x", "channel")})


def _summary(group) -> dict[str, Any]:
    attrs = group.attrs
    return {"surface": {key: attrs.get(key) for key in ("tileset", "light", "view", "origin",
                                                          "seed")}
            | {"shape": list(group[RADIANCE].shape)}}


def _lines(summary: dict[str, Any]) -> list[str]:
    f = summary["surface"]
    return [f"surface: {f['shape'][0]} x {f['shape'][1]} texels of light {f['light']}, view "
            f"{f['view']} at {tuple(f['origin'])}, seed {f['seed']}, from {f['tileset']}"]


class SurfaceStore(Store):
    """One layer of a surface rendered from a tile set (``btf render`` to zarr)."""

    names = (NAME,)
    what = "surface store"
    check = staticmethod(check_surface)
    summary = staticmethod(_summary)
    lines = staticmethod(_lines)


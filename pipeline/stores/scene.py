"""Scene stores (``btf_kind: scene``): the layers a scene asked for, in its directions.

``radiance`` float32 ``(direction, y, x, channel)``: one image per requested direction pair,
interpolated from the measured layers (:mod:`tasks.directions`), in chunks of
:func:`directions_per_chunk` directions: at least 16, more when the region is small, up to about
:data:`CHUNK_VALUES` values, so a small region of many directions is one file, not one per
direction (measured: 0.32 -> 0.11 s for 144 directions of 26^2 texels at 16 a chunk); the
coordinates ``theta_light``, ``phi_light``, ``theta_view``, ``phi_view`` (degrees) on
``direction`` and the ``channel`` labels; attrs with the scene spec, the source, the level and
the interpolation terms of every direction (``terms``: measured view, light and weight). A
scene asking for ``all`` directions is written as a radiance store instead (every measured
layer, on the view and light grid), which every stage takes.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from pipeline import checksums
from pipeline.errors import BTFError
from pipeline.scene_spec import DIRECTION_FIELDS
from pipeline.stores.base import RADIANCE, Store, add_array, check_variables, create_store

NAME = "scene"
DIMS = ("direction", "y", "x", "channel")
DIRECTIONS_PER_CHUNK = 16  # the fewest directions in a chunk (when there are as many)
CHUNK_VALUES = 2**22  # values (16 MiB of float32) in a chunk, when the region is small


def directions_per_chunk(n: int, block: tuple[int, int], channels: int) -> int:
    """Directions a chunk (or a block task) of ``block`` texels holds, out of ``n``.

    At least :data:`DIRECTIONS_PER_CHUNK`, and as many more as keep it within
    :data:`CHUNK_VALUES` values, so a small region costs a few chunks and tasks whatever the
    number of directions (``btf bench scene``: the fixed cost of a request).
    """
    per_direction = max(1, block[0] * block[1] * channels)
    return max(1, min(n, max(DIRECTIONS_PER_CHUNK, CHUNK_VALUES // per_direction)))


def create_scene_store(path, *, directions: np.ndarray, shape: tuple[int, int],
                       channels: tuple[str, ...], chunk: int, attrs: dict[str, Any]):
    """Create an empty scene store; returns its ``radiance`` array."""
    group = create_store(path, kind=NAME, attrs=attrs, directions=None, channels=channels)
    for k, name in enumerate(DIRECTION_FIELDS):
        coord = group.create_array(name, shape=(len(directions),), dtype="float64",
                                   dimension_names=("direction",),
                                   compressors=checksums.codec(),
                                   attributes={"units": "degree"})
        coord[:] = directions[:, k]
    block = min(chunk, shape[0]), min(chunk, shape[1])
    n = directions_per_chunk(len(directions), block, len(channels))
    return add_array(group, RADIANCE, shape=(len(directions), *shape, len(channels)),
                     dims=DIMS, chunks=(n, *block, len(channels)),
                     attrs={"coordinates": " ".join(DIRECTION_FIELDS),
                            "long_name": "radiance in the requested directions"})


def check_scene(group, path: str | Path) -> None:
    """Raise :class:`BTFError` unless ``group`` holds a scene's radiance and directions."""
    check_variables(group, path, {RADIANCE: DIMS})
    n = group[RADIANCE].shape[0]
    for name in DIRECTION_FIELDS:
        if name not in group.array_keys() or group[name].shape != (n,):
            raise BTFError(f"{path}: coordinate {name!r} is missing or not of length {n}")


def _summary(group) -> dict[str, Any]:
    attrs = group.attrs
    return {"scene": {"directions": group[RADIANCE].shape[0],
                      "shape": list(group[RADIANCE].shape[1:3]), "level": attrs.get("level"),
                      "source": attrs.get("source_store"),
                      "interpolation": (attrs.get("scene") or {}).get("interpolation")}}


def _lines(summary: dict[str, Any]) -> list[str]:
    s = summary["scene"]
    return [f"scene: {s['directions']} direction(s) of {s['shape'][0]} x {s['shape'][1]} "
            f"texels at level {s['level']}, {s['interpolation']} interpolation, from "
            f"{s['source']}"]


class SceneStore(Store):
    """What ``btf scene`` computed: radiance in the requested directions."""

    names = (NAME,)
    what = "scene store"
    check = staticmethod(check_scene)
    summary = staticmethod(_summary)
    lines = staticmethod(_lines)


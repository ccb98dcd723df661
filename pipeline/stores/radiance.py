"""Radiance stores (``btf_kind`` ``btf`` or ``abtf``): the layers themselves.

- ``radiance``: float32, dims ``(view, light, y, x, channel)``, chunked in spatial tiles times a
  block of light directions (optionally grouped into shards of several tiles);
- the direction coordinates and ``channel`` labels (:mod:`pipeline.stores.base`);
- attrs ``btf_kind`` (``"btf"``, or ``"abtf"`` for one top view), ``source`` and
  ``provenance``;
- generated stores also hold their ground truth: ``height``, ``albedo``, ``roughness`` and
  ``specular`` on ``(y, x[, channel])``.

Sharding is off by default: with zarr 3.1.6 it halved write and read throughput (measured on a
generated 576 MiB ABTF: 257 vs 549 MB/s writing, 405 vs 718 MB/s reading), and its only gain is
fewer files. ``--shard`` turns it on for file systems that need that. Writing sharded arrays
from many workers is only safe shard by shard (:func:`pipeline.graphs.blocks.store_aligned`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline import storage
from pipeline.errors import BTFError
from pipeline.stores.base import (
    DIRECTION_COORDS,
    RADIANCE,
    RADIANCE_DIMS,
    Directions,
    Store,
    add_array,
    check_coordinates,
    create_store,
    location,
    open_group,
    sampling_lines,
    sampling_summary,
)
from tasks.errors import InvalidParameter

NAMES = ("btf", "abtf")
TRUTH_DIMS = {"height": ("y", "x"), "albedo": ("y", "x", "channel"),
              "roughness": ("y", "x"), "specular": ("y", "x")}


@dataclass(frozen=True)
class Layout:
    """Chunking of a radiance store.

    Attributes
    ----------
    chunk
        Texels per side of a spatial chunk (the unit of compression and of partial reads).
    dir_chunk
        Light directions per chunk.
    shard
        Texels per side of a shard (a file holding several chunks; a multiple of ``chunk``),
        or 0 to store every chunk in its own file.
    """

    chunk: int = 128
    dir_chunk: int = 16
    shard: int = 0

    def __post_init__(self):
        if self.chunk < 8:
            raise InvalidParameter("chunk", f"must be at least 8 texels, got {self.chunk}")
        if self.dir_chunk < 1:
            raise InvalidParameter("dir_chunk", f"must be at least 1, got {self.dir_chunk}")
        if self.shard < 0 or (self.shard and self.shard % self.chunk):
            raise InvalidParameter("shard", f"must be 0 or a multiple of --chunk ({self.chunk}), "
                                      f"got {self.shard}")

    def spatial(self, n: int) -> tuple[int, int | None]:
        """Chunk and shard sizes along a spatial axis of length ``n``."""
        chunk = min(self.chunk, n)
        if not self.shard:
            return chunk, None
        shard = min(self.shard, math.ceil(n / chunk) * chunk) // chunk * chunk
        return chunk, (shard if shard > chunk else None)

    def grid(self, shape: tuple[int, ...], dims: tuple[str, ...]) -> tuple[tuple, tuple | None]:
        """Chunk and shard shapes of an array with the given dims (None: no sharding)."""
        chunks, shards, sharded = [], [], False
        for n, dim in zip(shape, dims, strict=True):
            if dim in ("y", "x"):
                c, s = self.spatial(n)
                sharded |= s is not None
                chunks.append(c)
                shards.append(s or c)
            elif dim == "light":
                chunks.append(min(self.dir_chunk, n))
                shards.append(chunks[-1])
            elif dim == "view":
                chunks.append(1)
                shards.append(1)
            else:
                chunks.append(n)
                shards.append(n)
        return tuple(chunks), (tuple(shards) if sharded else None)


def create_radiance_store(path: str | Path, *, directions: Directions, ny: int, nx: int,
                          channels: tuple[str, ...], layout: Layout, attrs: dict[str, Any],
                          truth: bool = False):
    """Create an empty radiance store (metadata, coordinates, empty arrays) and return its group.

    ``radiance`` is filled with NaN until written. With ``truth``, the ground-truth field
    arrays of a generated store are created too. ``btf_kind`` follows the directions.
    """
    group = create_store(path, kind=directions.kind, attrs=attrs, directions=directions,
                         channels=channels)
    shape = (directions.views, directions.lights, ny, nx, len(channels))
    chunks, shards = layout.grid(shape, RADIANCE_DIMS)
    add_array(group, RADIANCE, shape=shape, dims=RADIANCE_DIMS, chunks=chunks, shards=shards,
              attrs={"coordinates": " ".join(DIRECTION_COORDS), "units": "relative radiance",
                     "long_name": "radiance per (view, light, texel, channel)"})
    if truth:
        for name, dims in TRUTH_DIMS.items():
            tshape = tuple({"y": ny, "x": nx, "channel": len(channels)}[d] for d in dims)
            tchunks, tshards = layout.grid(tshape, dims)
            add_array(group, name, shape=tshape, dims=dims, chunks=tchunks, shards=tshards)
    return group


# What to run first where a stage needs radiance layers and is given another kind of store.
FIRST = {
    "compressed": "rebuild the layers this stage needs first, e.g. btf reconstruct STORE "
                  "OUT.zarr --light I,.. --view J,.. (--region, --rank)",
    "tileset": "render the surface first (btf render TILES OUT.exr) or use the sample it was "
               "quilted from",
    "compressed-tileset": "render the surface first (btf render TILES OUT.exr) or use the "
                          "sample it was quilted from",
    "surface": "a rendered surface holds one layer: use the store it was rendered from",
}


def check_radiance(group, path: str | Path) -> None:
    """Raise :class:`BTFError` naming what is wrong if ``group`` is not a radiance store."""
    names = sorted(group.array_keys())
    if RADIANCE not in names:
        kind = group.attrs.get("btf_kind")
        if kind in FIRST:
            raise BTFError(f"{path}: a {kind} store, not radiance layers: {FIRST[kind]}")
        raise BTFError(f"{path}: no variable {RADIANCE!r} (found: {', '.join(names) or 'none'})")
    rad = group[RADIANCE]
    dims = tuple(rad.metadata.dimension_names or ())
    if dims != RADIANCE_DIMS:
        raise BTFError(f"{path}: variable {RADIANCE!r} has dims {dims}, expected {RADIANCE_DIMS}")
    if rad.dtype != np.float32:
        raise BTFError(f"{path}: variable {RADIANCE!r} is {rad.dtype}, expected float32")
    sizes = {"view": rad.shape[0], "light": rad.shape[1], "channel": rad.shape[4]}
    check_coordinates(group, path, sizes, f"variable {RADIANCE!r}")


def open_dataset(path: str | Path, group=None, chunks=None):
    """Open a store as a lazy xarray Dataset whose data variables are dask arrays.

    ``chunks(group, name)`` gives each data variable's dask chunks (a graph's task blocks,
    :func:`pipeline.graphs.blocks.read_chunks`: whole write units, so that no read straddles a
    shard and no shard is read by two tasks); without it, the stored chunks. Coordinates stay
    small lazy arrays.
    """
    import xarray as xr

    group = open_group(path) if group is None else group
    ds = xr.open_zarr(storage.store(location(path)), consolidated=False,
                      chunks=None if chunks else {})
    if chunks:
        for name in ds.data_vars:
            ds[name] = ds[name].chunk(chunks(group, name))
    return ds


def open_radiance(path: str | Path, chunks=None):
    """Open and validate a radiance store as a lazy xarray Dataset (see :func:`open_dataset`)."""
    group = open_group(path)
    check_radiance(group, path)
    return open_dataset(path, group, chunks)


def _summary(group) -> dict[str, Any]:
    return {"sampling": sampling_summary(group)} if RADIANCE in group.array_keys() else {}


def _lines(summary: dict[str, Any]) -> list[str]:
    return sampling_lines(summary["sampling"]) if "sampling" in summary else []


class RadianceStore(Store):
    """A radiance store: its layers ``radiance`` ``(view, light, y, x, channel)``."""

    names = NAMES
    what = "radiance store"
    check = staticmethod(check_radiance)
    summary = staticmethod(_summary)
    lines = staticmethod(_lines)

    @property
    def radiance(self):
        """The layers (a zarr array)."""
        return self.group[RADIANCE]

    @property
    def shape(self) -> tuple[int, ...]:
        """``(view, light, y, x, channel)``."""
        return tuple(self.radiance.shape)

    @property
    def layout(self) -> Layout:
        """The chunking it was written with."""
        a = self.radiance
        return Layout(chunk=a.chunks[2], dir_chunk=a.chunks[1],
                      shard=a.shards[2] if a.shards else 0)

    @property
    def truth(self) -> bool:
        """Whether it holds a generated material's ground-truth fields."""
        return all(self.has(name) for name in TRUTH_DIMS)

    def dataset(self, chunks=None):
        """The store as a lazy xarray Dataset (``chunks``: see :func:`open_dataset`)."""
        return open_dataset(self.path, self.group, chunks)


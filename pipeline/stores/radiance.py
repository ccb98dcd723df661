"""Radiance stores (``btf_kind`` ``btf`` or ``abtf``): the layers themselves.

- ``radiance``: float32 or float16 (the precision the data has: 8-bit and half-float
  measurements lose nothing in float16), dims ``(view, light, y, x, channel)``, chunked in
  spatial tiles times a block of light directions (optionally grouped into shards of several
  tiles). Every stage reads either and computes in float32 (:func:`open_dataset`,
  :func:`as_float32`);
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

from pipeline import chunk_io, storage
from pipeline.errors import BTFError
from pipeline.params import option
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


DTYPES = ("float32", "float16")
# The largest finite float16; a value above it cannot be stored in a float16 store.
FLOAT16_MAX = float(np.finfo(np.float16).max)


@dataclass(frozen=True)
class Layout:
    """Chunking and precision of a radiance store.

    Attributes
    ----------
    chunk
        Texels per side of a spatial chunk (the unit of compression and of partial reads).
    dir_chunk
        Light directions per chunk.
    shard
        Texels per side of a shard (a file holding several chunks; a multiple of ``chunk``),
        or 0 to store every chunk in its own file.
    dtype
        The stored values' type, ``float32`` or ``float16``.
    """

    chunk: int = 128
    dir_chunk: int = 16
    shard: int = 0
    dtype: str = "float32"

    def __post_init__(self):
        if self.chunk < 8:
            raise InvalidParameter("chunk", f"must be at least 8 texels, got {self.chunk}")
        if self.dir_chunk < 1:
            raise InvalidParameter("dir_chunk", f"must be at least 1, got {self.dir_chunk}")
        if self.shard < 0 or (self.shard and self.shard % self.chunk):
            raise InvalidParameter("shard", f"must be 0 or a multiple of --chunk ({self.chunk}), "
                                      f"got {self.shard}")
        if self.dtype not in DTYPES:
            raise InvalidParameter("dtype", f"must be one of {', '.join(DTYPES)}, got "
                                            f"{self.dtype!r}")

    @property
    def itemsize(self) -> int:
        """Bytes per stored value."""
        return np.dtype(self.dtype).itemsize

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


LAYOUT = "layout of the output store"


@dataclass(frozen=True, kw_only=True)
class LayoutOptions:
    """The options of a stage that writes a radiance store: its :class:`Layout`.

    Stage parameters inherit these four fields; each left unset (None) takes the input
    store's value where the stage reads a radiance store, else the stage's default
    (:meth:`layout`).
    """

    chunk: int | None = option(
        None, group=LAYOUT, help="texels per side of a stored chunk (default: the input "
                                 "store's, else 128)")
    dir_chunk: int | None = option(
        None, group=LAYOUT, help="light directions per stored chunk (default: the input "
                                 "store's, else 16)")
    shard: int | None = option(
        None, group=LAYOUT, help="texels per side of a shard file grouping several chunks (a "
                                 "multiple of --chunk); 0: one file per chunk (default: the "
                                 "input store's, else 0)")
    dtype: str | None = option(
        None, choices=DTYPES, group=LAYOUT,
        help="stored values' type: float16 halves the bytes and holds 8-bit and half-float "
             "data exactly (default: the input's precision, else float32)")

    def layout(self, like: Layout | None = None, dtype: str | None = None) -> Layout:
        """The layout asked for; unset options from ``like``, else :class:`Layout`'s defaults.

        ``dtype`` is the stage's own default type, before ``like``'s (ingest: the source's).
        Raises :class:`~tasks.errors.InvalidParameter` naming a bad option.
        """
        base = like or Layout()
        chunk = base.chunk if self.chunk is None else self.chunk
        if self.shard is not None:
            shard = self.shard
        else:  # the input's shards only around its own chunks
            shard = base.shard if chunk == base.chunk else 0
        return Layout(chunk=chunk, dir_chunk=base.dir_chunk if self.dir_chunk is None
                      else self.dir_chunk, shard=shard, dtype=self.dtype or dtype or base.dtype)


def stored(values: np.ndarray, dtype, where: str) -> np.ndarray:
    """``values`` in a store's type, refusing values a float16 store cannot hold.

    A finite value beyond float16's range would become infinite: :class:`BTFError` naming
    ``where`` and the value, rather than a store of infinities.
    """
    if values.dtype == dtype:
        return values
    with np.errstate(over="ignore"):  # found below, and named
        out = np.asarray(values, dtype)
    if out.dtype == np.float16 and not np.isfinite(out).all():
        lost = np.isfinite(values) & ~np.isfinite(out)
        if lost.any():
            raise BTFError(f"{where}: a value of {float(np.abs(values[lost]).max()):.6g} "
                           f"exceeds float16's range (up to {FLOAT16_MAX:g}); write it as "
                           "float32 (--dtype float32)")
    return out


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
              dtype=layout.dtype,
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
    if str(rad.dtype) not in DTYPES:
        raise BTFError(f"{path}: variable {RADIANCE!r} is {rad.dtype}, expected "
                       f"{' or '.join(DTYPES)}")
    sizes = {"view": rad.shape[0], "light": rad.shape[1], "channel": rad.shape[4]}
    check_coordinates(group, path, sizes, f"variable {RADIANCE!r}")


# Float16 values from which as_float32 widens with the compiled kernel: below, numpy's cast
# (2 ms at this size) costs less than loading numba into a process that would not otherwise
# (0.3 s and 90 MB: small scenes and pages read a few such blocks).
COMPILED_WIDENING = 1 << 20


def as_float32(values) -> np.ndarray:
    """Values read from a store, float16 widened to float32 (the type stages compute in).

    Anything else is returned as it is (no copy). The widening is the CPU's conversion
    instruction where it has one (:func:`tasks.dfmf_kernel.halves_to_float32`: 0.25 ns a
    value here, exact for NaN and infinities too), 9x numpy's cast, which does not use it.
    """
    values = np.asarray(values)
    if values.dtype != np.float16:
        return values
    if values.size < COMPILED_WIDENING:
        return values.astype(np.float32)
    from tasks.dfmf_kernel import HALF_INSTRUCTION, halves_to_float32

    if not HALF_INSTRUCTION:
        return values.astype(np.float32)
    out = np.empty(values.shape, np.float32)
    halves_to_float32(np.ascontiguousarray(values).view(np.uint16), out)
    return out


def lazy_float32(array):
    """A dask array of stored values, float16 widened to float32 as each block is read."""
    if array.dtype != np.float16:
        return array
    return array.map_blocks(as_float32, dtype=np.float32,
                            meta=np.empty((0,) * array.ndim, np.float32))


def open_dataset(path: str | Path, group=None, chunks=None):
    """Open a store as a lazy xarray Dataset whose data variables are dask arrays.

    Float16 variables (``radiance``, ``V``) are read as float32: stages compute in float32
    whatever the store holds. ``chunks(group, name)`` gives each data variable's dask chunks
    (a graph's task blocks, :func:`pipeline.graphs.blocks.read_chunks`: whole write units, so
    that no read straddles a shard and no shard is read by two tasks); without it, the stored
    chunks. Coordinates stay small lazy arrays.
    """
    import xarray as xr

    group = open_group(path) if group is None else group
    ds = xr.open_zarr(storage.store(location(path)), consolidated=False,
                      chunks=None if chunks else {})
    for name in ds.data_vars:
        wanted = chunks(group, name) if chunks else None
        array = group[name]
        if _undecoded(ds[name], array):  # read in the task's thread (pipeline.chunk_io)
            ds[name] = ds[name].copy(data=chunk_io.dask_array(
                array, location(path), ds[name].data.chunks if wanted is None else wanted,
                ds[name].dims))
        elif wanted:
            ds[name] = ds[name].chunk(wanted)
    for name in ds.data_vars:
        if ds[name].dtype == np.float16:
            encoding = ds[name].encoding  # the stored chunks and type, which copy drops
            ds[name] = ds[name].copy(data=lazy_float32(ds[name].data))
            ds[name].encoding = encoding
    return ds


def _nan_or_none(value) -> bool:
    return value is None or (isinstance(value, float | np.floating) and np.isnan(value))


def _undecoded(variable, array) -> bool:
    """Whether xarray gives zarr ``array``'s values as they are stored.

    Floats, no scale or offset, no fill value to mask but NaN: reading them past xarray
    (:mod:`pipeline.chunk_io`) changes nothing.
    """
    encoding = variable.encoding
    return (variable.dtype == array.dtype and variable.dtype.kind == "f"
            and not {"scale_factor", "add_offset"} & encoding.keys()
            and all(_nan_or_none(encoding.get(k)) for k in ("_FillValue", "missing_value")))


def plain(array) -> bool:
    """What :func:`_undecoded` finds, told from zarr ``array``'s metadata without xarray.

    xarray takes a scale, an offset and a fill value to mask from the attributes (a zarr 3
    array's own ``fill_value`` is not a mask to it).
    """
    attrs = array.attrs
    return (array.dtype.kind == "f" and not {"scale_factor", "add_offset"} & attrs.keys()
            and all(_nan_or_none(attrs.get(k)) for k in ("_FillValue", "missing_value")))


def lazy_variable(store, name: str, chunks: dict[str, int]):
    """``(data, dims)``: variable ``name`` of ``store`` as a dask array, and its dimensions.

    ``chunks`` by dimension name (others whole), as :func:`open_dataset` takes them; float16
    is widened to float32 as each block is read. A :func:`plain` variable is read in the
    tasks' threads (:mod:`pipeline.chunk_io`) without xarray, whose import (with pandas') is
    0.6-0.7 s of a process; any other through xarray's decoding, as the Dataset gives it.
    """
    array = store.group[name]
    dims = tuple(array.metadata.dimension_names or ())
    if plain(array):
        return lazy_float32(chunk_io.dask_array(array, location(store.path), chunks, dims)), dims
    # the other variables whole ({}): only this one is read
    dataset = open_dataset(store.path, store.group, lambda _, n: chunks if n == name else {})
    return dataset[name].data, dims


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
                      shard=a.shards[2] if a.shards else 0, dtype=str(a.dtype))

    @property
    def dtype(self) -> str:
        """The stored values' type (``float32`` or ``float16``)."""
        return str(self.radiance.dtype)

    @property
    def itemsize(self) -> int:
        """Bytes per stored value."""
        return self.radiance.dtype.itemsize

    @property
    def truth(self) -> bool:
        """Whether it holds a generated material's ground-truth fields."""
        return all(self.has(name) for name in TRUTH_DIMS)

    def dataset(self, chunks=None):
        """The store as a lazy xarray Dataset (``chunks``: see :func:`open_dataset`)."""
        return open_dataset(self.path, self.group, chunks)


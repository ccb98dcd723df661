"""Radiance stores: the zarr v3 layout every stage reads and writes (DESIGN.md, store contract).

A radiance store is a zarr v3 group that ``xarray.open_zarr`` opens as a Dataset with

- ``radiance``: float32, dims ``(view, light, y, x, channel)``, chunked in spatial tiles times a
  block of light directions (optionally grouped into shards of several tiles);
- coordinates ``theta_view``, ``phi_view`` (on ``view``), ``theta_light``, ``phi_light`` (on
  ``light``) in degrees, and ``channel`` labels;
- attrs ``btf_kind`` (``"btf"`` or ``"abtf"``), ``source`` and ``provenance`` (the command,
  parameters and package version that made it);
- generated stores also hold their ground truth: ``height``, ``albedo``, ``roughness`` and
  ``specular`` on ``(y, x[, channel])``.

Tasks read and write blocks of about :data:`TASK_TEXELS` texels per side, always made of whole
write units (the shard of a sharded array, else the chunk). Writing sharded arrays from many
workers is only safe shard by shard: two tasks writing parts of one shard both rewrite the whole
shard file, and one of them loses (measured here with zarr 3.1.6: a quarter to a half of the data
lost, silently). :func:`store_aligned` therefore refuses dask chunks that split a write unit.

Sharding is off by default: with zarr 3.1.6 it halved write and read throughput (measured on a
generated 576 MiB ABTF: 257 vs 549 MB/s writing, 405 vs 718 MB/s reading), and its only gain is
fewer files. ``--shard`` turns it on for file systems that need that.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.errors import BTFError
from pipeline.params import ParamError
from tasks.sampling import btf_kind

RADIANCE = "radiance"
RADIANCE_DIMS = ("view", "light", "y", "x", "channel")
DIRECTION_COORDS = {"theta_view": "view", "phi_view": "view",
                    "theta_light": "light", "phi_light": "light"}
TRUTH_DIMS = {"height": ("y", "x"), "albedo": ("y", "x", "channel"),
              "roughness": ("y", "x"), "specular": ("y", "x")}


@dataclass(frozen=True)
class Directions:
    """View and light directions of a store, in degrees (float64 arrays)."""

    theta_view: np.ndarray
    phi_view: np.ndarray
    theta_light: np.ndarray
    phi_light: np.ndarray

    @property
    def kind(self) -> str:
        """``"abtf"`` or ``"btf"`` (:func:`tasks.sampling.btf_kind`)."""
        return btf_kind(self.theta_view)

    @staticmethod
    def of(ds) -> Directions:
        """The directions of an opened radiance Dataset."""
        return Directions(*(np.asarray(ds[name].values, np.float64) for name in DIRECTION_COORDS))


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
            raise ParamError("chunk", f"must be at least 8 texels, got {self.chunk}")
        if self.dir_chunk < 1:
            raise ParamError("dir_chunk", f"must be at least 1, got {self.dir_chunk}")
        if self.shard < 0 or (self.shard and self.shard % self.chunk):
            raise ParamError("shard", f"must be 0 or a multiple of --chunk ({self.chunk}), "
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


def location(path: str | Path) -> str:
    """The absolute form of a path, as handed to tasks: workers may run in another directory."""
    return str(Path(path).absolute())


def _compressors():
    from zarr.codecs import BloscCodec

    # Byte shuffling groups the float32 exponents together. Measured on a generated wood ABTF
    # (one 48 MiB shard): lz4 gives 1.26x at 830 MB/s encode / 1390 MB/s decode, zstd-3 1.33x
    # at 220 / 1060 MB/s. Stores are read many times over (compression passes), so lz4.
    return BloscCodec(cname="lz4", clevel=5, shuffle="shuffle")


def create_radiance_store(
    path: str | Path,
    *,
    directions: Directions,
    ny: int,
    nx: int,
    channels: tuple[str, ...],
    layout: Layout,
    attrs: dict[str, Any],
    truth: bool = False,
):
    """Create an empty radiance store (metadata, coordinates, empty arrays) and return its group.

    ``radiance`` is filled with NaN until written, so unwritten chunks are never mistaken for
    data. With ``truth``, the ground-truth field arrays of a generated store are created too.
    """
    import zarr

    group = zarr.open_group(location(path), mode="w-", zarr_format=3)
    group.attrs.update(attrs)
    shape = (directions.theta_view.size, directions.theta_light.size, ny, nx, len(channels))
    chunks, shards = layout.grid(shape, RADIANCE_DIMS)
    rad = group.create_array(
        RADIANCE, shape=shape, chunks=chunks, shards=shards, dtype="float32",
        dimension_names=RADIANCE_DIMS, compressors=_compressors(), fill_value=np.nan,
    )
    rad.attrs.update({"coordinates": " ".join(DIRECTION_COORDS), "units": "relative radiance",
                      "long_name": "radiance per (view, light, texel, channel)"})
    for name, dim in DIRECTION_COORDS.items():
        values = getattr(directions, name)
        coord = group.create_array(name, shape=values.shape, dtype="float64",
                                   dimension_names=(dim,), compressors=None)
        coord[:] = values
        coord.attrs["units"] = "degree"
    labels = group.create_array("channel", shape=(len(channels),), dtype=str,
                                dimension_names=("channel",), compressors=None)
    labels[:] = np.array(channels)
    if truth:
        for name, dims in TRUTH_DIMS.items():
            tshape = tuple({"y": ny, "x": nx, "channel": len(channels)}[d] for d in dims)
            tchunks, tshards = layout.grid(tshape, dims)
            group.create_array(name, shape=tshape, chunks=tchunks, shards=tshards,
                               dtype="float32", dimension_names=dims,
                               compressors=_compressors(), fill_value=np.nan)
    return group


TASK_TEXELS = 512  # texels per side of the block one task reads or writes


def write_unit(array) -> tuple[int, ...]:
    """The block shape that can be written independently: the shard, or else the chunk."""
    return tuple(array.shards or array.chunks)


def task_block(array) -> tuple[int, ...]:
    """The block one task reads or writes: whole write units, ~TASK_TEXELS per spatial side."""
    dims = array.metadata.dimension_names or (None,) * array.ndim
    return tuple(unit * max(1, TASK_TEXELS // unit) if dim in ("y", "x") else unit
                 for unit, dim in zip(write_unit(array), dims, strict=True))


def aligned_chunks(array) -> tuple[tuple[int, ...], ...]:
    """Dask chunks that cover ``array`` in task blocks (see :func:`task_block`)."""
    out = []
    for n, block in zip(array.shape, task_block(array), strict=True):
        full, rest = divmod(n, block)
        out.append((block,) * full + ((rest,) if rest else ()))
    return tuple(out)


def blocks(chunks: tuple[int, ...]) -> list[tuple[int, int]]:
    """``(start, size)`` of each block of one axis of dask chunks."""
    starts = np.concatenate([[0], np.cumsum(chunks)[:-1]]).astype(int)
    return [(int(a), int(c)) for a, c in zip(starts, chunks, strict=True)]


def block_regions(array) -> list[tuple[slice, ...]]:
    """The regions of ``array`` in task blocks (see :func:`task_block`), in C order."""
    import itertools

    axes = [[slice(a, a + c) for a, c in blocks(chunks)] for chunks in aligned_chunks(array)]
    return list(itertools.product(*axes))


def store_aligned(sources: list, targets: list):
    """A delayed write of dask arrays into zarr arrays, refused unless aligned to write units.

    Every dask chunk boundary must fall on a shard boundary (or chunk boundary for unsharded
    arrays), so no two tasks ever write into the same shard or chunk.
    """
    import dask.array as da

    for source, target in zip(sources, targets, strict=True):
        for dim, (chunks, unit) in enumerate(zip(source.chunks, write_unit(target), strict=True)):
            edges = np.cumsum(chunks)[:-1]
            if np.any(edges % unit):
                raise ValueError(
                    f"dask chunks {chunks} of axis {dim} split write units of {unit} in "
                    f"{target.path!r}: concurrent writes would lose data"
                )
    return da.store(sources, targets, lock=False, compute=False)


def open_group(path: str | Path):
    """Open a zarr v3 group for reading, with a clear error if it is not one."""
    import zarr

    p = Path(path)
    if not p.exists():
        raise BTFError(f"{path}: no such store")
    meta = p / "zarr.json"
    if not meta.is_file():
        hint = " (a zarr v2 store: convert it to zarr v3)" if (p / ".zgroup").exists() else ""
        raise BTFError(f"{path}: not a zarr v3 store, there is no zarr.json{hint}")
    try:
        node_type = json.loads(meta.read_text()).get("node_type")
    except (OSError, ValueError) as exc:
        raise BTFError(f"{path}: unreadable zarr.json ({exc})") from None
    if node_type != "group":
        raise BTFError(f"{path}: a zarr array, not a group of variables")
    return zarr.open_group(location(p), mode="r")


def read_chunks(group, name: str = RADIANCE) -> dict[str, int]:
    """Dask chunk size per dimension for reading ``name``: its task blocks."""
    array = group[name]
    dims = array.metadata.dimension_names or ()
    return dict(zip(dims, task_block(array), strict=True))


def check_radiance(group, path: str | Path) -> None:
    """Raise :class:`BTFError` naming what is wrong if ``group`` is not a radiance store."""
    names = sorted(group.array_keys())
    if RADIANCE not in names:
        raise BTFError(f"{path}: no variable {RADIANCE!r} (found: {', '.join(names) or 'none'})")
    rad = group[RADIANCE]
    dims = tuple(rad.metadata.dimension_names or ())
    if dims != RADIANCE_DIMS:
        raise BTFError(f"{path}: variable {RADIANCE!r} has dims {dims}, expected {RADIANCE_DIMS}")
    if rad.dtype != np.float32:
        raise BTFError(f"{path}: variable {RADIANCE!r} is {rad.dtype}, expected float32")
    for name, dim in {**DIRECTION_COORDS, "channel": "channel"}.items():
        if name not in names:
            raise BTFError(f"{path}: coordinate {name!r} is missing")
        size = rad.shape[RADIANCE_DIMS.index(dim)]
        if group[name].shape != (size,):
            raise BTFError(
                f"{path}: coordinate {name!r} has shape {group[name].shape}, expected ({size},)"
            )


def open_dataset(path: str | Path, group=None):
    """Open a store as a lazy xarray Dataset whose data variables are dask arrays of task blocks.

    Coordinates stay small lazy arrays; each data variable is chunked in whole write units, so
    no read straddles a shard and no shard is read by two tasks.
    """
    import xarray as xr

    group = open_group(path) if group is None else group
    ds = xr.open_zarr(location(path), consolidated=False, chunks=None)
    for name in ds.data_vars:
        ds[name] = ds[name].chunk(read_chunks(group, name))
    return ds


def open_radiance(path: str | Path):
    """Open and validate a radiance store as a lazy xarray Dataset (dask chunks: task blocks)."""
    group = open_group(path)
    check_radiance(group, path)
    return open_dataset(path, group)


def read_directions(group) -> Directions:
    """The direction coordinates of a radiance store (small arrays)."""
    return Directions(*(np.asarray(group[name][:], np.float64) for name in DIRECTION_COORDS))

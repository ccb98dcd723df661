"""Reductions over stores with dask's own machinery (``dask.array.reduction`` and friends).

- :func:`read_array`: a zarr variable as a dask array of task blocks whose read errors name the
  store, variable and block (the chunk, for a failed checksum); :func:`bad_chunks` lists every
  unreadable chunk of some variables;
- :func:`statistics`: counts of NaN, Inf and negative values and the finite minimum, maximum
  and sum of an array, all from one read of each block;
- :func:`light_sums`: the per-texel sums over all lights of one view that the reference image
  is made from (:func:`tasks.reference.light_sums`), combined over light blocks by a tree.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from pipeline import checksums, chunk_io, storage
from pipeline.errors import BTFError
from pipeline.graphs.blocks import aligned_chunks
from pipeline.stores.base import RADIANCE, location
from pipeline.stores.radiance import as_float32
from tasks.reference import SUMS, combine_light_sums
from tasks.reference import light_sums as block_light_sums


def _read_region(block_info=None, *, store: str, variable: str) -> np.ndarray:
    region = tuple(slice(a, b) for a, b in block_info[None]["array-location"])
    return _read(store, variable, region)


def _read(store: str, variable: str, region: tuple[slice, ...]) -> np.ndarray:
    """``region`` of a variable; an error names the store, the variable and the block."""
    import zarr

    array = zarr.open_array(storage.store(store), path=variable, mode="r")
    try:
        return as_float32(chunk_io.read(array, region))
    except Exception as exc:  # re-raised with the block's key, whatever the codec raised
        if (error := checksums.named(store, variable, array, region, exc)) is not None:
            raise error from None
        where = ", ".join(f"{r.start}:{r.stop}" for r in region)
        raise BTFError(f"{store}: variable {variable!r}, block [{where}] is unreadable: "
                       f"{type(exc).__name__}: {exc}") from None


def read_array(path: str | Path, name: str):
    """Variable ``name`` of a store as a dask array of task blocks (one read per block)."""
    import dask.array as da
    import zarr

    store = location(path)
    array = zarr.open_array(storage.store(store), path=name, mode="r")
    dtype = np.float32 if array.dtype == np.float16 else array.dtype  # read as float32
    return da.map_blocks(_read_region, chunks=aligned_chunks(array), dtype=dtype,
                         meta=np.empty((0,) * array.ndim, dtype), store=store, variable=name)


def _bad_chunks(store: str, variable: str, region: tuple[slice, ...]) -> list:
    import zarr

    array = zarr.open_array(storage.store(store), path=variable, mode="r")
    try:
        array[region]
        return []
    except Exception:  # one chunk at a time, to find which
        return checksums.bad_chunks(array, region)


def bad_chunks(path: str | Path, names: list[str]) -> dict:
    """Delayed lists of the unreadable chunks of variables ``names`` (grid indices), per name.

    Read task block by task block; a block that fails is read again chunk by chunk.
    """
    import dask
    import zarr
    from dask.array.core import slices_from_chunks

    store = location(path)
    out = {}
    for name in names:
        array = zarr.open_array(storage.store(store), path=name, mode="r")
        parts = [dask.delayed(_bad_chunks, pure=True)(store, name, region)
                 for region in slices_from_chunks(aligned_chunks(array))]
        out[name] = dask.delayed(lambda *lists: sorted(c for part in lists for c in part),
                                 pure=True)(*parts)
    return out


def statistics(x) -> dict:
    """Lazy counts and extremes of an array, from one read of each block.

    ``nan``, ``inf``, ``negative`` and ``finite`` counts, and the ``min``, ``max`` and ``sum``
    (float64) of the finite values (``+inf``, ``-inf`` and 0 if there are none).
    """
    import dask.array as da

    finite = da.isfinite(x)
    return {"nan": da.isnan(x).sum(), "inf": da.isinf(x).sum(), "negative": (x < 0).sum(),
            "finite": finite.sum(), "min": da.where(finite, x, np.inf).min(),
            "max": da.where(finite, x, -np.inf).max(),
            "sum": da.where(finite, x, 0).sum(dtype=np.float64)}


def _block_sums(block_info=None, *, store: str, view: int, edges: tuple[np.ndarray, ...],
                lights: np.ndarray) -> np.ndarray:
    """The light sums of one block of lights and texels of a view, read here."""
    index = block_info[None]["chunk-location"]
    region = tuple(slice(int(e[i]), int(e[i + 1])) for e, i in zip(edges, index[:3],
                                                                    strict=True))
    layers = _read(store, RADIANCE, (slice(view, view + 1), *region))[0]
    return block_light_sums(layers, lights[region[0]])[None]


def _sums_of(layers: np.ndarray, lights: np.ndarray) -> np.ndarray:
    return block_light_sums(layers, lights)[None]


def _keep(sums: np.ndarray, axis, keepdims: bool) -> np.ndarray:
    return sums if keepdims else sums[0]


def _combine(parts: np.ndarray, axis, keepdims: bool) -> np.ndarray:
    out = combine_light_sums(parts)
    return out[None] if keepdims else out


def light_sums(path: str | Path, view: int, lights: np.ndarray) -> tuple[Any, tuple[int, ...]]:
    """Per-texel sums over all lights of one view's radiance, and its task blocks.

    The sums are a dask array ``(y, x, len(SUMS))`` of float64; the blocks are counted along
    lights, rows and columns. ``lights`` are the unit light vectors ``(light, 3)``. Each task
    block of lights and texels is read and summed in one task (only its sums leave it: on the
    ``processes`` scheduler a read of its own would send the block's radiance through the
    client), then the blocks are combined by :func:`tasks.reference.combine_light_sums` (which
    rescales their weights to a common maximum) in a tree, so any number of lights is reduced
    in memory bounded by a few blocks.
    """
    import dask.array as da
    import zarr

    store = location(path)
    radiance = zarr.open_array(storage.store(store), path=RADIANCE, mode="r")
    chunks = aligned_chunks(radiance)[1:4]
    edges = tuple(np.concatenate([[0], np.cumsum(c)]) for c in chunks)
    per_block = da.map_blocks(
        _block_sums, chunks=((1,) * len(chunks[0]), chunks[1], chunks[2], (len(SUMS),)),
        dtype=np.float64, meta=np.empty((0,) * 4, np.float64), store=store, view=view,
        edges=edges, lights=np.asarray(lights, np.float64))
    return _combined(per_block), tuple(len(c) for c in chunks)


def layer_light_sums(layers, lights: np.ndarray) -> tuple[Any, tuple[int, ...]]:
    """:func:`light_sums` of layers given as a dask array ``(light, y, x, channel)``.

    For layers that are computed, not read: a compressed store's reconstruction.
    """
    import dask.array as da

    vectors = da.from_array(np.asarray(lights, np.float64), chunks=(layers.chunks[0], 3))
    per_block = da.blockwise(
        _sums_of, "lyxs", layers, "lyxc", vectors, "ld", new_axes={"s": len(SUMS)},
        adjust_chunks={"l": 1}, concatenate=True, dtype=np.float64,
        meta=np.empty((0,) * 4, np.float64))
    return _combined(per_block), tuple(len(c) for c in layers.chunks[:3])


def _combined(per_block):
    """Light sums of blocks ``(block, y, x, sums)`` combined over the blocks, in a tree."""
    import dask.array as da

    return da.reduction(per_block, chunk=_keep, combine=_combine, aggregate=_combine, axis=0,
                        dtype=np.float64, concatenate=True, meta=np.empty((0,) * 3, np.float64))

"""Compressed stores: ``U``, ``S``, ``V`` of a BTF matrix, and radiance rebuilt on demand.

A compressed store (made by ``btf compress``) is a zarr v3 group holding

- ``U``: float32, dims ``(view, light, channel, component)``: the eigen-ABRDFs;
- ``S``: float32, dims ``(component,)``: singular values, decreasing;
- ``V``: float32, dims ``(y, x, component)``: the eigentextures, chunked in spatial tiles;
- the direction coordinates and ``channel`` labels of the radiance store it came from;
- attrs ``btf_kind = "compressed"``, the range reduction (``log(radiance + eps)``), the SVD's
  parameters, its measured error and the provenance.

:func:`open_compressed` gives a Dataset whose ``radiance`` is a lazy dask array with the dims,
coordinates and chunking of a radiance store. Each of its blocks is
``exp(U[rows] diag(S) V[tile]^T) - eps`` and depends on one chunk of ``U`` and one tile of
``V``, so ``sel``/``isel`` followed by ``compute`` reads only what the selection needs.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from pipeline.errors import BTFError
from pipeline.store import (
    DIRECTION_COORDS,
    RADIANCE,
    Directions,
    location,
    open_group,
    read_directions,
)
from tasks.svd import reconstruct_layers

KIND = "compressed"
FACTOR_DIMS = {"U": ("view", "light", "channel", "component"), "S": ("component",),
               "V": ("y", "x", "component")}


def create_compressed_store(path: str | Path, *, directions: Directions,
                            channels: tuple[str, ...], ny: int, nx: int, rank: int,
                            chunk: int, dir_chunk: int, attrs: dict[str, Any]):
    """Create an empty compressed store with its coordinates; returns the zarr group."""
    import zarr
    from zarr.codecs import BloscCodec

    group = zarr.open_group(location(path), mode="w-", zarr_format=3)
    group.attrs.update({**attrs, "btf_kind": KIND})
    nv, nl, nc = directions.theta_view.size, directions.theta_light.size, len(channels)
    compressors = BloscCodec(cname="lz4", clevel=5, shuffle="shuffle")
    shapes = {"U": (nv, nl, nc, rank), "S": (rank,), "V": (ny, nx, rank)}
    chunks = {"U": (1, min(dir_chunk, nl), nc, rank), "S": (rank,),
              "V": (min(chunk, ny), min(chunk, nx), rank)}
    for name, dims in FACTOR_DIMS.items():
        group.create_array(name, shape=shapes[name], chunks=chunks[name], dtype="float32",
                           dimension_names=dims, compressors=compressors, fill_value=np.nan)
    group["U"].attrs["long_name"] = "eigen-ABRDFs"
    group["V"].attrs["long_name"] = "eigentextures"
    group["S"].attrs["long_name"] = "singular values"
    group["U"].attrs["coordinates"] = " ".join(DIRECTION_COORDS)
    for name, dim in DIRECTION_COORDS.items():
        coord = group.create_array(name, shape=(getattr(directions, name).size,),
                                   dtype="float64", dimension_names=(dim,), compressors=None)
        coord[:] = getattr(directions, name)
        coord.attrs["units"] = "degree"
    labels = group.create_array("channel", shape=(nc,), dtype=str,
                                dimension_names=("channel",), compressors=None)
    labels[:] = np.array(channels)
    return group


def check_compressed(group, path: str | Path) -> None:
    """Raise :class:`BTFError` naming what is wrong if ``group`` is not a compressed store."""
    if group.attrs.get("btf_kind") != KIND:
        raise BTFError(f"{path}: not a compressed store (btf_kind is "
                       f"{group.attrs.get('btf_kind')!r}; make one with btf compress)")
    names = set(group.array_keys())
    for name, dims in FACTOR_DIMS.items():
        if name not in names:
            raise BTFError(f"{path}: variable {name!r} is missing")
        if tuple(group[name].metadata.dimension_names or ()) != dims:
            raise BTFError(f"{path}: variable {name!r} has dims "
                           f"{group[name].metadata.dimension_names}, expected {dims}")
    if "transform" not in group.attrs or "eps" not in group.attrs["transform"]:
        raise BTFError(f"{path}: attrs lack the range reduction ('transform' with 'eps')")
    u, s, v = (group[n].shape for n in ("U", "S", "V"))
    if not u[-1] == s[0] == v[-1]:
        raise BTFError(f"{path}: U, S and V disagree on the rank: {u[-1]}, {s[0]}, {v[-1]}")
    sizes = {"view": u[0], "light": u[1], "channel": u[2]}
    for name, dim in {**DIRECTION_COORDS, "channel": "channel"}.items():
        if name not in names:
            raise BTFError(f"{path}: coordinate {name!r} is missing")
        if group[name].shape != (sizes[dim],):
            raise BTFError(f"{path}: coordinate {name!r} has shape {group[name].shape}, but U "
                           f"has {sizes[dim]} {dim}(s)")


def _rebuild(u, s, v, *, eps: float) -> np.ndarray:
    return reconstruct_layers(u, s, v, eps=eps)


def lazy_radiance(u, s, v, *, eps: float):
    """Dask radiance ``(view, light, y, x, channel)`` from dask factors.

    There is one block per pair of a ``U`` chunk and a ``V`` tile.
    """
    import dask.array as da

    return da.blockwise(
        _rebuild, "vlyxc", u, "vlck", s, "k", v, "yxk", concatenate=True, align_arrays=False,
        dtype=np.float32, meta=np.empty((0,) * 5, np.float32), eps=eps)


def open_compressed(path: str | Path, *, rank: int | None = None):
    """Open a compressed store as a Dataset with a lazy ``radiance`` (and ``U``, ``S``, ``V``).

    Parameters
    ----------
    path
        The compressed store.
    rank
        Use only the first ``rank`` components (default: all).
    """
    import dask.array as da
    import xarray as xr
    import zarr

    group = open_group(path)
    check_compressed(group, path)
    full = group["S"].shape[0]
    rank = full if rank is None else rank
    if not 1 <= rank <= full:
        raise BTFError(f"{path}: --rank {rank} is not between 1 and the stored rank {full}")
    # zarr arrays, not a path: dask would open a path through fsspec instead of zarr's store
    factors = {name: da.from_zarr(zarr.open_array(location(path), path=name, mode="r"))[
        ..., :rank] for name in FACTOR_DIMS}
    eps = float(group.attrs["transform"]["eps"])
    radiance = lazy_radiance(factors["U"], factors["S"], factors["V"], eps=eps)
    d = read_directions(group)
    coords = {name: (dim, getattr(d, name)) for name, dim in DIRECTION_COORDS.items()}
    coords["channel"] = ("channel", [str(c) for c in group["channel"][:]])
    attrs = {**group.attrs, "rank_used": rank}
    data = {RADIANCE: (("view", "light", "y", "x", "channel"), radiance,
                       {"rank_used": rank, "eps": eps, "error": attrs.get("error"),
                        "long_name": "radiance rebuilt as exp(U S V^T) - eps"})}
    data.update({name: (FACTOR_DIMS[name], factors[name]) for name in FACTOR_DIMS})
    return xr.Dataset(data, coords=coords, attrs=attrs)

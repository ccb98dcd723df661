"""One layer of the unbounded surface a tile set covers, as a lazy dask array.

The tiles of the layer are read once (one task) and every block of the surface is a pure
gather from them (:mod:`tasks.placement`): quilting's tiles placed by the corner types a hash of
the lattice vertices and the seed gives, the roller's on their (possibly sheared) lattice,
chosen per cell by a hash of the cell and the seed. Only that layer of the tile set is read.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline import storage
from pipeline.errors import BTFError
from pipeline.stores.base import RADIANCE, check_computed, location
from pipeline.stores.tileset import corner_order, open_tileset, stored_seed
from tasks.placement import gather, lattice_gather


def _layer_tiles(store: str, view: int, light: int, order: np.ndarray | None = None
                 ) -> np.ndarray:
    """The tiles of one layer, ``(tiles, ty, tx, channel)`` float32, in ``order``."""
    import zarr

    group = zarr.open_group(storage.store(store), mode="r", use_consolidated=False)
    if group.attrs["btf_kind"] == "tileset":
        tiles = group[RADIANCE][:, view, light]
    else:  # the layer's values formed on the sample, then each tile's prescription applied
        from pipeline.stores.tileset import tile_layers
        from tasks.transform import Transform

        u = group["U"][view, light]  # (channel, component)
        scale = Transform.from_attrs(group.attrs["transform"]).layer_scale(
            group["theta_light"][light : light + 1])
        tiles = tile_layers(group, range(group["corners"].shape[0]), u[None],
                            scale=scale)[:, :, :, 0]
    if order is None or np.array_equal(order, np.arange(len(tiles))):
        return tiles
    return tiles[order]


def _surface_block(tiles, block_info=None, *, origin, seed, corners):
    (y0, y1), (x0, x1), _ = block_info[None]["array-location"]
    return gather(tiles, origin[0] + y0, origin[1] + x0, y1 - y0, x1 - x0, seed=seed,
                  corners=corners)


def _lattice_block(tiles, block_info=None, *, origin, seed, hnf, basis, representative):
    (y0, y1), (x0, x1), _ = block_info[None]["array-location"]
    return lattice_gather(tiles, origin[0] + y0, origin[1] + x0, y1 - y0, x1 - x0, hnf=hnf,
                          basis=basis, representative=representative, seed=seed)


def lazy_layer(path: str | Path, *, view: int, light: int, size: tuple[int, int],
               origin: tuple[int, int] = (0, 0), seed: int | None = None, chunk: int = 2048):
    """One layer of the surface tiled by a tile set, ``(y, x, channel)``, in blocks of ``chunk``.

    ``seed=None``: the seed stored with the tile set.
    """
    import dask
    import dask.array as da
    from dask.array.core import normalize_chunks

    group = open_tileset(path)
    nv, nl = group["theta_view"].shape[0], group["theta_light"].shape[0]
    if not 0 <= view < nv:
        raise BTFError(f"{path}: --view {view} is out of range (the tile set has {nv} views)")
    if not 0 <= light < nl:
        raise BTFError(f"{path}: --light {light} is out of range (the tile set has {nl} lights)")
    check_computed(group, str(path), view, light)
    if seed is None:
        seed = stored_seed(group)
    channels = group["channel"].shape[0]
    lattice = group.attrs.get("placement") == "lattice"
    order = None if lattice else corner_order(path, group["corners"][...],
                                              int(group.attrs["corner_types"]))
    tiles = dask.delayed(_layer_tiles, pure=True)(location(path), view, light, order)
    chunks = normalize_chunks((chunk, chunk, channels), (*size, channels))
    meta = np.empty((0, 0, 0), np.float32)
    if lattice:
        spec = group.attrs["lattice"]
        rep = group["representative"][...] if "representative" in group.array_keys() else None
        return da.map_blocks(_lattice_block, tiles, chunks=chunks, dtype=np.float32, meta=meta,
                             origin=origin, seed=seed, hnf=tuple(spec["hnf"]),
                             basis=(tuple(spec["U"]), tuple(spec["V"])),
                             representative=rep)
    corners = int(group.attrs["corner_types"])
    return da.map_blocks(_surface_block, tiles, chunks=chunks, dtype=np.float32, meta=meta,
                         origin=origin, seed=seed, corners=corners)

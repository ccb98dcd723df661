"""One layer of the unbounded surface a tile set covers, as a lazy dask array.

The tiles of the layer are read once (one task) and every block of the surface is a pure
gather from them (:mod:`tasks.placement`): quilting's tiles placed by the corner types a hash of
the lattice vertices and the seed gives, the roller's on their (possibly sheared) lattice,
chosen per cell by a hash of the cell and the seed. Only that layer of the tile set is read.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.errors import BTFError
from pipeline.stores import TileSetStore, open_store
from pipeline.stores.base import RADIANCE
from pipeline.stores.radiance import as_float32
from tasks.placement import gather, lattice_gather


def _layer_tiles(store: str, view: int, light: int, order: np.ndarray | None = None
                 ) -> np.ndarray:
    """The tiles of one layer, ``(tiles, ty, tx, channel)`` float32, in ``order``."""
    tileset = open_store(store, TileSetStore, checked=False)
    if not tileset.compressed:
        tiles = as_float32(tileset[RADIANCE][:, view, light])
    else:  # the layer's values formed on the sample, then each tile's prescription applied
        u = tileset["U"][view, light]  # (channel, component)
        tiles = tileset.tile_layers(range(tileset.tiles), u[None],
                                    scale=tileset.layer_scale([light]))[:, :, :, 0]
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


def lazy_layer(path: str | Path | TileSetStore, *, view: int, light: int,
               size: tuple[int, int], origin: tuple[int, int] = (0, 0), seed: int | None = None,
               chunk: int = 2048):
    """One layer of the surface tiled by a tile set, ``(y, x, channel)``, in blocks of ``chunk``.

    ``path``: the tile set, or its handle. ``seed=None``: the seed stored with the tile set.
    """
    import dask
    import dask.array as da
    from dask.array.core import normalize_chunks

    tileset = path if isinstance(path, TileSetStore) else open_store(path, TileSetStore)
    d = tileset.directions
    if not 0 <= view < d.views:
        raise BTFError(f"{tileset.path}: --view {view} is out of range (the tile set has "
                       f"{d.views} views)")
    if not 0 <= light < d.lights:
        raise BTFError(f"{tileset.path}: --light {light} is out of range (the tile set has "
                       f"{d.lights} lights)")
    tileset.check_computed(view, light)
    if seed is None:
        seed = tileset.seed
    channels = len(tileset.channels)
    lattice = tileset.placement == "lattice"
    order = None if lattice else tileset.order()
    tiles = dask.delayed(_layer_tiles, pure=True)(tileset.location, view, light, order)
    chunks = normalize_chunks((chunk, chunk, channels), (*size, channels))
    meta = np.empty((0, 0, 0), np.float32)
    if lattice:
        return da.map_blocks(_lattice_block, tiles, chunks=chunks, dtype=np.float32, meta=meta,
                             origin=origin, seed=seed, hnf=tileset.hnf, basis=tileset.basis,
                             representative=tileset.representative)
    return da.map_blocks(_surface_block, tiles, chunks=chunks, dtype=np.float32, meta=meta,
                         origin=origin, seed=seed, corners=tileset.corner_types)

"""Graphs of ``btf scene``: only the chunks a scene touches, per kind of source.

Every graph yields ``(direction, y, x, channel)`` float32 at the requested level, as a dask
array in blocks of about ``chunk`` texels a side of what is read (level 0, or the stored level
n) and of as many directions as :func:`pipeline.stores.scene.directions_per_chunk` allows:

- radiance stores: the requested layers' chunks of the region (dask culls the rest), from the
  pyramid level when the store has it, else block means of level 0;
- compressed stores: the ``V`` tiles of the region (of the pyramid level, else of level 0,
  averaged after reconstruction, so in linear radiance) and only the ``U`` chunks holding the
  needed layers; each block rebuilds just those layers (:func:`tasks.scene.compressed_block`);
- tile sets: each output block depends on the tiles its lattice cells show (quilting's corner
  placement is a hash, so they are known before anything is read), at the tiles' pyramid level
  when it is stored; roller sets with several tiles pick a tile per cell of a sheared lattice,
  and there every tile of the layer is read;
- surface stores: one layer, read like a radiance store.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from pipeline import storage
from pipeline.stores.base import RADIANCE, location
from pipeline.stores.radiance import as_float32
from pipeline.stores.scene import directions_per_chunk
from tasks.scene import compressed_block, surface_block
from tasks.transform import Transform


@dataclasses.dataclass(frozen=True)
class Request:
    """A scene resolved against its source.

    Attributes
    ----------
    layers
        Distinct ``(view, light)`` store indices the scene needs.
    weights
        ``(direction, layer)`` interpolation weights over ``layers``, a scipy CSR matrix
        (``directions: all`` of a dome151 store is 22801 x 22801).
    window
        ``(y0, y1, x0, x1)`` of the output in level-n texels (surface coordinates for tile
        sets; may be negative there).
    level
        Level of detail n; ``factor`` = 2^n.
    stored_level
        Whether level n is read from the store's pyramid (else averaged from level 0).
    chunk
        Texels per side of an output block, of what is read: level 0 (then a block is
        ``chunk / 2^n`` level-n texels a side) or the stored level n.
    """

    layers: list[tuple[int, int]]
    weights: Any
    window: tuple[int, int, int, int]
    level: int
    stored_level: bool
    chunk: int
    rank: int | None = None

    @property
    def factor(self) -> int:
        """Level-0 texels per level-n texel along each side."""
        return 2**self.level

    @property
    def shape(self) -> tuple[int, int]:
        """Output texels ``(y, x)``."""
        y0, y1, x0, x1 = self.window
        return y1 - y0, x1 - x0

    @property
    def block(self) -> int:
        """Level-n texels per side of an output block (``chunk`` texels of what is read)."""
        return self.chunk if self.stored_level else max(1, self.chunk // self.factor)

    @property
    def read_factor(self) -> int:
        """Texels read per level-n texel along each side: 1 from a stored level, else 2^n."""
        return 1 if self.stored_level else self.factor

    def layers_per_task(self, block: tuple[int, int], channels: int) -> int:
        """Distinct layers a block task of ``block`` texels holds (as a scene store chunk)."""
        return directions_per_chunk(max(len(self.layers), 1), block, channels)

    def read_window(self) -> tuple[slice, slice]:
        """The texels read: of level n when it is stored, else of level 0."""
        y0, y1, x0, x1 = self.window
        return (slice(y0, y1), slice(x0, x1)) if self.stored_level else self.level0()

    def level0(self) -> tuple[slice, slice]:
        """The level-0 texels the window covers."""
        y0, y1, x0, x1 = self.window
        f = self.factor
        return slice(y0 * f, y1 * f), slice(x0 * f, x1 * f)


def _mean32(block, axis=None):
    return np.mean(block, axis=axis, dtype=np.float64).astype(np.float32)


def _coarsen(layer, factor: int):
    """Block means of a dask ``(y, x, channel)`` layer whose sides are multiples of factor."""
    import dask.array as da

    if factor == 1:
        return layer
    side = max(factor, (layer.chunksize[0] // factor) * factor)
    layer = layer.rechunk((side, side, -1))
    return da.coarsen(_mean32, layer, {0: factor, 1: factor})


def radiance_graph(data, request: Request):
    """Scene from a radiance ``(view, light, y, x, channel)`` dask array.

    ``data`` is level n itself when ``request.stored_level``, else level 0.
    """
    import dask.array as da

    ys, xs = request.read_window()
    factor = request.read_factor
    layers = [_coarsen(data[v, li, ys, xs], factor) for v, li in request.layers]
    out = []
    w = request.weights
    for d in range(w.shape[0]):
        used, values = w.indices[w.indptr[d]:w.indptr[d + 1]], w.data[w.indptr[d]:w.indptr[d + 1]]
        if len(used) == 1 and values[0] == 1.0:
            out.append(layers[used[0]])
        else:
            out.append(sum(np.float32(x) * layers[k] for k, x in zip(used, values, strict=True)
                           ).astype(np.float32))
    block = request.block
    ny, nx = request.shape
    # as many directions as a scene store chunk of ``chunk`` level-n texels holds: a thin
    # on-the-fly block must not gather the directions of a whole output task
    per_task = directions_per_chunk(len(out), (min(request.chunk, ny),
                                               min(request.chunk, nx)), out[0].shape[-1])
    return da.stack(out).rechunk((per_task, block, block, -1))


def read_u_rows(u, layers: list[tuple[int, int]], rank: int) -> tuple[np.ndarray, int]:
    """Rows ``(layer, channel, k)`` of a zarr ``U`` and the number of chunks read.

    Each chunk holding a needed row is read once. When those chunks are exactly the chunks of
    their bounding box (every layer, say), the box is read in one call, which zarr fetches
    concurrently: 144 layers of a hemi:12 store in 3 ms instead of 6, which is what a small
    region of every direction costs at a coarse level.
    """
    cv, dl = u.chunks[0], u.chunks[1]
    needed = {(v // cv, li // dl) for v, li in layers}
    a0, a1 = min(a for a, _ in needed), max(a for a, _ in needed) + 1
    b0, b1 = min(b for _, b in needed), max(b for _, b in needed) + 1
    if len(needed) > 1 and len(needed) == (a1 - a0) * (b1 - b0):
        box = np.asarray(u[a0 * cv : a1 * cv, b0 * dl : b1 * dl, :, :rank])
        return (np.stack([box[v - a0 * cv, li - b0 * dl] for v, li in layers]),
                len(needed))
    chunks = {(a, b): np.asarray(u[a * cv : (a + 1) * cv, b * dl : (b + 1) * dl, :, :rank])
              for a, b in needed}
    return (np.stack([chunks[(v // cv, li // dl)][v % cv, li % dl] for v, li in layers]),
            len(needed))


def compressed_graph(v, u_rows: np.ndarray, s: np.ndarray, transform: Transform,
                     request: Request, scale: np.ndarray | None = None):
    """Scene from a compressed store: ``v`` the dask ``V`` (level n if stored, else level 0).

    Only the region's ``V`` tiles are read; each block rebuilds just the needed layers.
    ``scale`` (one per layer of the request): a cosine store's layer scale.
    """
    ys, xs = request.read_window()
    factor = request.read_factor
    import dask.array as da

    rank = u_rows.shape[-1]
    region = v[ys, xs, :rank]
    side = max(factor, (request.chunk // factor) * factor)
    region = region.rechunk((side, side, -1))
    nc = u_rows.shape[1]
    block = region.chunks[0][0], region.chunks[1][0]  # texels a task rebuilds layers on
    parts = []
    for dirs, used, w in direction_groups(request.weights, request.layers_per_task(block, nc)):
        chunks = ((len(dirs),), tuple(c // factor for c in region.chunks[0]),
                  tuple(c // factor for c in region.chunks[1]), (nc,))
        parts.append(region.map_blocks(
            compressed_block, u=u_rows[used], s=np.asarray(s[:rank], np.float32),
            transform=transform, weights=w, factor=factor,
            scale=None if scale is None else scale[used], chunks=chunks, drop_axis=2,
            new_axis=[0, 3],
            dtype=np.float32, meta=np.empty((0, 0, 0, 0), np.float32)))
    return da.concatenate(parts, axis=0) if len(parts) > 1 else parts[0]


def _blocks(request: Request) -> list[list[tuple[int, int, int, int]]]:
    """Output blocks ``(y0, y1, x0, x1)`` in level-n surface texels, as a grid of rows."""
    y0, y1, x0, x1 = request.window
    b = request.block
    return [[(ya, min(ya + b, y1), xa, min(xa + b, x1)) for xa in range(x0, x1, b)]
            for ya in range(y0, y1, b)]


def _tile_data(store: str, tile: int, layers, rank, path: str):
    """One stored tile of the variable at ``path`` (level 0, or a level of the pyramid).

    ``(y, x, layer, channel)`` radiance of ``layers``; for a compressed tile set (``layers``
    None) its ``(y, x, k)`` eigentextures.
    """
    import zarr

    array = zarr.open_array(storage.store(store), path=path, mode="r")
    if layers is None:
        return as_float32(array[tile, :, :, :rank])
    return as_float32(np.stack([array[tile, v, li] for v, li in layers], axis=2))


def _open(store: str):
    """The compressed tile set at ``store`` (its stage checked it)."""
    from pipeline.stores import CompressedTileSetStore, open_store

    return open_store(store, CompressedTileSetStore, checked=False)


def _sample_values(store: str, u_rows: np.ndarray, rank) -> np.ndarray:
    """A prescribed compressed tile set's sample values of some layers: ``(y, x, n * nc)``."""
    tiles = _open(store)
    return tiles.sample_values(tiles.layer_coefficients(u_rows, rank))


def _prescribed_tile(store: str, tile: int, values: np.ndarray, layers: int, scale
                     ) -> np.ndarray:
    """Radiance ``(y, x, layer, channel)`` of one tile of a prescribed compressed tile set."""
    tiles = _open(store)
    return tiles.decode(tiles.prescribe(tile, values), layers, scale)


def _surface(tiles: dict, y0, x0, ny, nx, *, factor: int, placement: dict, u, s, transform,
             weights, scale=None):
    from tasks.placement import gather, lattice_gather

    f = factor
    if placement["lattice"]:
        stack = np.stack([tiles[t] for t in sorted(tiles)])
        values = lattice_gather(stack, y0 * f, x0 * f, ny * f, nx * f, hnf=placement["hnf"],
                                basis=placement["basis"],
                                representative=placement["representative"],
                                seed=placement["seed"])
    else:
        values = gather(tiles, y0 * f, x0 * f, ny * f, nx * f, seed=placement["seed"],
                        corners=placement["corners"])
    return surface_block(values, weights=weights, factor=f, u=u, s=s, transform=transform,
                         scale=scale)


def visible_tiles(y0: int, x0: int, ny: int, nx: int, *, factor: int, tile_shape,
                  placement: dict) -> list[int]:
    """Stored tiles a level-n block of the surface shows (corner placement), else all."""
    from tasks.placement import region_tiles

    if placement["lattice"]:
        return list(range(placement["tiles"]))
    codes = region_tiles(y0 * factor, x0 * factor, ny * factor, nx * factor,
                         tile_shape=tile_shape, seed=placement["seed"],
                         corners=placement["corners"])
    return sorted({int(c) for c in np.unique(codes)})


def tileset_graph(tileset, request: Request, placement: dict, *, u_rows=None,
                  s=None, transform: Transform | None = None, level_path: str | None = None,
                  scale: np.ndarray | None = None):
    """Scene of the surface a tile set covers; returns the dask array and the tiles read.

    ``tileset`` is the :class:`pipeline.stores.TileSetStore` handle.

    With ``level_path`` (the tiles' stored level n, ``request.stored_level``) the surface is
    laid from the level-n tiles: tile sides are multiples of 2^n, so that equals the block
    means of the level-0 surface (corner placement only).

    Directions are processed in groups whose layers number at most
    :meth:`Request.layers_per_task` of the values a task holds per layer (its block and the
    radiance tiles it shows), so a task holds a bounded number of values; a compressed tile
    set's tiles are eigentextures, read once for all groups.
    """
    import dask
    import dask.array as da

    compressed = u_rows is not None
    # a compressed set that keeps the sample's V: its tiles are radiance computed per group of
    # layers (the sample's values formed once, then each tile prescribed), laid as a radiance
    # tile set's are
    from_sample = compressed and tileset.prescribed
    store = tileset.location
    f = request.read_factor
    tile_shape = tuple(t // (request.factor // f) for t in tileset.tile_shape)
    path = level_path or ("V" if compressed else RADIANCE)
    order = placement["order"]  # placement code -> stored tile
    read: set = set()
    parts = []
    shared: dict = {}
    nc = u_rows.shape[1] if compressed else len(tileset.channels)
    grid = [[(block, visible_tiles(block[0], block[2], block[1] - block[0],
                                   block[3] - block[2], factor=f, tile_shape=tile_shape,
                                   placement=placement)) for block in row]
            for row in _blocks(request)]  # the same for every group of directions
    # values per layer a task holds: its block's surface at the level read, and (radiance
    # tiles) every tile the block shows, whole
    ny, nx = request.shape
    texels = min(request.block, ny) * f * min(request.block, nx) * f
    if not compressed or from_sample:
        shown = max(len(codes) for row in grid for _, codes in row)
        texels += shown * tile_shape[0] * tile_shape[1]
    if from_sample:  # and the sample's values of the group's layers
        texels += int(np.prod(tileset.sample_shape))
    most = request.layers_per_task((1, texels), nc)
    for dirs, used, w in direction_groups(request.weights, most):
        layers = None if compressed else [request.layers[k] for k in used]
        u = u_rows[used] if compressed else None
        tiles = shared if compressed and not from_sample else {}
        sample = (dask.delayed(_sample_values, pure=True)(location(store), u, request.rank)
                  if from_sample else None)
        rows = []
        for row in grid:
            blocks = []
            for (y0, y1, x0, x1), codes in row:
                for c in codes:
                    if c in tiles:
                        continue
                    if from_sample:
                        tiles[c] = dask.delayed(_prescribed_tile, pure=True)(
                            location(store), int(order[c]), sample, len(used),
                            None if scale is None else scale[used])
                        read.add((int(order[c]), tuple(int(k) for k in used)))
                        continue
                    tiles[c] = dask.delayed(_tile_data, pure=True)(
                        location(store), int(order[c]), layers, request.rank, path)
                    read.add((int(order[c]), None if layers is None else tuple(layers)))
                block = dask.delayed(_surface, pure=True)(
                    {c: tiles[c] for c in codes}, y0, x0, y1 - y0, x1 - x0,
                    factor=f, placement=placement, u=None if from_sample else u, s=s,
                    transform=transform, weights=w,
                    scale=None if scale is None or from_sample else scale[used])
                blocks.append(da.from_delayed(block, (len(dirs), y1 - y0, x1 - x0, nc),
                                              dtype=np.float32))
            rows.append(blocks)
        parts.append(da.block([[[[b] for b in r] for r in rows]]))
    return (da.concatenate(parts, axis=0) if len(parts) > 1 else parts[0]), read


def direction_groups(weights, most: int) -> list[tuple[range, np.ndarray, np.ndarray]]:
    """Consecutive directions in groups whose distinct layers number at most ``most``.

    Returns ``(directions, layers, dense weights)`` per group: the group's rows of the CSR
    ``weights`` restricted to the layers they use (greedy, in order; a direction with more
    layers than ``most`` is a group of its own).
    """
    groups, start, layers = [], 0, set()
    bounds = weights.indptr
    for d in range(weights.shape[0]):
        mine = set(weights.indices[bounds[d]:bounds[d + 1]].tolist())
        if d > start and len(layers | mine) > most:
            groups.append(range(start, d))
            start, layers = d, set()
        layers |= mine
    groups.append(range(start, weights.shape[0]))
    out = []
    for dirs in groups:
        rows = weights[dirs.start:dirs.stop]
        used = np.unique(rows.indices)
        out.append((dirs, used, rows[:, used].toarray()))
    return out


def chunks_touched(shape, chunks, selection) -> int:
    """Storage chunks of an array that a selection (per axis: a slice or indices) touches."""
    total = 1
    for n, c, sel in zip(shape, chunks, selection, strict=True):
        if isinstance(sel, slice):
            start, stop, _ = sel.indices(n)
            total *= 0 if stop <= start else (stop - 1) // c - start // c + 1
        else:
            total *= len({i // c for i in sel})
    return total


def layer_chunks(layers: list[tuple[int, int]], light_chunk: int) -> int:
    """Distinct ``(view, light chunk)`` pairs the layers fall in."""
    return len({(v, li // light_chunk) for v, li in layers})


def total_chunks(shape, chunks) -> int:
    """Chunks of an array."""
    return math.prod(-(-n // c) for n, c in zip(shape, chunks, strict=True))


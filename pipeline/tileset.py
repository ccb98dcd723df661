"""Tile-set stores (quilting and the roller) and surfaces rendered from them on demand.

A tile-set store is a zarr v3 group holding

- ``radiance``: float32 ``(tile, view, light, y, x, channel)``, one chunk per tile and layer, so
  that rendering one layer reads nothing of the others; or, for a compressed source, ``U`` and
  ``S`` of the source with eigentextures per tile ``V`` ``(tile, y, x, component)`` (the
  prescription blends the log-domain eigentextures, so blended texels are weighted geometric
  means of the radiance they join);
- ``corners`` ``(tile, corner)``: the corner types (top-left, top-right, bottom-left,
  bottom-right) of each tile;
- ``prescription_index`` / ``prescription_weight`` ``(tile, pixel, term)``: each tile's
  prescription (:mod:`tasks.prescription`), so it can be applied again to other data;
- ``reference`` ``(sample_y, sample_x, reference_channel)``: the reference image it was planned on;
- the direction coordinates and ``channel`` labels of the source, and attrs ``btf_kind``
  (``tileset`` or ``compressed-tileset``), the planning parameters, seed and placements.

:func:`lazy_layer` is one layer of an unbounded surface covered by the tiles, as a dask array:
each block gathers from the tiles of that layer only (:func:`tasks.placement.gather`).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.errors import BTFError
from pipeline.store import DIRECTION_COORDS, RADIANCE, Directions, location, open_group
from tasks.placement import corner_code, gather, lattice_gather

KINDS = ("tileset", "compressed-tileset")
CORNERS = ("top_left", "top_right", "bottom_left", "bottom_right")


def create_tileset_store(path, *, directions: Directions, channels: tuple[str, ...],
                         tiles: int, tile_shape: tuple[int, int], terms: int,
                         reference: np.ndarray, attrs: dict[str, Any], rank: int | None = None):
    """Create an empty tile-set store (``rank``: a compressed one); returns the zarr group."""
    import zarr
    from zarr.codecs import BloscCodec

    compressors = BloscCodec(cname="lz4", clevel=5, shuffle="shuffle")
    group = zarr.open_group(location(path), mode="w-", zarr_format=3)
    group.attrs.update({**attrs, "btf_kind": KINDS[rank is not None]})
    ty, tx = tile_shape
    nv, nl, nc = directions.theta_view.size, directions.theta_light.size, len(channels)
    if rank is None:
        rad = group.create_array(
            RADIANCE, shape=(tiles, nv, nl, ty, tx, nc), chunks=(1, 1, 1, ty, tx, nc),
            dtype="float32", dimension_names=("tile", "view", "light", "y", "x", "channel"),
            compressors=compressors, fill_value=np.nan)
        rad.attrs["coordinates"] = " ".join(DIRECTION_COORDS)
    else:
        group.create_array("U", shape=(nv, nl, nc, rank), dtype="float32",
                           dimension_names=("view", "light", "channel", "component"),
                           compressors=compressors)
        group.create_array("S", shape=(rank,), dtype="float32", dimension_names=("component",))
        group.create_array("V", shape=(tiles, ty, tx, rank), chunks=(1, ty, tx, rank),
                           dtype="float32", dimension_names=("tile", "y", "x", "component"),
                           compressors=compressors)
    pixels = ty * tx
    group.create_array("corners", shape=(tiles, 4), dtype="int64",
                       dimension_names=("tile", "corner"))
    group.create_array("prescription_index", shape=(tiles, pixels, terms),
                       chunks=(1, pixels, terms), dtype="int32",
                       dimension_names=("tile", "pixel", "term"), compressors=compressors)
    group.create_array("prescription_weight", shape=(tiles, pixels, terms),
                       chunks=(1, pixels, terms), dtype="float32",
                       dimension_names=("tile", "pixel", "term"), compressors=compressors)
    ref = group.create_array("reference", shape=reference.shape, dtype="float32",
                             dimension_names=("sample_y", "sample_x", "reference_channel"),
                             compressors=compressors)
    ref[...] = reference
    for name, dim in DIRECTION_COORDS.items():
        values = getattr(directions, name)
        coord = group.create_array(name, shape=values.shape, dtype="float64",
                                   dimension_names=(dim,), compressors=None)
        coord[:] = values
    labels = group.create_array("channel", shape=(nc,), dtype=str,
                                dimension_names=("channel",), compressors=None)
    labels[:] = np.array(channels)
    names = group.create_array("corner", shape=(4,), dtype=str, dimension_names=("corner",),
                               compressors=None)
    names[:] = np.array(CORNERS)
    return group


def open_layers(path: str | Path):
    """A Dataset with a (lazy) ``radiance``, from a radiance or a compressed store."""
    from pipeline.compressed import KIND as COMPRESSED
    from pipeline.compressed import open_compressed
    from pipeline.store import open_radiance

    group = open_group(path)
    if group.attrs.get("btf_kind") == COMPRESSED:
        return open_compressed(path)
    return open_radiance(path)


APPLY_BUDGET = 128 * 2**20  # bytes of layers one application task holds at a time
# A compressed source's task holds a band of its eigentextures and its tiles' results: half each.
BAND_BUDGET = APPLY_BUDGET // 2
RESULT_BUDGET = APPLY_BUDGET // 2


def _apply_block(store: str, out: str, view: int, light0: int, light1: int, matrices,
                 tile_shape) -> None:
    """Apply every tile's prescription to a block of lights, a few whole layers at a time.

    ``P`` may take any texel of the sample, so a whole layer is the smallest unit read; when
    fewer layers than a stored chunk holds fit in the budget, that chunk is read (and
    decompressed) once per group of layers.
    """
    import zarr

    from tasks.prescription import apply

    source = zarr.open_array(store, path=RADIANCE, mode="r")
    target = zarr.open_array(out, path=RADIANCE, mode="r+")
    ny, nx, nc = source.shape[-3:]
    layer = 4 * nc * (ny * nx + tile_shape[0] * tile_shape[1])  # a source and a tile layer
    step = max(1, min(light1 - light0, APPLY_BUDGET // layer))
    for l0 in range(light0, light1, step):
        l1 = min(l0 + step, light1)
        layers = source[view, l0:l1]
        result = np.empty((l1 - l0, *tile_shape, nc), np.float32)  # reused by every tile
        for t, matrix in enumerate(matrices):
            target[t, view, l0:l1] = apply(matrix, layers, output=tile_shape, out=result)


def _apply_eigentextures(store: str, out: str, tiles: Sequence[int], matrices) -> None:
    """Some tiles' eigentextures, reading the source's once, in bands of whole chunk rows.

    The bands are as many chunk rows as fit in :data:`BAND_BUDGET` (at least one); every band
    serves all the task's tiles, whose results and CSC matrices (within :data:`RESULT_BUDGET`,
    see :func:`_tile_groups`) are held until the last band.
    """
    import zarr

    from tasks.prescription import apply_texel_rows

    source = zarr.open_array(store, path="V", mode="r")
    target = zarr.open_array(out, path="V", mode="r+")
    ny, nx, rank = source.shape
    columns = [matrices[t].tocsc() for t in tiles]
    results = [np.zeros((c.shape[0], rank), np.float32) for c in columns]
    band = source.chunks[0] * max(1, BAND_BUDGET // (4 * rank * nx * source.chunks[0]))
    for y0 in range(0, ny, band):
        texels = source[y0 : y0 + band]
        for matrix, result in zip(columns, results, strict=True):
            apply_texel_rows(matrix, texels, y0 * nx, result)
    for t, result in zip(tiles, results, strict=True):
        target[t] = result.reshape(target.shape[1:])


def _tile_groups(tiles: int, tile_bytes: int, parallelism: int) -> list[range]:
    """Tiles split evenly into groups for :func:`_apply_eigentextures`, each reading V once.

    As few groups as keep every one of ``parallelism`` tasks busy (one per tile at most) and
    fit each group's ``tile_bytes`` per tile in :data:`RESULT_BUDGET`.
    """
    per_group = max(1, RESULT_BUDGET // max(1, tile_bytes))
    groups = max(min(tiles, parallelism), -(-tiles // per_group))
    return [range(int(g[0]), int(g[-1]) + 1)
            for g in np.array_split(np.arange(tiles), groups)]


def write_tileset(store: str, tmp, *, group, index: Sequence[np.ndarray],
                  weight: Sequence[np.ndarray],
                  tile_shape: tuple[int, int], reference: np.ndarray, corners: np.ndarray,
                  attrs: dict[str, Any], session, label: str, output,
                  arrays: dict[str, np.ndarray] | None = None) -> None:
    """Write a tile set into ``tmp``: the prescriptions, and every layer of ``store``.

    The prescriptions (per tile, ``(pixel, term)``) are applied to every layer of ``store``, or
    to its eigentextures (then the tile set is compressed).
    """
    import dask

    from pipeline.compressed import KIND as COMPRESSED
    from tasks.prescription import to_csr

    compressed = group.attrs.get("btf_kind") == COMPRESSED
    d = Directions.of(open_layers(store))
    channels = tuple(str(c) for c in group["channel"][:])
    samples = int(np.prod(reference.shape[:2]))
    matrices = [to_csr(i, w, samples) for i, w in zip(index, weight, strict=True)]
    attrs = {**attrs, "source_store": store, "tile_shape": list(tile_shape),
             "sample_shape": list(reference.shape[:2]),
             "source_btf_kind": group.attrs.get("source_btf_kind") if compressed
             else group.attrs.get("btf_kind")}
    if compressed:
        attrs["transform"] = group.attrs["transform"]
    out = create_tileset_store(tmp, directions=d, channels=channels, tiles=len(matrices),
                               tile_shape=tile_shape, terms=index[0].shape[-1],
                               reference=reference, attrs=attrs,
                               rank=group["S"].shape[0] if compressed else None)
    out["corners"][...] = corners
    for t in range(len(matrices)):
        out["prescription_index"][t] = index[t].astype(np.int32)
        out["prescription_weight"][t] = weight[t]
    for name, values in (arrays or {}).items():
        out.create_array(name, shape=values.shape, dtype=values.dtype, compressors=None)[...] = (
            values)
    shared = session.share(matrices)
    if compressed:
        out["U"][...] = group["U"][...]
        out["S"][...] = group["S"][...]
        texels, terms = tile_shape[0] * tile_shape[1], index[0].shape[-1]
        # a result, and a CSC matrix (values and row indices per term, a pointer per column)
        tile_bytes = 4 * texels * group["S"].shape[0] + 8 * texels * terms + 4 * (samples + 1)
        writes = [dask.delayed(_apply_eigentextures)(location(store), location(tmp), tiles,
                                                     shared)
                  for tiles in _tile_groups(len(matrices), tile_bytes, session.parallelism)]
    else:
        nv, nl = d.theta_view.size, d.theta_light.size
        block = group[RADIANCE].chunks[1]
        writes = [dask.delayed(_apply_block)(location(store), location(tmp), v, l0,
                                             min(l0 + block, nl), shared, tile_shape)
                  for v in range(nv) for l0 in range(0, nl, block)]
    session.log(f"{label}: applying {len(matrices)} prescription(s) to "
                f"{'the eigentextures in ' if compressed else ''}{len(writes)} "
                f"{'group(s) of tiles' if compressed else 'blocks of layers'}"
                f" -> {output}")
    session.compute(*writes)


def open_tileset(path: str | Path):
    """Open a tile-set store (zarr group), checking its kind and variables."""
    group = open_group(path)
    kind = group.attrs.get("btf_kind")
    if kind not in KINDS:
        raise BTFError(f"{path}: not a tile-set store (btf_kind is {kind!r}; make one with btf "
                       "quilt or btf roller)")
    needed = [RADIANCE] if kind == "tileset" else ["U", "S", "V"]
    for name in (*needed, "corners", "prescription_index", "prescription_weight"):
        if name not in group.array_keys():
            raise BTFError(f"{path}: variable {name!r} is missing")
    return group


def _layer_tiles(store: str, view: int, light: int, order: np.ndarray | None = None
                 ) -> np.ndarray:
    """The tiles of one layer, ``(tiles, ty, tx, channel)`` float32, in ``order``.

    Reads only that layer.
    """
    import zarr

    group = zarr.open_group(store, mode="r")
    if group.attrs["btf_kind"] == "tileset":
        tiles = group[RADIANCE][:, view, light]
    else:
        from tasks.svd import reconstruct_layers

        u = group["U"][view, light]  # (channel, component)
        s = group["S"][:]
        eps = float(group.attrs["transform"]["eps"])
        tiles = np.stack([reconstruct_layers(u, s, v, eps=eps) for v in group["V"]])
    if order is None or np.array_equal(order, np.arange(len(tiles))):
        return tiles
    return tiles[order]


def corner_order(path, corners: np.ndarray, types: int) -> np.ndarray:
    """Stored tile of each corner combination, in :func:`tasks.placement.cell_tiles` order.

    Every combination of ``types`` corner types must be stored exactly once.
    """
    corners = np.asarray(corners)
    codes = corner_code(*corners.T, corners=types)
    if (corners.min(initial=0) < 0 or corners.max(initial=0) >= types
            or sorted(codes.tolist()) != list(range(types**4))):
        raise BTFError(f"{path}: variable 'corners' does not hold every combination of "
                       f"{types} corner types exactly once")
    return np.argsort(codes)


def _surface_block(tiles, block_info=None, *, origin, seed, corners):
    (y0, y1), (x0, x1), _ = block_info[None]["array-location"]
    return gather(tiles, origin[0] + y0, origin[1] + x0, y1 - y0, x1 - x0, seed=seed,
                  corners=corners)


def _lattice_block(tiles, block_info=None, *, origin, seed, hnf, basis, representative):
    (y0, y1), (x0, x1), _ = block_info[None]["array-location"]
    return lattice_gather(tiles, origin[0] + y0, origin[1] + x0, y1 - y0, x1 - x0, hnf=hnf,
                          basis=basis, representative=representative, seed=seed)


def stored_seed(group) -> int:
    """The placement seed recorded with a tile set (older quilt sets: the planning seed)."""
    attrs = group.attrs
    return int(attrs.get("seed", (attrs.get("quilt") or {}).get("seed", 0)))


def lazy_layer(path: str | Path, *, view: int, light: int, size: tuple[int, int],
               origin: tuple[int, int] = (0, 0), seed: int | None = None, chunk: int = 2048):
    """One layer of the surface tiled by a tile set, as a lazy dask array ``(y, x, channel)``.

    The tiles of the layer are read once (one task) and every block of the surface is a pure
    gather from them: quilting's tiles placed by the corner types a hash of the lattice
    vertices and ``seed`` gives, the roller's on their (possibly sheared) lattice, chosen per
    cell by a hash of the cell and ``seed``. ``seed=None``: the seed stored with the tile set.
    """
    import dask
    import dask.array as da

    group = open_tileset(path)
    nv, nl = group["theta_view"].shape[0], group["theta_light"].shape[0]
    if not 0 <= view < nv:
        raise BTFError(f"{path}: --view {view} is out of range (the tile set has {nv} views)")
    if not 0 <= light < nl:
        raise BTFError(f"{path}: --light {light} is out of range (the tile set has {nl} lights)")
    if seed is None:
        seed = stored_seed(group)
    channels = group["channel"].shape[0]
    lattice = group.attrs.get("placement") == "lattice"
    order = None if lattice else corner_order(path, group["corners"][...],
                                              int(group.attrs["corner_types"]))
    tiles = dask.delayed(_layer_tiles, pure=True)(location(path), view, light, order)
    h, w = size
    chunks = (tuple(min(chunk, h - i) for i in range(0, h, chunk)),
              tuple(min(chunk, w - i) for i in range(0, w, chunk)), (channels,))
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

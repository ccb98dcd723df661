"""Applying a tile set's prescriptions to every layer, or to the eigentextures (papers 003, 004).

A prescription ``P`` may take any texel of the sample, so a whole layer is the smallest unit a
task reads. For a radiance source, one task per (view, block of stored lights) reads a few whole
layers at a time within :data:`APPLY_BUDGET` and writes every tile's layers. For a compressed
source, the tiles are split into groups (:func:`tile_groups`), one task per group, each reading
the eigentextures ``V`` once in bands of whole chunk rows and accumulating its tiles' results.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from pipeline import storage
from pipeline.stores.base import RADIANCE, location

APPLY_BUDGET = 128 * 2**20  # bytes of layers one application task holds at a time
# A compressed source's task holds a band of its eigentextures and its tiles' results: half each.
BAND_BUDGET = APPLY_BUDGET // 2
RESULT_BUDGET = APPLY_BUDGET // 2


def _apply_block(store: str, out: str, view: int, light0: int, light1: int, matrices,
                 tile_shape) -> None:
    """Apply every tile's prescription to a block of lights, a few whole layers at a time.

    When fewer layers than a stored chunk holds fit in the budget, that chunk is read (and
    decompressed) once per group of layers.
    """
    import zarr

    from tasks.prescription import apply

    source = zarr.open_array(storage.store(store), path=RADIANCE, mode="r")
    target = zarr.open_array(storage.store(out), path=RADIANCE, mode="r+")
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
    see :func:`tile_groups`) are held until the last band.
    """
    import zarr

    from tasks.prescription import apply_texel_rows

    source = zarr.open_array(storage.store(store), path="V", mode="r")
    target = zarr.open_array(storage.store(out), path="V", mode="r+")
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


def tile_groups(tiles: int, tile_bytes: int, parallelism: int) -> list[range]:
    """Tiles split evenly into groups, each reading the eigentextures once.

    As few groups as keep every one of ``parallelism`` tasks busy (one per tile at most) and
    fit each group's ``tile_bytes`` per tile in :data:`RESULT_BUDGET`.
    """
    per_group = max(1, RESULT_BUDGET // max(1, tile_bytes))
    groups = max(min(tiles, parallelism), -(-tiles // per_group))
    return [range(int(g[0]), int(g[-1]) + 1)
            for g in np.array_split(np.arange(tiles), groups)]


def layer_writes(store: str, out: str, matrices, *, shape: tuple[int, ...], dir_chunk: int,
                 tile_shape: tuple[int, int], needs=None) -> list:
    """Delayed tasks writing every tile's layers of a radiance source of ``shape``.

    ``matrices`` is a handle of the tiles' CSR prescriptions (:meth:`Session.share`). With
    ``needs`` (:class:`pipeline.scene_needs.Needs`), only blocks of lights holding a layer
    it needs.
    """
    import dask

    nv, nl = shape[:2]
    return [dask.delayed(_apply_block)(location(store), location(out), v, l0,
                                       min(l0 + dir_chunk, nl), matrices, tile_shape)
            for v in range(nv) for l0 in range(0, nl, dir_chunk)
            if needs is None or needs.keeps(v, range(l0, min(l0 + dir_chunk, nl)))]


def eigentexture_writes(store: str, out: str, matrices, *, tiles: int, tile_bytes: int,
                        parallelism: int) -> list:
    """Delayed tasks writing every tile's eigentextures of a compressed source."""
    import dask

    return [dask.delayed(_apply_eigentextures)(location(store), location(out), group, matrices)
            for group in tile_groups(tiles, tile_bytes, parallelism)]


def apply_tileset(source: str, out, tiles, *, source_group, share, parallelism: int,
                  needs=None) -> tuple[list, str]:
    """Delayed tasks filling a tile-set store at ``out`` from ``source``, and what they do.

    ``tiles`` is the :class:`pipeline.stores.tileset.TileSet` the store was created for;
    ``share`` makes the prescriptions a task argument every task reads
    (:meth:`pipeline.session.Session.share`); ``parallelism`` is how many tasks run at once.
    """
    matrices = tiles.matrices()
    handle = share(matrices)
    if source_group.attrs.get("btf_kind") == "compressed":
        rank = source_group["S"].shape[0]
        texels, terms = tiles.tile_shape[0] * tiles.tile_shape[1], tiles.index[0].shape[-1]
        # a result, and a CSC matrix (values and row indices per term, a pointer per column)
        tile_bytes = 4 * texels * rank + 8 * texels * terms + 4 * (tiles.samples + 1)
        writes = eigentexture_writes(source, out, handle, tiles=len(matrices),
                                     tile_bytes=tile_bytes, parallelism=parallelism)
        return writes, (f"{len(matrices)} prescription(s) to the eigentextures in "
                        f"{len(writes)} group(s) of tiles")
    radiance = source_group[RADIANCE]
    writes = layer_writes(source, out, handle, shape=radiance.shape,
                          dir_chunk=radiance.chunks[1], tile_shape=tiles.tile_shape,
                          needs=needs)
    return writes, f"{len(matrices)} prescription(s) to {len(writes)} blocks of layers"


def write_tileset(tiles, out: str | Path, *, source: str, session, label: str,
                  overwrite: bool, needs=None, record: dict | None = None) -> Path:
    """Write a tile-set store for ``tiles`` planned on ``source``: all or nothing at ``out``.

    The one place both tile-set stages (quilting, the roller) end: the store is created
    (:func:`pipeline.stores.tileset.write_tileset_store`) in a partial output, filled by
    :func:`apply_tileset` on the session's scheduler, and moved to ``out``. ``tiles`` is the
    :class:`~pipeline.stores.tileset.TileSet`, or a function that plans it, called inside the
    partial output, with ``record`` the stage's provenance. A run killed after its plan was
    stored resumes with it (the plan is read back, not made again) and with the groups of
    writes it had not finished (:mod:`pipeline.resume`), unless a chunk the killed run wrote
    fails its checksum: then it starts over.
    """
    from pipeline.atomic import atomic_output
    from pipeline.resume import Progress
    from pipeline.stores.base import open_group
    from pipeline.stores.tileset import read_plan, write_tileset_store

    group = open_group(source)
    with atomic_output(out, directory=True, overwrite=overwrite,
                       resume=tiles.attrs.get("provenance") if record is None else record
                       ) as tmp:
        progress = Progress(tmp)
        progress.distrust_damaged(lambda line: session.log(f"{label}: {line}"))
        if callable(tiles) and progress.created:
            session.log(f"{label}: resuming: the plan the killed run stored is kept")
            tiles = read_plan(tmp)
        elif callable(tiles):
            tiles = tiles()
        progress.skeleton(lambda: write_tileset_store(tmp, tiles, source=source,
                                                      source_group=group))
        writes, what = apply_tileset(source, tmp, tiles, source_group=group,
                                     share=session.share, parallelism=session.parallelism,
                                     needs=needs)
        # how the writes are grouped depends on the session (tile_groups): a rerun with
        # other workers groups them otherwise, and then keeps nothing of the killed run's
        grouping = f"{len(writes)}x{session.parallelism}"
        todo, done = progress.pending((f"write-{grouping}-{i}", w)
                                      for i, w in enumerate(writes))
        session.log(f"{label}: applying {what} -> {out}"
                    + (f" (resuming: {done} already written)" if done else ""))
        session.compute(*todo)
    return Path(out)

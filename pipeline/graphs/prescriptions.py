"""Applying a tile set's prescriptions to every layer, or to the eigentextures (papers 003, 004).

A prescription ``P`` may take any texel of the sample, so a whole layer is the smallest unit a
task reads. For a radiance source, one task per (view, block of stored lights) reads a few whole
layers at a time within :data:`APPLY_BUDGET` and writes every tile's layers. A compressed
source's tile set keeps the prescriptions and a copy of the sample's eigentextures ``V``
(:func:`sample_copies`); its tiles are computed where they are read
(:mod:`pipeline.stores.tileset`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline import chunk_io, storage
from pipeline.stores.base import RADIANCE, location
from pipeline.stores.radiance import as_float32, stored

APPLY_BUDGET = 128 * 2**20  # bytes of layers one application task holds at a time


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
        layers = as_float32(chunk_io.read(source, (view, slice(l0, l1))))
        result = np.empty((l1 - l0, *tile_shape, nc), np.float32)  # reused by every tile
        for t, matrix in enumerate(matrices):
            chunk_io.write(target, (t, view, slice(l0, l1)), stored(
                apply(matrix, layers, output=tile_shape, out=result), target.dtype, out))


def _copy_band(store: str, out: str, y0: int, y1: int) -> None:
    import zarr

    source = zarr.open_array(storage.store(store), path="V", mode="r")
    target = zarr.open_array(storage.store(out), path="V", mode="r+")
    target[y0:y1] = source[y0:y1]


def sample_copies(store: str, out: str) -> list:
    """Delayed tasks copying a compressed source's ``V`` into a tile set, a chunk row each.

    The tile set's ``V`` has the source's chunks (:func:`pipeline.stores.tileset.
    create_tileset_store`), so each task writes whole chunks of its own.
    """
    import dask
    import zarr

    v = zarr.open_array(storage.store(location(store)), path="V", mode="r")
    step = v.chunks[0]
    return [dask.delayed(_copy_band)(location(store), location(out), y0,
                                     min(y0 + step, v.shape[0]))
            for y0 in range(0, v.shape[0], step)]


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


def apply_tileset(source, out, tiles, *, share, needs=None) -> tuple[list, str]:
    """Delayed tasks filling a tile-set store at ``out`` from ``source``, and what they do.

    ``source`` is the sample's store handle; ``tiles`` the
    :class:`pipeline.stores.tileset.TileSet` the store was created for; ``share`` makes the
    prescriptions a task argument every task reads (:meth:`pipeline.session.Session.share`).
    """
    from pipeline.stores import CompressedStore

    if isinstance(source, CompressedStore):
        # the tiles are their prescriptions applied to the sample's eigentextures, computed
        # where they are read (pipeline.stores.tileset.tile_values): only V is copied
        writes = sample_copies(source.location, out)
        return writes, (f"{len(tiles.index)} prescription(s) kept with the sample's "
                        f"eigentextures ({len(writes)} band(s) of V copied)")
    matrices = tiles.matrices()
    handle = share(matrices)
    radiance = source[RADIANCE]
    writes = layer_writes(source.location, out, handle, shape=radiance.shape,
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
    from pipeline.stores import CompressedStore, RadianceStore, open_store
    from pipeline.stores.tileset import read_plan, write_tileset_store

    sample = open_store(source, RadianceStore, CompressedStore)
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
        progress.skeleton(lambda: write_tileset_store(tmp, tiles, source=sample))
        writes, what = apply_tileset(sample, tmp, tiles, share=session.share, needs=needs)
        # the writes' names carry the session's parallelism: a rerun with other workers keeps
        # nothing of the killed run's
        grouping = f"{len(writes)}x{session.parallelism}"
        todo, done = progress.pending((f"write-{grouping}-{i}", w)
                                      for i, w in enumerate(writes))
        session.log(f"{label}: applying {what} -> {out}"
                    + (f" (resuming: {done} already written)" if done else ""))
        session.compute(*todo)
    return Path(out)

"""Applying a tile set's prescriptions to every layer, or to the eigentextures (papers 003, 004).

A prescription ``P`` may take any texel of the sample, so a whole layer is the smallest unit a
task reads. For a radiance source, one task per view and block of stored lights (or part of
one, :func:`light_blocks`) reads a few whole layers at a time within :data:`APPLY_BUDGET` and
writes every tile's layers. A compressed source's tile set keeps the prescriptions and a copy
of the sample's eigentextures ``V`` (:func:`sample_copies`); its tiles are computed where they
are read (:mod:`pipeline.stores.tileset`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline import chunk_io, storage
from pipeline.stores.base import RADIANCE, location
from pipeline.stores.radiance import as_float32, stored

APPLY_BUDGET = 128 * 2**20  # bytes of layers one application task holds at a time
PAIR = 2  # layers applied at once (the product works on two RGB layers in one pass)
TASKS_PER_WORKER = 4  # blocks of lights are split until there are this many tasks a worker


def _apply_block(store: str, out: str, view: int, light0: int, light1: int, matrices,
                 tile_shape, compiled: bool = True) -> None:
    """Apply every tile's prescription to a block of lights, a few whole layers at a time.

    When fewer layers than a stored chunk holds fit in the budget, that chunk is read (and
    decompressed) once per group of layers. The results are made :data:`PAIR` layers at a
    time into one buffer, written as soon as they are made: a buffer of the whole group (110
    MB for ten 960^2 layers) was mapped afresh for every group (see
    :func:`pipeline.session.steady_memory`), and its page faults cost six times the products.
    ``compiled``: by numba's loop or scipy's (:func:`tasks.prescription.compiled_pays`).
    """
    import zarr

    from tasks.prescription import apply

    source = zarr.open_array(storage.store(store), path=RADIANCE, mode="r")
    target = zarr.open_array(storage.store(out), path=RADIANCE, mode="r+")
    ny, nx, nc = source.shape[-3:]
    layer = 4 * nc * (ny * nx + tile_shape[0] * tile_shape[1])  # a source and a tile layer
    step = max(1, min(light1 - light0, APPLY_BUDGET // layer))
    result = np.empty((min(PAIR, light1 - light0), *tile_shape, nc), np.float32)  # reused
    for l0 in range(light0, light1, step):
        l1 = min(l0 + step, light1)
        layers = as_float32(chunk_io.read(source, (view, slice(l0, l1))))
        for p0 in range(0, l1 - l0, PAIR):
            pair = layers[p0:p0 + PAIR]
            made = result[:len(pair)]
            for t, matrix in enumerate(matrices):
                chunk_io.write(target, (t, view, slice(l0 + p0, l0 + p0 + len(pair))),
                               stored(apply(matrix, pair, output=tile_shape, out=made,
                                            compiled=compiled), target.dtype, out))


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


def light_blocks(nv: int, nl: int, dir_chunk: int, *, tasks: int = 1,
                 needs=None) -> list[tuple[int, int, int]]:
    """``(view, light0, light1)`` of the application tasks of ``nv`` views of ``nl`` lights.

    A task takes a stored block of ``dir_chunk`` lights, or a part of one while there are
    fewer than ``tasks`` tasks (halved down to :data:`PAIR` lights; each part reads its block
    again): three blocks on two threads left one thread idle a third of the time. With
    ``needs`` (:class:`pipeline.scene_needs.Needs`), only parts holding a layer it needs.
    """
    def kept(blocks):
        return [(v, l0, l1) for v, l0, l1 in blocks
                if needs is None or needs.keeps(v, range(l0, l1))]

    blocks = kept((v, l0, min(l0 + dir_chunk, nl)) for v in range(nv)
                  for l0 in range(0, nl, dir_chunk))
    while len(blocks) < tasks and any(l1 - l0 > PAIR for _, l0, l1 in blocks):
        parts = []
        for v, l0, l1 in blocks:
            middle = l0 + max(PAIR, (l1 - l0) // (2 * PAIR) * PAIR)  # whole pairs first
            parts += [(v, l0, middle), (v, middle, l1)] if middle < l1 else [(v, l0, l1)]
        blocks = kept(parts)
    return blocks


def layer_writes(store: str, out: str, matrices, *, shape: tuple[int, ...], dir_chunk: int,
                 tile_shape: tuple[int, int], tiles: int, needs=None, tasks: int = 1) -> list:
    """Delayed tasks writing every tile's layers of a radiance source of ``shape``.

    ``matrices`` is a handle of the ``tiles`` tiles' CSR prescriptions
    (:meth:`Session.share`); the tasks' lights are :func:`light_blocks`'s. The product is
    numba's or scipy's as the values written say (:func:`tasks.prescription.compiled_pays`).
    """
    import dask

    from tasks.prescription import compiled_pays

    blocks = light_blocks(*shape[:2], dir_chunk, tasks=tasks, needs=needs)
    values = tiles * sum(l1 - l0 for _, l0, l1 in blocks) * tile_shape[0] * tile_shape[1]
    compiled = compiled_pays(values * shape[-1])
    return [dask.delayed(_apply_block)(location(store), location(out), v, l0, l1, matrices,
                                       tile_shape, compiled)
            for v, l0, l1 in blocks]


def apply_tileset(source, out, tiles, *, share, needs=None, parallelism: int = 1
                  ) -> tuple[list, str]:
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
                          tiles=len(matrices), needs=needs, tasks=TASKS_PER_WORKER * parallelism)
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
        writes, what = apply_tileset(sample, tmp, tiles, share=session.share, needs=needs,
                                     parallelism=session.parallelism)
        # the writes' names carry the session's parallelism: a rerun with other workers keeps
        # nothing of the killed run's
        grouping = f"{len(writes)}x{session.parallelism}"
        todo, done = progress.pending((f"write-{grouping}-{i}", w)
                                      for i, w in enumerate(writes))
        session.log(f"{label}: applying {what} -> {out}"
                    + (f" (resuming: {done} already written)" if done else ""))
        session.compute(*todo)
    return Path(out)

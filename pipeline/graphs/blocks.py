"""The blocks tasks read and write: whole write units, about :data:`TASK_TEXELS` a side.

Tasks read and write blocks made of whole write units (the shard of a sharded array, else the
chunk), so no two tasks ever write the same file. Writing sharded arrays from many workers is
only safe shard by shard: two tasks writing parts of one shard both rewrite the whole shard
file, and one of them loses (measured here with zarr 3.1.6: a quarter to a half of the data
lost, silently). :func:`store_aligned` therefore refuses dask chunks that split a write unit.
"""

from __future__ import annotations

import functools

import numpy as np

TASK_TEXELS = 512  # texels per side of the block one task reads or writes
TASK_VALUES = 2**20  # values a grouped task block gathers across directions (4 MB of float32)


def write_unit(array) -> tuple[int, ...]:
    """The block shape that can be written independently: the shard, or else the chunk."""
    return tuple(array.shards or array.chunks)


def task_side(unit: int) -> int:
    """Texels per side of a task block over write units of ``unit`` texels a side.

    Whole units, about :data:`TASK_TEXELS` (one unit when a unit is larger; 0 for zarr's
    chunk 0 of an empty axis).
    """
    return unit * max(1, TASK_TEXELS // unit) if unit else 0


def task_block(array, *, grouped: bool = False) -> tuple[int, ...]:
    """The block one task reads or writes: whole write units, ~TASK_TEXELS per spatial side.

    ``grouped``: the other axes (directions, tiles) also gather whole write units, last axis
    first, up to :data:`TASK_VALUES` values a block, so that stores of small textures in small
    chunks are not cut into thousands of tiny tasks. Only for work that is the same whatever
    the grouping (per-texel means, copies): the blocks of a seeded or summed computation are
    part of its result.
    """
    dims = array.metadata.dimension_names or (None,) * array.ndim
    block = [task_side(unit) if dim in ("y", "x") else unit
             for unit, dim in zip(write_unit(array), dims, strict=True)]
    if grouped:
        for axis in reversed(range(len(block))):
            if dims[axis] in ("y", "x"):
                continue
            others = int(np.prod([min(b, n) for i, (b, n) in enumerate(zip(
                block, array.shape, strict=True)) if i != axis]))
            unit, size = block[axis], array.shape[axis]
            whole = -(-size // unit) * unit if unit else 0  # the axis in whole units
            block[axis] = whole if others * size <= TASK_VALUES else \
                min(whole, unit * max(1, TASK_VALUES // (others * unit)))
    return tuple(block)


def aligned_chunks(array, *, grouped: bool = False) -> tuple[tuple[int, ...], ...]:
    """Dask chunks that cover ``array`` in task blocks (see :func:`task_block`).

    As ``dask.array.core.normalize_chunks`` gives them (whole blocks, then the rest; ``(0,)``
    along an empty axis), without importing ``dask.array`` (0.44 s of a ``btf ingest``).
    """
    def cover(size: int, block: int) -> tuple[int, ...]:
        if not size:  # an empty axis (its block may be 0: a grouped one, zarr's chunk)
            return (0,)
        whole, rest = divmod(size, block)
        return (block,) * whole + ((rest,) if rest else ())

    return tuple(cover(int(n), int(b)) for n, b in zip(array.shape, task_block(
        array, grouped=grouped), strict=True))


def read_chunks(group, name: str) -> dict[str, int]:
    """Dask chunk size per dimension for reading variable ``name``: its task blocks."""
    array = group[name]
    dims = array.metadata.dimension_names or ()
    return dict(zip(dims, task_block(array), strict=True))


def store_aligned(sources: list, targets: list, *, progress=None, keep=None):
    """A delayed write of dask arrays into zarr arrays, refused unless aligned to write units.

    Every dask chunk boundary must fall on a shard boundary (or chunk boundary for unsharded
    arrays), so no two tasks ever write into the same shard or chunk. With ``progress`` (a
    :class:`pipeline.resume.Progress`) every block is a unit of work of its own: blocks an
    earlier, killed run finished are skipped, and each block marks itself done once written.
    With ``keep`` (``keep(region) -> bool``, region a tuple of slices of the target), only the
    blocks it keeps are computed and written.
    """
    from dask.base import tokenize

    for source, target in zip(sources, targets, strict=True):
        _refuse_split(source.chunks, target, "dask chunks")
    sources = [_in_type_of(source, target) for source, target in zip(sources, targets,
                                                                      strict=True)]
    units, regions = [], {}
    # each block written by the task that computes it (as da.store does; here in the task's
    # own thread where it can, see pipeline.chunk_io), not by a task of
    # its own: the processes scheduler would move every block to the client and out again
    # and each marks itself done right after its write: a marker of its own, in a task of its
    # own, ran when dask's order reached it, often long after (a kill at 60% of a generate
    # found 416 chunks written and 42 blocks marked)
    writes = [source.map_blocks(_write_here, target=target, progress=progress,
                                chunks=(1,) * source.ndim, dtype=np.int8,
                                meta=np.empty((0,) * source.ndim, np.int8))
              for source, target in zip(sources, targets, strict=True)]
    graph = _optimized_together(writes)
    token = tokenize([w.name for w in writes])
    for source, written, target in zip(sources, writes, targets, strict=True):
        starts = [np.cumsum((0, *c)) for c in source.chunks]
        for index in np.ndindex(written.numblocks):
            region = tuple(slice(int(s[i]), int(s[i + 1])) for s, i in zip(starts, index,
                                                                           strict=True))
            if keep is not None and not keep(region):
                continue
            name = f"{target.path}/{'.'.join(map(str, index))}"
            regions[name] = (target, region)
            units.append((name, (written.name, *index)))
    return _pending(graph, token, units, regions, progress)


def store_blocks(target, chunks: tuple[tuple[int, ...], ...], make, *, progress=None):
    """:func:`store_aligned` for blocks made by plain tasks, without a dask array.

    ``chunks``: the blocks' sizes per axis (:func:`aligned_chunks`: whole write units);
    ``make(index)``: a function of no arguments making block ``index`` of that grid, in
    ``target``'s dtype and block shape. Each block is one task, which makes, writes and (with
    ``progress``) marks it, named as :func:`store_aligned` names it, so a run killed under
    either resumes under the other. Building a dask array of such blocks imported
    ``dask.array`` (0.44 s of a ``btf ingest``) and concatenated them into a graph only to
    cut it into the same blocks again.
    """
    import uuid

    _refuse_split(chunks, target, "blocks")
    if tuple(map(sum, chunks)) != tuple(target.shape):
        raise ValueError(f"blocks {chunks} do not cover {target.path!r} of {target.shape}")
    token = uuid.uuid4().hex
    name = f"store-blocks-{token}"
    starts = [np.cumsum((0, *c)) for c in chunks]
    graph, units, regions = {}, [], {}
    for index in np.ndindex(*map(len, chunks)):
        region = tuple(slice(int(s[i]), int(s[i + 1])) for s, i in zip(starts, index,
                                                                       strict=True))
        unit = f"{target.path}/{'.'.join(map(str, index))}"
        key = (name, *index)
        graph[key] = (functools.partial(_make_here, make(index), target, region,
                                        unit if progress is not None else None, progress),)
        regions[unit] = (target, region)
        units.append((unit, key))
    return _pending(graph, token, units, regions, progress)


def _refuse_split(chunks: tuple[tuple[int, ...], ...], target, what: str) -> None:
    """Refuse blocks of ``chunks`` that split a write unit of ``target`` (see the module)."""
    for dim, (sizes, unit) in enumerate(zip(chunks, write_unit(target), strict=True)):
        if np.any(np.cumsum(sizes)[:-1] % unit):
            raise ValueError(f"{what} {sizes} of axis {dim} split write units of {unit} in "
                             f"{target.path!r}: concurrent writes would lose data")


def _make_here(make, target, region: tuple[slice, ...], unit: str | None, progress) -> int:
    """A block of :func:`store_blocks` made, written and marked done (its unit's marker).

    A block of another type or shape than its place is refused: a cast would let values
    overflow a float16 store unseen (:func:`pipeline.stores.radiance.stored` refuses them),
    and a smaller block would be broadcast over its place.
    """
    block = make()
    shape = tuple(r.stop - r.start for r in region)
    if block.dtype != target.dtype or block.shape != shape:
        raise ValueError(f"a block of {block.dtype} {block.shape} for {shape} of "
                         f"{target.path!r} ({target.dtype})")
    _write_block(block, target, region)
    if unit is not None:
        from pipeline import resume

        resume.mark_done(np.zeros((1,) * len(region), np.int8), progress.marker(unit),
                         logged=True)
    return 1


def _pending(graph, token: str, units: list, regions: dict, progress):
    """The write of every unit, or with ``progress`` of those a killed run did not finish.

    The units a killed run finished are kept. Those it finished on this machine since it
    last started need no check (:meth:`~pipeline.resume.Progress.vouched`); the others (a
    crash of the machine, another machine) are checked (:func:`_intact`) by tasks of the same
    graph, alongside the units left: a check run first held every resumed run up (4.5 s of a
    24 s rerun of a 2048^2 reconstruct whose store had left the page cache). A unit that
    fails is made again by the task that checked it (:func:`_kept_or_made`).
    """
    if progress is None:
        return _gathered(graph, token, [key for _, key in units])
    kept = set(progress.finished(regions))
    keys = [key for name, key in units if name not in kept]
    kept -= set(progress.vouched(kept))  # written before a kill, on this machine: in its cache
    if kept:
        graph = dict(graph)
        made = _Units(graph)
        checks = {(f"kept-{token}", i): (_kept_or_made, *regions[name], made(key))
                  for i, (name, key) in enumerate(units) if name in kept}
        graph.update(checks)
        keys += list(checks)
    return _gathered(graph, token, keys)


class _Units:
    """The tasks that make each unit of a graph, apart: ``units(key)`` is a :class:`_Unit`.

    A check task carries its own unit's tasks only: the processes scheduler pickles every
    task's arguments, and a check task carrying the whole graph copied it once per check.
    """

    def __init__(self, graph: dict):
        self.graph, self.deps = graph, {}  # key: its dependencies, found once

    def __call__(self, key) -> _Unit:
        from dask.core import get_dependencies

        tasks, todo = {}, [key]
        while todo:
            k = todo.pop()
            if k not in tasks:
                tasks[k] = self.graph[k]
                if k not in self.deps:
                    self.deps[k] = get_dependencies(self.graph, key=k)
                todo.extend(self.deps[k])
        return _Unit(tasks, key)


class _Unit:
    """The tasks of one unit and its key, carried as a task's argument.

    Dask looks into a task's tuples, lists and dicts for keys to compute first; not in here.
    """

    def __init__(self, tasks: dict, key):
        self.tasks, self.key = tasks, key


def _kept_or_made(target, region: tuple[slice, ...], unit: _Unit) -> int:
    """A unit a killed run finished: checked, and made again if it fails.

    Made again by running its tasks here, on the synchronous scheduler: its block is written
    and marked done as in any run (a crash of the machine can leave a marker whose chunks
    never reached the disk).
    """
    if not _intact(target, region):
        from dask.local import get_sync

        get_sync(unit.tasks, [unit.key])
    return 1


def _gathered(graph: dict, token: str, keys: list):
    """One delayed value: :func:`_count` of ``keys`` in the optimised ``graph``.

    Built as one graph, not as a ``dask.delayed`` call per key: each such call culled the
    whole graph again (6 s of a 24 s reconstruct of 1,510 blocks).
    """
    from dask.delayed import Delayed

    name = f"count-{token}"
    dsk = {**graph, name: (_count, list(keys))}
    return Delayed(name, dsk)


def _in_type_of(source, target):
    """``source`` cast to ``target``'s type (a float16 store: refusing what overflows it)."""
    if source.dtype == target.dtype:
        return source
    from pipeline.stores.radiance import stored

    return source.map_blocks(stored, np.dtype(target.dtype), f"{target.store}/{target.path}",
                             dtype=target.dtype)


def _optimized_together(arrays: list):
    """One graph of ``arrays`` optimised as one, as :func:`dask.array.store` does.

    Blockwise fusion then sees every consumer of a shared input, and fuses it into none: it
    is computed once. (``dask.optimize(*arrays)`` optimises each array's graph on its own and
    fuses a shared input into each: ``btf generate`` computed every block's material fields
    five times, once for the radiance and once per truth array.)
    """
    from dask.array.optimization import optimize
    from dask.core import flatten
    from dask.highlevelgraph import HighLevelGraph

    graph = HighLevelGraph.merge(*(a.__dask_graph__() for a in arrays))
    return optimize(graph, [k for a in arrays for k in flatten(a.__dask_keys__())])


def _intact(target, region: tuple[slice, ...]) -> bool:
    """Whether a block a killed run wrote reads back: every chunk passes its checksum."""
    from pipeline.checksums import ChecksumError

    summed = _stored_sums_match(target, region)
    if summed is not None:
        return summed
    try:
        target[region]
    except ChecksumError:
        return False
    return True


def _stored_sums_match(target, region: tuple[slice, ...]) -> bool | None:
    """Whether every chunk file of ``region`` holds the CRC-32C of its bytes (None: unknown).

    The check of :func:`_intact` without decoding: a chunk's last 4 bytes are the checksum of
    the rest (the ``crc32c`` codec, last of btf's codecs), so the files are read and summed,
    not decompressed (a resumed generate read back 60% of its store to check it). A missing
    file is a chunk not written: False. Only for unsharded arrays on a local disk whose codecs
    end with the checksum; elsewhere None, and the block is read back.
    """
    from pathlib import Path

    from zarr.codecs import Crc32cCodec

    from pipeline.checksums import chunk_slices
    from pipeline.chunk_io import local_store

    codecs = getattr(target.metadata, "codecs", ())
    store = local_store(target)  # inside btf's own wrapper (pipeline.storage.Strict)
    if (target.shards is not None or store is None or not codecs
            or not isinstance(codecs[-1], Crc32cCodec)):
        return None
    import google_crc32c

    root = Path(str(store.root), target.path)
    for index, _ in chunk_slices(target, region):
        try:
            raw = (root / target.metadata.encode_chunk_key(index)).read_bytes()
        except FileNotFoundError:
            return False
        # the bytes before the checksum as a view (a slice of the bytes copied them)
        if len(raw) < 4 or google_crc32c.value(np.frombuffer(raw, np.uint8)[:-4]) != \
                int.from_bytes(raw[-4:], "little"):
            return False
    return True


def _write_block(block: np.ndarray, target, region: tuple[slice, ...]) -> None:
    from pipeline import chunk_io

    chunk_io.write(target, region, block)


def _write_here(block: np.ndarray, *, target, progress=None, block_info=None) -> np.ndarray:
    """Write a block where it lies in ``target``; a one-element array stands for it.

    With ``progress``, the block is then marked done (its unit's marker, named as
    :func:`store_aligned` names the units).
    """
    region = tuple(slice(a, b) for a, b in block_info[0]["array-location"])
    _write_block(block, target, region)
    done = np.zeros((1,) * block.ndim, np.int8)
    if progress is not None:
        from pipeline import resume

        index = ".".join(map(str, block_info[0]["chunk-location"]))
        resume.mark_done(done, progress.marker(f"{target.path}/{index}"), logged=True)
    return done


def _count(done: list) -> int:
    return len(done)


"""Every chunk of a store btf writes is written, and a missing one is an error, not fill values.

zarr reads a chunk that has no object as the array's fill value (NaN for btf's float
variables), and by default does not write a chunk that equals it. So a chunk lost on its way
to storage (a write acknowledged and lost, a copy cut short, a deleted file) or not found on
a read (an object store that answers "no such key" while it restarts) would read as fill
values, with no error: checksums (:mod:`pipeline.checksums`) can only check bytes that exist.
btf closes that gap in three steps:

- **Every chunk is written**, even one that equals the fill value (zarr's
  ``array.write_empty_chunks``, set by :func:`pipeline.storage.store` in every process that
  opens a store).
- **A store is sealed when its stage finishes** (:func:`seal`, called by :mod:`pipeline.atomic`
  before the commit): every array's chunk objects (shards, for a sharded array) are listed
  against its chunk grid. A missing one fails the stage with one message naming the array and
  the chunk, and the partial output is removed, so that the same command starts over. A
  complete store is marked (the root attribute :data:`pipeline.storage.SEALED`).
- **A sealed store is read strictly** (the ``Strict`` store :func:`pipeline.storage.store`
  gives): a chunk object that a read-only open does not find is a
  :class:`~pipeline.checksums.MissingChunkError` naming the store, the array and the chunk.

Unsealed stores (made by a btf that did not seal, and partial outputs) are read leniently (a
missing chunk is fill values): a partial output lacks the chunks it has not written yet. So
is a store computed only for a scene (``computed_for_scene``): it holds only the chunks its
scene reads, and is not sealed.
"""

from __future__ import annotations

import contextlib
import itertools
import math
import warnings

from pipeline import storage
from pipeline.checksums import MissingChunkError


def expected_keys(array) -> list[str]:
    """The keys of every chunk object of ``array`` (its shards, if sharded), from its root."""
    unit = array.shards or array.chunks
    grid = [range(math.ceil(n / u)) for n, u in zip(array.shape, unit, strict=True)]
    prefix = f"{array.path}/" if array.path else ""
    return [prefix + array.metadata.encode_chunk_key(index)
            for index in itertools.product(*grid)]


def object_key(array, index: tuple[int, ...]) -> str:
    """The key, from the store's root, of the object holding chunk ``index`` (its shard)."""
    unit = array.shards or array.chunks
    shard = tuple(i * c // u for i, c, u in zip(index, array.chunks, unit, strict=True))
    prefix = f"{array.path}/" if array.path else ""
    return prefix + array.metadata.encode_chunk_key(shard)


@contextlib.contextmanager
def _quiet():
    """Silence the warnings about hidden entries (resume markers), which are no zarr nodes."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Object at .* is not recognized")
        yield


def _open(location: str, mode: str):
    import zarr

    with _quiet():
        return zarr.open(storage.store(location), mode=mode, use_consolidated=False)


def _arrays(node) -> list:
    import zarr

    if isinstance(node, zarr.Array):
        return [node]
    with _quiet():
        members = list(node.members(max_depth=None))
    return [m for path, m in members if isinstance(m, zarr.Array)
            and not any(p.startswith(".") for p in path.split("/"))]


def missing(location: str) -> dict[str, list[str]]:
    """The chunk objects that the store at ``location`` lacks, by array path (one listing)."""
    present = set(storage.list_below(location))
    out: dict[str, list[str]] = {}
    for array in _arrays(_open(location, "r")):
        lacking = [k for k in expected_keys(array) if k not in present]
        if lacking:
            out[array.path] = lacking
    return out


def describe(lacking: dict[str, list[str]]) -> str:
    """``missing()``'s result in a few words: arrays, counts and a first key each."""
    parts = [f"{path!r} {len(keys)} (e.g. {keys[0]})" for path, keys in sorted(lacking.items())]
    return "; ".join(parts[:4]) + (f"; and {len(parts) - 4} more arrays" if len(parts) > 4 else "")


def seal(location: str, shown: str) -> None:
    """Check that the finished store at ``location`` has every chunk, then mark it sealed.

    A store computed only for a scene is left unsealed (see the module).

    Raises
    ------
    MissingChunkError
        Naming the arrays and chunks that are missing (the caller removes the output).
    """
    node = _open(location, "r+")
    if node.attrs.get("computed_for_scene"):
        return
    if (error := missing_error(location, shown)) is not None:
        raise error
    node.attrs[storage.SEALED] = True


def missing_error(location: str, shown: str) -> MissingChunkError | None:
    """The error for the chunks a finished store (or group) lacks; None if it lacks none."""
    lacking = missing(location)
    if not lacking:
        return None
    count = sum(len(k) for k in lacking.values())
    return MissingChunkError(
        f"{shown}: {count} chunk object(s) are missing once the stage finished, although it "
        f"wrote every chunk: {describe(lacking)}. A write was lost on its way to storage; "
        "the partial output was removed: run the same command again")

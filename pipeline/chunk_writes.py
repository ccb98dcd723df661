"""Writing whole chunks of a local store in the task's own thread, past zarr's event loop.

zarr 3 writes every chunk through its event loop: a write from a dask thread hands the chunk to
zarr's I/O thread, which sends its encoding (one codec at a time) and its file write each to a
thread pool of its own and back, and the dask thread waits. On 2 cores that machinery, not the
encoding or the disk, set the rate of every stage that writes radiance: a reconstruct's dask
threads spent as long waiting for zarr as computing, and writing a gigabyte of 786 KB chunks from
memory took 3.8-4.4 s through ``array[...] = block``, 0.9-1.6 s encoded and written here.

:func:`write` does, for a block made of whole chunks of an unsharded array in a local store,
what zarr's codec pipeline does for a complete chunk: the array's own codecs encode it (zarr's
codec objects, so the bytes are zarr's: a test compares them file by file), and the file is
written as zarr's ``LocalStore`` writes it (a temporary file in the same folder, renamed into
place, so a reader or a kill never sees half a chunk). Anything else (a sharded array, another
store, a block that covers part of a chunk, array-to-array codecs, a store that skips chunks of
the fill value) is written by zarr, as before.
"""

from __future__ import annotations

import os
import uuid
from pathlib import Path

import numpy as np


def write(target, region: tuple, block: np.ndarray) -> None:
    """``target[region] = block``, chunk by chunk in this thread where :func:`_writer` can.

    ``region``: one slice (step 1) or integer per axis of ``target``, as zarr takes them.
    """
    writer = _writer(target)
    region = tuple(region) + (slice(None),) * (target.ndim - len(region))
    if writer is None or len(region) != target.ndim or not all(
            isinstance(r, slice | int | np.integer) for r in region):
        target[region] = block
        return
    whole = tuple(slice(int(r), int(r) + 1) if not isinstance(r, slice) else
                  slice(*r.indices(n)[:2]) if r.step in (None, 1) else r
                  for r, n in zip(region, target.shape, strict=True))
    if not writer.covers(whole):
        target[region] = block
        return
    shape = tuple(s.stop - s.start for s in whole)
    writer.write(whole, np.broadcast_to(np.asarray(block, dtype=target.dtype), shape))


def _writer(target) -> _Writer | None:
    """A :class:`_Writer` for ``target``, or None where zarr must write it."""
    from zarr.core.codec_pipeline import codecs_from_list

    store = local_store(target)
    if store is None or store.read_only or target.shards is not None:
        return None
    config = target.async_array.config
    if not config.write_empty_chunks or target.metadata.zarr_format != 3:
        return None
    array_array, array_bytes, bytes_bytes = codecs_from_list(target.metadata.codecs)
    if array_array:
        return None
    return _Writer(target, store, config, array_bytes, bytes_bytes)


def local_store(array):
    """The ``LocalStore`` ``array`` is in (inside btf's wrappers), or None elsewhere."""
    from zarr.storage import LocalStore, WrapperStore

    store = array.store
    while isinstance(store, WrapperStore) and not isinstance(store, LocalStore):
        store = store._store
    return store if type(store) is LocalStore else None


class _Writer:
    """Encodes and writes whole chunks of one array (see the module)."""

    def __init__(self, target, store, config, array_bytes, bytes_bytes) -> None:
        from zarr.core.buffer import default_buffer_prototype

        self.target, self.store, self.config = target, store, config
        self.prefix = f"{target.path}/" if target.path else ""
        self.array_bytes, self.bytes_bytes = array_bytes, tuple(bytes_bytes)
        self.prototype = default_buffer_prototype()

    def covers(self, region: tuple[slice, ...]) -> bool:
        """Whether ``region`` is made of whole chunks (clipped at the array's end)."""
        for s, c, n in zip(region, self.target.chunks, self.target.shape, strict=True):
            start, stop = s.start or 0, n if s.stop is None else s.stop
            if s.step not in (None, 1) or start % c or (stop % c and stop != n) or stop > n:
                return False
        return True

    def write(self, region: tuple[slice, ...], block: np.ndarray) -> None:
        from pipeline.checksums import chunk_slices

        starts = [s.start or 0 for s in region]
        for index, where in chunk_slices(self.target, region):
            inside = tuple(slice(w.start - s0, w.stop - s0) for w, s0 in zip(where, starts,
                                                                              strict=True))
            self._put(index, block[inside])

    def _put(self, index: tuple[int, ...], values: np.ndarray) -> None:
        metadata = self.target.metadata
        spec = metadata.get_chunk_spec(index, self.config, self.prototype)
        if values.shape == spec.shape:
            chunk = self.prototype.nd_buffer.from_numpy_array(values)
        else:  # the array's last chunk along some axis: padded as zarr pads it
            from zarr.core.codec_pipeline import fill_value_or_default

            chunk = self.prototype.nd_buffer.create(
                shape=spec.shape, dtype=spec.dtype.to_native_dtype(), order=spec.order,
                fill_value=fill_value_or_default(spec))
            chunk[tuple(slice(0, n) for n in values.shape)] = \
                self.prototype.nd_buffer.from_numpy_array(values)
        encoded = self.array_bytes._encode_sync(chunk, spec)
        for codec in self.bytes_bytes:
            encoded = codec._encode_sync(encoded, spec)
        _put(self.store, self.prefix + metadata.encode_chunk_key(index),
             encoded.as_buffer_like())


def _put(store, key: str, data) -> None:
    """Write ``data`` at ``key`` of a ``LocalStore`` as it does: a temporary file, renamed."""
    path = Path(str(store.root), key)
    partial = path.with_suffix(f".{uuid.uuid4().hex}.partial")
    try:
        f = open(partial, "wb")  # closed below, before the rename
    except FileNotFoundError:  # the chunk's first in its folder
        os.makedirs(path.parent, exist_ok=True)
        f = open(partial, "wb")
    try:
        with f:
            f.write(data)
        os.replace(partial, path)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise

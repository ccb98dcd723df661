"""Reading and writing whole chunks of a local store in the task's own thread, past zarr's loop.

zarr 3 reads and writes every chunk through its event loop: a call from a dask thread hands the
chunk to zarr's I/O thread, which sends its decoding or encoding (one codec at a time) and its
file access each to a thread pool of its own and back, and the dask thread waits. On 2 cores
that machinery, not the codecs or the disk, set the rate of every stage that moves radiance: a
reconstruct's dask threads spent as long waiting for zarr as computing. A gigabyte of 786 KB
chunks from memory took 3.8-4.4 s to write through ``array[...] = block`` and 0.9-1.6 s
encoded and written here; read back whole, 1.7-2.7 s through zarr and 0.35-0.47 s here.

:func:`write` does, for a block made of whole chunks of an unsharded array in a local store,
what zarr's codec pipeline does for a complete chunk: the array's own codecs encode it (zarr's
codec objects, so the bytes are zarr's: a test compares them file by file), and the file is
written as zarr's ``LocalStore`` writes it (a temporary file in the same folder, renamed into
place, so a reader or a kill never sees half a chunk). :class:`Reader` reads any region of
such an array by decoding the chunks it touches with the same codecs. Anything else (a sharded
array, another store, a block that covers part of a chunk, array-to-array codecs, a store that
skips chunks of the fill value; for reads, a chunk that is not there or fails to decode) goes
through zarr, as before, with zarr's and btf's errors.
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
    whole = _regions(target, region)
    if writer is None or whole is None or not writer.covers(whole[0]):
        target[region] = block
        return
    whole, integers = whole
    shape = tuple(s.stop - s.start for s in whole)
    block = np.expand_dims(np.asarray(block, dtype=target.dtype), integers)
    writer.write(whole, np.broadcast_to(block, shape))


def _regions(array, index: tuple) -> tuple[tuple[slice, ...], tuple[int, ...]] | None:
    """``index`` as one slice per axis, and the axes that integers took; None for others.

    Integers (negative ones counted from the end) and slices of step 1, as zarr takes them;
    missing trailing axes are whole. None for anything else (zarr then takes ``index``).
    """
    import operator

    index = tuple(index) + (slice(None),) * (array.ndim - len(index))
    if len(index) != array.ndim:
        return None
    out, integers = [], []
    for axis, (i, n) in enumerate(zip(index, array.shape, strict=True)):
        if isinstance(i, slice):
            if i.step not in (None, 1):
                return None
            out.append(slice(*i.indices(n)[:2]))
        elif isinstance(i, int | np.integer):
            i = operator.index(i)
            i += n if i < 0 else 0
            if not 0 <= i < n:
                return None
            out.append(slice(i, i + 1))
            integers.append(axis)
        else:
            return None
    return tuple(out), tuple(integers)


def dask_array(array, where: str, chunks, dims=None):
    """A dask array of zarr ``array`` (at store location ``where``) read by :class:`Reader`.

    ``chunks``: dask's chunks, or a dict by dimension name (``dims``; others whole). Its tasks
    are named by the location, the array's metadata and when that was last written, so a
    store made again at the same path gets other names.
    """
    import dask.array as da
    from dask.base import tokenize

    if isinstance(chunks, dict):
        chunks = tuple(chunks.get(d, -1) for d in dims)
    name = f"read-{array.path}-" + tokenize(str(where), array.path, array.shape,
                                             array.dtype.str, chunks, array.metadata.to_dict(),
                                             _written(where, array.path))
    return da.from_array(Reader(array), chunks=chunks, name=name, asarray=False,
                         meta=np.empty((0,) * array.ndim, array.dtype), lock=False)


def _written(where: str, path: str) -> int | None:
    """When a local array's metadata was last written; None elsewhere or if not there."""
    from pipeline import storage

    if storage.is_url(str(where)):
        return None
    try:
        return os.stat(os.path.join(str(where), path, "zarr.json")).st_mtime_ns
    except OSError:
        return None


def read(array, index: tuple) -> np.ndarray:
    """``array[index]`` (slices of step 1 and integers, as zarr takes them), read here."""
    found = _regions(array, index)
    if found is None:
        return array[index]
    region, integers = found
    values = Reader(array)[region]
    return values[tuple(0 if axis in integers else slice(None) for axis in range(array.ndim))]


class Reader:
    """``array[region]`` for dask (``da.from_array``), read here where :func:`_codecs` can.

    Chunks the region touches are decoded in the calling thread and copied into place. A
    chunk file that is missing or does not decode sends the whole region to zarr, which
    reads a missing chunk as the fill value or raises btf's error for it (a sealed store's
    missing chunk, a failed checksum).
    """

    def __init__(self, array) -> None:
        self.array = array
        self.shape, self.dtype, self.ndim = array.shape, array.dtype, array.ndim

    def __getitem__(self, region):
        from pipeline.checksums import chunk_slices

        array = self.array
        found, whole = _codecs(array), _regions(array, region) if isinstance(region, tuple) \
            else None
        if found is None or whole is None or whole[1]:  # dask asks for slices only
            return array[region]
        store, array_bytes, bytes_bytes, config = found
        region = whole[0]
        out = np.empty(tuple(max(0, r.stop - r.start) for r in region), self.dtype)
        if out.size == 0:
            return out
        from zarr.core.buffer import default_buffer_prototype

        prototype = default_buffer_prototype()
        metadata = array.metadata
        prefix = f"{array.path}/" if array.path else ""
        try:
            for index, where in chunk_slices(array, region):
                spec = metadata.get_chunk_spec(index, config, prototype)
                data = prototype.buffer.from_bytes(
                    _get(store, prefix + metadata.encode_chunk_key(index)))
                for codec in reversed(bytes_bytes):
                    data = codec._decode_sync(data, spec)
                chunk = array_bytes._decode_sync(data, spec).as_numpy_array()
                inner = tuple(slice(max(w.start, r.start) - i * c, min(w.stop, r.stop) - i * c)
                              for w, r, i, c in zip(where, region, index, array.chunks,
                                                    strict=True))
                at = tuple(slice(max(w.start, r.start) - r.start, min(w.stop, r.stop) - r.start)
                           for w, r in zip(where, region, strict=True))
                out[at] = chunk[inner]
        except Exception:  # a chunk not there, or not decoding: zarr's own read and errors
            return array[region]
        return out


def _codecs(array):
    """What reading or writing ``array`` here takes, or None where zarr must.

    ``(store, array-to-bytes codec, bytes-to-bytes codecs, config)``.
    """
    from zarr.core.codec_pipeline import codecs_from_list

    store = local_store(array)
    if store is None or array.shards is not None or array.metadata.zarr_format != 3:
        return None
    array_array, array_bytes, bytes_bytes = codecs_from_list(array.metadata.codecs)
    if array_array:
        return None
    return store, array_bytes, tuple(bytes_bytes), array.async_array.config


def here(array) -> bool:
    """Whether ``array``'s chunks are read and written here (else through zarr)."""
    return _codecs(array) is not None


def _writer(target) -> _Writer | None:
    """A :class:`_Writer` for ``target``, or None where zarr must write it."""
    found = _codecs(target)
    if found is None:
        return None
    store, array_bytes, bytes_bytes, config = found
    if store.read_only or not config.write_empty_chunks:
        return None
    return _Writer(target, store, config, array_bytes, bytes_bytes)


def local_store(array):
    """The ``LocalStore`` ``array`` is in (inside btf's own wrappers), or None elsewhere.

    Other wrappers (one that renamed keys, say) are not looked through: zarr writes there.
    """
    from zarr.storage import LocalStore

    from pipeline.storage import OWN_WRAPPERS

    store = array.store
    while type(store).__name__ in OWN_WRAPPERS and hasattr(store, "_store"):
        store = store._store  # btf's wrappers change reads of missing chunks, not keys
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
        """Whether ``region`` is made of whole chunks, the last clipped at the array's end.

        ``region``: slices as :func:`_regions` gives them.
        """
        return all(not s.start % c and (not s.stop % c or s.stop == n) for s, c, n in zip(
            region, self.target.chunks, self.target.shape, strict=True))

    def write(self, region: tuple[slice, ...], block: np.ndarray) -> None:
        from pipeline.checksums import chunk_slices

        for index, where in chunk_slices(self.target, region):
            self._put(index, block[tuple(slice(w.start - s.start, w.stop - s.start)
                                         for w, s in zip(where, region, strict=True))])

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


def _get(store, key: str) -> bytes:
    """The bytes at ``key`` of a ``LocalStore`` (``FileNotFoundError`` if there are none)."""
    return Path(str(store.root), key).read_bytes()


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

"""A checksum on every stored chunk, and errors that say which chunk changed.

Every array btf writes ends its codecs with zarr v3's ``crc32c`` codec (after Blosc for data
variables; alone for coordinates): the CRC-32C of a chunk's encoded bytes is stored with them
and checked whenever the chunk is read, so a changed byte (bit rot, a truncated copy, a
half-synced mirror) is found instead of read as numbers. A sharded array's index carries its
own (zarr's default). Stores written before checksums came stay readable: their metadata names
no ``crc32c`` codec, so nothing is checked for them.

:func:`install` makes zarr decode ``crc32c`` with :class:`ChunkChecksum`, zarr's own codec
whose failure is a :class:`ChecksumError` (a :class:`~pipeline.errors.BTFError`: the CLI prints
it and exits 1) rather than a ``ValueError``. A codec does not know its chunk's key, so readers
that know their region name the chunk with :func:`named`.
"""

from __future__ import annotations

import asyncio
import itertools
from dataclasses import dataclass

from pipeline.errors import BTFError

RESTORE = ("the bytes changed after btf wrote them (bit rot, a truncated or half-synced "
           "copy): restore the store from a good copy or write it again")
ADVICE = f"{RESTORE}; `btf inspect STORE --scan` lists a store's bad chunks"
# Encoded chunks from this size on are summed on zarr's threads, smaller ones on its event loop
# (a thread hop cost about 0.2 ms of CPU here; summing and copying 256 KiB about 0.05 ms).
ON_THREADS = 1 << 18


class ChecksumError(BTFError):
    """A stored chunk whose bytes do not match their checksum."""


class MissingChunkError(BTFError):
    """A chunk object that a complete (sealed) store lacks (:mod:`pipeline.completeness`)."""


def codec():
    """The checksum codec every array btf writes ends with (bytes to bytes, 4 bytes a chunk)."""
    install()
    return _codec_class()()


_installed = False


def install() -> None:
    """Make zarr check ``crc32c`` chunks with :class:`ChunkChecksum` (once per process)."""
    global _installed
    if not _installed:
        import zarr
        from zarr.registry import register_codec

        register_codec("crc32c", _codec_class())
        zarr.config.set({"codecs.crc32c": f"{__name__}.ChunkChecksum"})
        _installed = True


def _codec_class() -> type:
    """``ChunkChecksum``: zarr's ``crc32c`` codec, failing with a :class:`ChecksumError`.

    Made on first use, so that importing this module (``btf --help`` does) loads no zarr.
    """
    made = globals().get("ChunkChecksum")
    if made is not None:
        return made
    from zarr.codecs import Crc32cCodec

    @dataclass(frozen=True)
    class ChunkChecksum(Crc32cCodec):
        def _decode_sync(self, chunk_bytes, chunk_spec):
            if len(chunk_bytes) < 4:
                raise ChecksumError(f"a stored chunk of shape {chunk_spec.shape} has "
                                    f"{len(chunk_bytes)} byte(s), too few to hold its "
                                    f"checksum: {ADVICE}")
            try:
                return super()._decode_sync(chunk_bytes, chunk_spec)
            except ValueError:
                raise ChecksumError(f"a stored chunk of shape {chunk_spec.shape} fails its "
                                    f"checksum: {ADVICE}") from None

        # zarr runs this codec on its event loop's thread, one chunk after another, where Blosc
        # runs on its threads: there, large chunks are summed (and copied) concurrently as well.
        # A small one is summed in place: the hop to a thread costs more than the sum.
        async def _decode_single(self, chunk_bytes, chunk_spec):
            if len(chunk_bytes) < ON_THREADS:
                return self._decode_sync(chunk_bytes, chunk_spec)
            return await asyncio.to_thread(self._decode_sync, chunk_bytes, chunk_spec)

        async def _encode_single(self, chunk_bytes, chunk_spec):
            if len(chunk_bytes) < ON_THREADS:
                return self._encode_sync(chunk_bytes, chunk_spec)
            return await asyncio.to_thread(self._encode_sync, chunk_bytes, chunk_spec)

    ChunkChecksum.__module__, ChunkChecksum.__qualname__ = __name__, "ChunkChecksum"
    globals()["ChunkChecksum"] = ChunkChecksum  # where pickle and zarr's config look it up
    return ChunkChecksum


def __getattr__(name: str):
    if name == "ChunkChecksum":  # pickle's lookup in a process that has not made it yet
        return _codec_class()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def chunk_slices(array, region: tuple[slice, ...]):
    """The chunks of ``array`` (inner chunks of a sharded one) that ``region`` touches.

    Yields each one's grid index and slices.
    """
    ranges = []
    for s, c, n in zip(region, array.chunks, array.shape, strict=True):
        start, stop = s.start or 0, n if s.stop is None else s.stop
        ranges.append(range(start // c, -(-stop // c)))
    for index in itertools.product(*ranges):
        yield index, tuple(slice(i * c, min((i + 1) * c, n))
                           for i, c, n in zip(index, array.chunks, array.shape, strict=True))


def bad_chunks(array, region: tuple[slice, ...] | None = None) -> list[tuple[int, ...]]:
    """The chunks of ``array`` within ``region`` (all of it by default) that cannot be read.

    Each is read on its own; any error counts (a failed checksum, a chunk the codec cannot
    decode).
    """
    region = region or tuple(slice(0, n) for n in array.shape)
    bad = []
    for index, where in chunk_slices(array, region):
        try:
            array[where]
        except Exception:  # whatever the codec raised, the chunk is unreadable
            bad.append(index)
    return bad


def named(store: str, variable: str, array, region: tuple[slice, ...],
          error: BaseException) -> BTFError | None:
    """For a read of ``region`` that failed a checksum: an error naming the bad chunks.

    A missing chunk's error (:class:`MissingChunkError`) names its chunk already and is
    returned as it is; None for any other failure (the caller names it).
    """
    if isinstance(error, MissingChunkError):
        return error
    if not isinstance(error, ChecksumError):
        return None
    bad = bad_chunks(array, region)
    if not bad:
        return None
    shown = ", ".join(chunk_name(array, c) for c in bad[:8])
    more = f" and {len(bad) - 8} more" if len(bad) > 8 else ""
    return ChecksumError(f"{store}: variable {variable!r}, chunk {shown}{more} "
                         f"{'fails its' if len(bad) == 1 else 'fail their'} checksum: "
                         f"{RESTORE}")


def chunk_name(array, index: tuple[int, ...]) -> str:
    """A chunk as its grid index and the values it holds, e.g. ``(0, 3) [0:1, 12:16]``."""
    where = ", ".join(f"{i * c}:{min((i + 1) * c, n)}"
                      for i, c, n in zip(index, array.chunks, array.shape, strict=True))
    return f"({', '.join(map(str, index))}) [{where}]"

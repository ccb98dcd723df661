"""Resuming a stage after a crash: what a partial output already holds.

A stage that may be resumed writes into a partial output named after its provenance
(:func:`pipeline.atomic.atomic_output` with ``resume``), so a rerun of the same command after a
``kill -9`` or the out-of-memory killer finds it again. (Chunk files are not fsynced: after a
power loss a marker may outlive its unit's data. Blocks written by
:func:`pipeline.graphs.blocks.store_aligned` that a killed run finished on another machine or
before this machine last started are checked, alongside the work left, and written again if
a chunk fails its checksum (:meth:`Progress.vouched`); the stages whose units write elsewhere
(tile sets, enlargement, compression, staged images) read back the whole partial output and,
if a chunk fails, start over (:meth:`Progress.distrust_damaged`). A chunk that never reached the
disk at all reads as its fill value, which no checksum can see: resuming is for killed
processes, and only mostly for crashed machines.) One run at a time writes a partial output:
it holds a lock on it. Inside it, :class:`Progress` keeps a marker per finished unit of work
(a block of a store, a pass of the SVD; of a pass, also its running total so far:
:class:`PassCheckpoint`) in ``.btf-done/``: a file holding the unit's result,
or, for a unit whose result is the data it wrote (a block of a store on a local disk), a line
naming it in a log of the process that did it (``.done-HOST-PID-TOKEN-boot-ID.log``, ID the
machine's boot id, appended by one
``write`` per line; a line a kill cut short names nothing). A file per block cost a file
created, renamed and at the end deleted per chunk written: on an ext4 disk a reconstruct of
1,510 chunks of 786 KB took 1.2-2.1 s longer with them (its system time 1.5-2.6 s). A marker
is written only after its unit's data is written, so a unit cut off in the middle is simply
done again; units are deterministic (seeded per block), so a resumed output is bit-identical
to an uninterrupted one. The markers are removed before the output is moved into place.

An interrupt (Ctrl-C) or an error still removes the partial output: resuming is for runs that
were killed before they could clean up, and for a full disk, which keeps it
(:mod:`pipeline.atomic`).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import pickle
import warnings
from collections.abc import Callable, Iterable
from typing import Any

from pipeline import storage

DONE = ".btf-done"
CREATED = "_created"
# a process's log of its finished units, a name a line; BOOT where the machine has a boot id
LOG = ".done-{host}-{pid}-{token}{boot}.log"
BOOT = "-boot-{id}"
BOOT_ID = "/proc/sys/kernel/random/boot_id"  # Linux: new each time the machine starts
PARTIAL = ".partial"  # a unit's running total so far (:class:`PassCheckpoint`)
CHECKPOINTS = 16  # running totals a pass keeps at most
# a pass's kept totals write at most this share of the bytes it reads (a rows x sketch total is
# small beside wide textures, not beside a store of a few texels)
CHECKPOINT_SHARE = 0.05
_TOKEN: tuple[int, str] = (0, "")  # (pid, random token) of this process's log


def _is_log(name: str) -> bool:
    return name.startswith(".done-") and name.endswith(".log")


class Progress:
    """The finished units of a partial output: ``partial/.btf-done/NAME`` markers.

    Files on a local disk, objects in object storage (:mod:`pipeline.storage`).
    """

    def __init__(self, partial: str | os.PathLike):
        self.dir = storage.join(str(partial), DONE)

    def _names(self) -> set[str]:
        names = set()
        for name in storage.children(self.dir):
            if _is_log(name):
                names.update(_logged(storage.join(self.dir, name)))
            elif not name.endswith((".tmp", PARTIAL)):
                names.add(name)
        return names

    @property
    def created(self) -> bool:
        """Whether the output's skeleton (its metadata and client-written arrays) is complete."""
        return storage.exists(storage.join(self.dir, CREATED))

    def mark_created(self) -> None:
        """Record that the skeleton is complete: a rerun resumes instead of starting over."""
        storage.write(storage.join(self.dir, CREATED), b"")

    def skeleton(self, create: Callable[[], Any]):
        """The partial output's zarr group, made once.

        ``create()`` makes it (the store's metadata and client-written arrays) and it is then
        marked complete; when a killed run had completed it, it is opened as it is.
        """
        if self.created:
            return self.group()
        made = create()
        self.mark_created()
        return made

    def group(self):
        """The partial output's zarr group, opened for writing (a resumed run's store)."""
        from pipeline.stores.groups import writable

        return writable(storage.parent(self.dir))

    def distrust_damaged(self, say: Callable[[str], Any],
                         only: Iterable[str] | None = None) -> list[str]:
        """What a killed run left, read back: if a chunk fails its checksum, it is not kept.

        For stages whose units cannot be told from their chunks. Every array of the partial
        output is read back (what the killed run wrote, once more), and if a chunk fails, the
        partial output is emptied: the stage makes its skeleton again (call this before
        :meth:`skeleton`) and does every unit again. With ``only`` (array paths written by
        units alone, none by the skeleton), just those arrays are read, and on a failure their
        bad chunks (their shards, if sharded) and the units' markers go, the skeleton stays.
        ``say`` is told in one line. Returns the bad chunks, as ``ARRAY chunk (i, j, ..)
        [ranges]``; empty when all read back or nothing was kept.
        """
        if not (self.count() if only is not None else self.created):
            return []
        import zarr

        from pipeline import checksums
        from pipeline.stores.groups import readable

        root = storage.parent(self.dir)
        group = readable(root)
        with warnings.catch_warnings():  # the markers' folder is no zarr node: zarr says so
            warnings.filterwarnings("ignore", "Object at .* is not recognized")
            arrays = sorted((a for p, a in group.members(max_depth=None)
                             if isinstance(a, zarr.Array) and (only is None or p in only)),
                            key=lambda a: a.path)  # zarr lists them in no fixed order
        damaged = {array.path: _damaged(array) for array in arrays}
        bad = [f"{array.path} chunk {checksums.chunk_name(array, c)}" for array in arrays
               for c in damaged[array.path]]
        if not bad:
            return []
        if only is None:
            for child in storage.children(root):
                storage.remove(storage.join(root, child))
        else:
            for array in arrays:  # gone, so that no unit done again reads them to add to them
                _remove_chunks(root, array, damaged[array.path])
            for name in storage.children(self.dir):  # marker files and logs
                if name != CREATED:
                    storage.remove(storage.join(self.dir, name))
        more = f" (and {len(bad) - 1} more)" if len(bad) > 1 else ""
        say(f"resuming: {bad[0]}{more} of the killed run fails its checksum: "
            + ("starting over" if only is None else "every unit is done again"))
        return bad

    def done(self, name: str) -> bool:
        """Whether unit ``name`` is finished."""
        return (storage.exists(storage.join(self.dir, _file(name)))
                or (not storage.is_url(self.dir) and _file(name) in self._names()))

    def count(self) -> int:
        """Finished units (the skeleton aside)."""
        return len(self._names() - {CREATED})

    def finished(self, names: Iterable[str]) -> list[str]:
        """Those of unit ``names`` that are marked done."""
        done = self._names()
        return [n for n in names if _file(n) in done]

    def vouched(self, names: Iterable[str]) -> list[str]:
        """Those of unit ``names`` marked done on this machine since it last started.

        Such a unit's data was written before its marker by a process that was at most
        killed: the kernel holds all it was given (in its page cache if not yet on the disk),
        so its chunks need no check (:func:`pipeline.graphs.blocks._intact`). Only a crash of
        the machine loses unsynced data, and it changes the boot id. Markers elsewhere (other
        machines, an earlier boot, object storage, a system without boot ids) vouch for
        nothing: their units are checked.
        """
        boot = _boot()
        if boot is None or storage.is_url(self.dir):
            return []
        mine = BOOT.format(id=boot) + ".log"
        done = set()
        for name in storage.children(self.dir):
            if _is_log(name) and name.endswith(mine):
                done.update(_logged(storage.join(self.dir, name)))
        return [n for n in names if _file(n) in done]

    def marker(self, name: str) -> str:
        """Where unit ``name``'s marker is written (by :func:`mark_done`) once it is done."""
        return storage.join(self.dir, _file(name))

    def pending(self, units: Iterable[tuple[str, Any]], redo: Iterable[str] = ()
                ) -> tuple[list, int]:
        """Delayed ``units`` (``(name, delayed)``) not yet done, each marking itself when done.

        Units named in ``redo`` are done again even if marked done (their data did not read
        back: a crash of the machine can leave a marker whose chunks never reached the disk).
        Returns the units and how many were kept.
        """
        import dask

        finished = self._names() - {_file(n) for n in redo}  # one look at the markers
        todo, skipped = [], 0
        for name, unit in units:
            if _file(name) in finished:
                skipped += 1
                continue
            todo.append(dask.delayed(_keep, pure=True)(unit, self.marker(name)))
        return todo, skipped

    def run(self, compute: Callable[..., tuple], units: list[tuple[str, Any]]) -> list:
        """The results of delayed ``units``, computing (with ``compute``) only those not done.

        Each unit's result is kept in its marker (pickled; small results only), so units a
        killed run finished give their results without running again.
        """
        import dask

        finished = self._names()  # one look at the markers
        results, todo, where = [None] * len(units), [], []
        for i, (name, unit) in enumerate(units):
            marker = storage.join(self.dir, _file(name))
            if _file(name) in finished:
                results[i] = _load(marker)
            else:
                todo.append(dask.delayed(_keep, pure=True)(unit, marker))
                where.append(i)
        for i, value in zip(where, compute(*todo) if todo else (), strict=True):
            results[i] = value
        return results

    def memo(self, name: str, compute: Callable[[], Any]) -> tuple[Any, bool]:
        """``compute()``, or its result stored by an earlier run; and whether it was stored."""
        marker = self.marker(name)
        if storage.exists(marker):
            return _load(marker), True
        value = compute()
        _keep(value, marker)
        PassCheckpoint(marker + PARTIAL, 1).discard()  # what it kept of it on the way
        return value, False


@dataclasses.dataclass(frozen=True)
class PassCheckpoint:
    """The running total of a unit summed in a fixed chain of steps, kept as it goes.

    A pass of the SVD sums its parts in a fixed order
    (:func:`pipeline.graphs.row_passes.running_sum`). Every few steps the total so far is
    written over one file beside the markers (``NAME.partial``, with the number of steps it
    holds), so that a pass killed in its middle resumes from there: a rerun loads it and sums
    only the parts after it, in the same order, to the same bits. A total is kept at most
    :data:`CHECKPOINTS` times a pass, and no more often than keeps the bytes written under
    :data:`CHECKPOINT_SHARE` of those read (``read_per_step``: the bytes a step's parts read).
    """

    marker: str
    read_per_step: int
    inputs: str = ""  # a digest of what every part reads besides the store

    @classmethod
    def of(cls, progress: Progress, name: str, read_per_step: int, inputs: Any = None
           ) -> PassCheckpoint:
        """The checkpoint of unit ``name`` among ``progress``'s markers.

        ``inputs``: what the parts read besides the store (the sketch, the factors). A total
        kept from other inputs is not resumed from: a client's products can differ in their
        last bits on another machine (its BLAS threads), and a pass must add parts of one.
        """
        import hashlib

        digest = hashlib.sha256(pickle.dumps(inputs, protocol=pickle.HIGHEST_PROTOCOL))
        return cls(progress.marker(name) + PARTIAL, max(1, int(read_per_step)),
                   digest.hexdigest())

    def latest(self) -> tuple[int, Any] | None:
        """``(steps summed, total)`` that a killed run kept from the same inputs, or None.

        A file that does not unpickle (one a crashed machine left part of) is ignored.
        """
        data = storage.read(self.marker)
        if data is None:
            return None
        try:
            inputs, steps, total = pickle.loads(data)
        except Exception:  # any damage (a crashed machine's file): sum the pass again
            return None
        return (int(steps), total) if inputs == self.inputs else None

    def keep(self, step: int, steps: int, total: Any) -> None:
        """After step ``step`` (from 0) of ``steps``: keep ``total`` if this step is due.

        Due every ``max(steps / CHECKPOINTS, nbytes / (CHECKPOINT_SHARE * read_per_step))``
        steps, rounded up (``total.nbytes``), but not at the last one: the whole pass is kept
        as its unit.
        """
        done = step + 1
        if done >= steps:
            return
        every = max(-(-steps // CHECKPOINTS),
                    math.ceil(total.nbytes / (CHECKPOINT_SHARE * self.read_per_step)))
        if done % every == 0:
            storage.write(self.marker, pickle.dumps((self.inputs, done, total),
                                                    protocol=pickle.HIGHEST_PROTOCOL),
                          durable=False)

    def discard(self) -> None:
        """Remove the kept total (its unit is done, or was kept whole)."""
        if storage.exists(self.marker):
            storage.remove(self.marker)


def _damaged(array) -> list[tuple[int, ...]]:
    """The chunks of ``array`` that fail their checksum.

    Read a write unit (a shard, or a chunk) at a time on threads; a failing unit then chunk by
    chunk.
    """
    import itertools
    from concurrent.futures import ThreadPoolExecutor

    from pipeline.checksums import ChecksumError, bad_chunks

    unit = array.shards or array.chunks
    regions = [tuple(slice(i * u, min((i + 1) * u, n)) for i, u, n in zip(
        index, unit, array.shape, strict=True)) for index in itertools.product(
        *(range(-(-n // u)) for n, u in zip(array.shape, unit, strict=True)))]

    def fails(region) -> bool:
        try:
            array[region]
        except ChecksumError:
            return True
        return False

    with ThreadPoolExecutor(4) as pool:
        failing = [r for r, f in zip(regions, pool.map(fails, regions), strict=True) if f]
    return [c for region in failing for c in bad_chunks(array, region)]


def _remove_chunks(root: str, array, chunks: list[tuple[int, ...]]) -> None:
    """Remove ``chunks`` (grid indices) of ``array`` under ``root``: their shards, if sharded."""
    from pipeline.completeness import object_key

    for key in {object_key(array, index) for index in chunks}:
        storage.remove(storage.join(root, key))


def _file(name: str) -> str:
    return name.replace("/", "~")


def mark_done(result: Any, marker: str, *, logged: bool = False) -> Any:
    """:func:`_keep`, looked up when called (tests replace it to stop a run there)."""
    return _keep(result, marker, logged=logged)


def _keep(result: Any, marker: str, *, logged: bool = False) -> Any:
    """Store ``result`` as the marker of its unit, written whole.

    A file renamed into place, or one object. Runs after the unit it depends on: its data is
    written, so it is done. With ``logged`` (a unit whose result is the data it wrote, never
    read back from its marker), a local marker is a line in this process's log instead.
    """
    # not fsynced: the unit's chunks are not either, so a marker that outlived a power loss
    # would vouch for nothing more (see the module); a killed process loses neither
    if logged and not storage.is_url(marker):
        _log(marker)
        return result
    storage.write(marker, pickle.dumps(result, protocol=pickle.HIGHEST_PROTOCOL), durable=False)
    return result


def _log(marker: str) -> None:
    """Append the name of ``marker`` to this process's log beside it, in one ``write``.

    ``O_APPEND``: the threads of a process each add whole lines. A process killed after the
    write returned leaves the line in the file (the kernel's page cache holds it); a kill
    cannot leave part of a line but at the end, without its newline, which reads as nothing.
    The log is this process's alone (its host, pid and a random token: a rerun in a container
    may have the killed run's pid), so no other process appends after a cut line.
    """
    import socket
    import uuid

    global _TOKEN
    if _TOKEN[0] != os.getpid():  # a fork has a log of its own
        _TOKEN = (os.getpid(), uuid.uuid4().hex[:12])
    folder, name = os.path.split(marker)
    boot = _boot()
    path = os.path.join(folder, LOG.format(host=socket.gethostname(), pid=_TOKEN[0],
                                           token=_TOKEN[1],
                                           boot=BOOT.format(id=boot) if boot else ""))
    line = memoryview((name + "\n").encode())
    try:
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    except FileNotFoundError:  # the folder is made on the first marker
        os.makedirs(folder, exist_ok=True)
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        while line:  # a short write (a full disk raises on the next)
            line = line[os.write(fd, line):]
    finally:
        os.close(fd)


@functools.cache
def _boot() -> str | None:
    """The boot id of the machine, or None where it has none (not Linux)."""
    try:
        with open(BOOT_ID) as f:
            return f.read().strip() or None
    except OSError:
        return None


def _logged(log: str) -> set[str]:
    """The units a log names: its whole lines (a last line without its newline is not one)."""
    data = storage.read(log)
    if data is None:  # removed since it was listed
        return set()
    return {line.decode() for line in data.split(b"\n")[:-1] if line}


def _load(marker: str) -> Any:
    return pickle.loads(storage.read(marker))

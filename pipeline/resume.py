"""Resuming a stage after a crash: what a partial output already holds.

A stage that may be resumed writes into a partial output named after its provenance
(:func:`pipeline.atomic.atomic_output` with ``resume``), so a rerun of the same command after a
``kill -9`` or the out-of-memory killer finds it again. (Chunk files are not fsynced: after a
power loss a marker may outlive its unit's data, so resuming is for killed processes, not for
crashed machines.) One run at a time writes a partial output: it holds a lock on it. Inside it,
:class:`Progress` keeps one empty marker file per finished unit of work (a block of a store, a
pass of the SVD) in ``.btf-done/``. A marker is written only after its unit's data is written,
so a unit cut off in the middle is simply done again; units are deterministic (seeded per
block), so a resumed output is bit-identical to an uninterrupted one. The markers are removed
before the output is moved into place.

An interrupt (Ctrl-C) or an error still removes the partial output: resuming is for runs that
were killed before they could clean up.
"""

from __future__ import annotations

import os
import pickle
import uuid
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

DONE = ".btf-done"
CREATED = "_created"


class Progress:
    """The finished units of a partial output (``partial/.btf-done/NAME`` marker files)."""

    def __init__(self, partial: str | os.PathLike):
        self.dir = Path(partial) / DONE

    @property
    def created(self) -> bool:
        """Whether the output's skeleton (its metadata and client-written arrays) is complete."""
        return (self.dir / CREATED).is_file()

    def mark_created(self) -> None:
        """Record that the skeleton is complete: a rerun resumes instead of starting over."""
        self.dir.mkdir(parents=True, exist_ok=True)
        _touch(self.dir / CREATED)

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
        import zarr

        return zarr.open_group(str(self.dir.parent), mode="r+", use_consolidated=False)

    def done(self, name: str) -> bool:
        """Whether unit ``name`` is finished."""
        return (self.dir / _file(name)).is_file()

    def count(self) -> int:
        """Finished units (the skeleton aside)."""
        if not self.dir.is_dir():
            return 0
        return sum(1 for p in self.dir.iterdir() if p.name != CREATED and p.suffix != ".tmp")

    def pending(self, units: Iterable[tuple[str, Any]]) -> tuple[list, int]:
        """Delayed ``units`` (``(name, delayed)``) not yet done, each marking itself when done.

        Returns them and how many were already done.
        """
        import dask

        self.dir.mkdir(parents=True, exist_ok=True)
        todo, skipped = [], 0
        for name, unit in units:
            if self.done(name):
                skipped += 1
                continue
            todo.append(dask.delayed(_keep, pure=True)(unit, str(self.dir / _file(name))))
        return todo, skipped

    def run(self, compute: Callable[..., tuple], units: list[tuple[str, Any]]) -> list:
        """The results of delayed ``units``, computing (with ``compute``) only those not done.

        Each unit's result is kept in its marker (pickled; small results only), so units a
        killed run finished give their results without running again.
        """
        import dask

        self.dir.mkdir(parents=True, exist_ok=True)
        results, todo, where = [None] * len(units), [], []
        for i, (name, unit) in enumerate(units):  # one look at the markers
            path = self.dir / _file(name)
            if path.is_file():
                results[i] = _load(path)
            else:
                todo.append(dask.delayed(_keep, pure=True)(unit, str(path)))
                where.append(i)
        for i, value in zip(where, compute(*todo) if todo else (), strict=True):
            results[i] = value
        return results

    def memo(self, name: str, compute: Callable[[], Any]) -> tuple[Any, bool]:
        """``compute()``, or its result stored by an earlier run; and whether it was stored."""
        path = self.dir / _file(name)
        if path.is_file():
            return _load(path), True
        value = compute()
        self.dir.mkdir(parents=True, exist_ok=True)
        _keep(value, str(path))
        return value, False


def _file(name: str) -> str:
    return name.replace("/", "~")


def _touch(path: Path) -> None:
    with path.open("w") as f:
        f.flush()
        os.fsync(f.fileno())


def _keep(result: Any, marker: str) -> Any:
    """Store ``result`` as the marker of its unit (written whole, then renamed into place).

    Runs after the unit it depends on: its data is written, so it is done.
    """
    path = Path(marker)
    tmp = path.with_name(f"{path.name}.{uuid.uuid4().hex[:8]}.tmp")  # a retried task: its own
    with tmp.open("wb") as f:
        pickle.dump(result, f, protocol=pickle.HIGHEST_PROTOCOL)
        f.flush()
        os.fsync(f.fileno())
    tmp.rename(path)
    return result


def _load(path: Path) -> Any:
    with path.open("rb") as f:
        return pickle.load(f)

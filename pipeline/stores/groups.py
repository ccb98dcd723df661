"""Zarr groups of stores opened as they are: for reading without checks, or for writing.

The bottom of the store layer (it imports only :mod:`pipeline.storage`), so that the
infrastructure below the stores (resuming, provenance) can open a partial output or read a
store's attributes without importing them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pipeline import storage


def readable(path: str | Path):
    """A store's group opened for reading as it is, with no checks.

    For a partial output, or a store a task reopens that its stage checked (the files, not the
    consolidated copy).
    """
    import zarr

    return zarr.open_group(storage.store(storage.parse(path)), mode="r", use_consolidated=False)


def stored_attrs(path: str | Path) -> dict[str, Any] | None:
    """The attributes of the group at ``path``; None where there is none to read."""
    where = storage.parse(path)
    if not storage.exists(storage.join(where, storage.ROOT)):
        return None
    try:
        return dict(readable(where).attrs)
    except Exception:  # unreadable metadata: as good as none
        return None


def writable(path: str | Path, subgroup: str | None = None, *, new: bool = False):
    """A store's group (or ``subgroup`` of it) opened for writing.

    For a stage's own output while it writes it, or a store it adds to (``btf pyramid``'s
    levels); ``new`` creates the subgroup, refusing one that exists.
    """
    import zarr

    store = storage.store(storage.parse(path))
    if new:
        return zarr.open_group(store, path=subgroup, mode="w-", zarr_format=3)
    return zarr.open_group(store, path=subgroup or "", mode="r+", use_consolidated=False)


def made_by_btf(attrs: dict[str, Any]) -> bool:
    """Whether a group's attributes are a store btf wrote (its kind, or a provenance)."""
    return "btf_kind" in attrs or "provenance" in attrs

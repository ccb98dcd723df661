"""Declarations a package collects from its own modules: stages, source formats.

A package whose modules each declare one object under a fixed name (``STAGE``, ``FORMAT``)
finds them with :func:`collect`: a new module is a new entry, with no list to edit.
"""

from __future__ import annotations

import importlib
import pkgutil
from typing import Any


def declared(package: str, module: str, attribute: str, kind: type) -> Any | None:
    """``package.module``'s ``attribute`` if it is a ``kind``, else None (importing it)."""
    found = getattr(importlib.import_module(f"{package}.{module}"), attribute, None)
    return found if isinstance(found, kind) else None


def collect(package: str, path, attribute: str, kind: type,
            order: tuple[str, ...]) -> dict[str, Any]:
    """Every ``kind`` declared as ``attribute`` in the modules of ``package`` (at ``path``).

    Keyed by the declaration's ``name``; the names in ``order`` first, in that order, then the
    others by name.
    """
    found = {}
    for module in pkgutil.iter_modules(path):
        item = declared(package, module.name, attribute, kind)
        if item is not None:
            found[item.name] = item
    rank = {name: k for k, name in enumerate(order)}
    return dict(sorted(found.items(), key=lambda entry: (rank.get(entry[0], len(order)),
                                                         entry[0])))

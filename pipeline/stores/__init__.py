"""The kinds of store the project writes, one module each on one shared base.

:data:`KINDS` maps every ``btf_kind`` attribute value to its :class:`StoreKind` (how to check,
summarise and open it); ``btf inspect`` and the stages look kinds up here. The shared base
(:mod:`pipeline.stores.base`) creates every store: group, attrs, direction coordinates, channel
labels and data variables in the project's codec.
"""

from __future__ import annotations

from pathlib import Path

from pipeline.errors import BTFError
from pipeline.stores import compressed, fitted, radiance, scene, surface, tileset
from pipeline.stores.base import StoreKind, open_group

KINDS: dict[str, StoreKind] = {name: module.KIND
                               for module in (radiance, compressed, tileset, fitted, surface, scene)
                               for name in module.KIND.names}


def kind_of(group) -> StoreKind | None:
    """The kind of an opened store (None for a group no stage of the project wrote)."""
    return KINDS.get(group.attrs.get("btf_kind"))


def open_layers(path: str | Path):
    """A Dataset with a (lazy) ``radiance`` of layers, from a radiance or a compressed store."""
    group = open_group(path)
    if group.attrs.get("btf_kind") == compressed.NAME:
        return compressed.open_compressed(path)
    if group.attrs.get("btf_kind") in KINDS and group.attrs["btf_kind"] not in radiance.NAMES:
        raise BTFError(f"{path}: a {group.attrs['btf_kind']} store; expected a radiance store "
                       "or a compressed one")
    return radiance.open_radiance(path)

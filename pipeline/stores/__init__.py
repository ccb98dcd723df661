"""The kinds of store the project writes, one class each on one shared base.

:data:`KINDS` maps every ``btf_kind`` attribute value to its class (a subclass of
:class:`~pipeline.stores.base.Store`: how to check, summarise and read it, its attributes as
typed properties); :func:`open_store` opens a path as one, and stages pass these handles. The
shared base (:mod:`pipeline.stores.base`) creates every store: group, attrs, direction
coordinates, channel labels and data variables in the project's codec.
"""

from __future__ import annotations

from pathlib import Path

from pipeline.errors import BTFError
from pipeline.stores import compressed, fitted, radiance, scene, surface, tileset
from pipeline.stores.base import Store, open_group
from pipeline.stores.compressed import CompressedStore
from pipeline.stores.fitted import FittedStore
from pipeline.stores.radiance import FIRST, RadianceStore
from pipeline.stores.scene import SceneStore
from pipeline.stores.surface import SurfaceStore
from pipeline.stores.tileset import CompressedTileSetStore, TileSetStore

__all__ = ["KINDS", "CompressedStore", "CompressedTileSetStore", "FittedStore",
           "RadianceStore", "SceneStore", "Store", "SurfaceStore", "TileSetStore", "kind_of",
           "open_layers", "open_store"]

KINDS: dict[str, type[Store]] = {
    name: kind for kind in (RadianceStore, CompressedStore, TileSetStore,
                            CompressedTileSetStore, FittedStore, SurfaceStore, SceneStore)
    for name in kind.names}


def kind_of(group) -> type[Store] | None:
    """The class of an opened group's kind (None for a group no stage of the project wrote)."""
    return KINDS.get(group.attrs.get("btf_kind"))


def open_store(path: str | Path, *expected: type[Store], checked: bool = True) -> Store:
    """The store at ``path`` as the class its ``btf_kind`` names, checked.

    With ``expected`` classes, another kind is refused with one message naming the store, what
    it is and what to run first (a radiance stage given a compressed store: ``btf
    reconstruct``). ``checked=False`` skips the kind's checks: for tasks reopening a store
    their stage has checked.
    """
    group = open_group(path)
    store = _class_of(group)(path, group)
    if expected and not isinstance(store, expected):
        _refuse(store, expected)
    if checked:
        store.validate()
    return store


def _class_of(group) -> type[Store]:
    """The class of a group's kind.

    A group with ``radiance`` but no ``btf_kind`` (written by another tool) is a radiance
    store; any other group is of the base class.
    """
    kind = group.attrs.get("btf_kind")
    if kind in KINDS:
        return KINDS[kind]
    if kind is None and "radiance" in group.array_keys():
        return RadianceStore
    return Store


def _refuse(store: Store, expected: tuple[type[Store], ...]) -> None:
    """One message for a store of another kind than ``expected``.

    One expected kind: that kind's own check says what is wrong (and what to run first, for
    radiance); several: which kinds would do.
    """
    if len(expected) == 1 or (RadianceStore in expected and store.kind not in KINDS):
        (expected[0] if len(expected) == 1 else RadianceStore).check(store.group, store.path)
    wanted = " or ".join(f"a {kind.what}" for kind in expected)
    hint = FIRST.get(store.kind or "") if RadianceStore in expected else None
    raise BTFError(f"{store.path}: a {store.kind or 'non-btf'} store, where {wanted} is needed"
                   + (f": {hint}" if hint else ""))


def open_layers(path: str | Path, chunks=None):
    """A Dataset with a (lazy) ``radiance`` of layers, from a radiance or a compressed store.

    ``chunks``: a radiance store's dask chunks (:func:`pipeline.stores.radiance.open_dataset`).
    """
    store = open_store(path, RadianceStore, CompressedStore)
    return store.dataset(chunks)


def lazy_layers(store: RadianceStore | CompressedStore, chunks):
    """A radiance or compressed store's radiance ``(view, light, y, x, channel)``, lazily.

    :func:`open_layers`' radiance as a dask array, without xarray (0.6-0.7 s of a process
    to import): a radiance store's read in the dask chunks ``chunks(group, name)`` gives (by
    dimension name: :func:`pipeline.graphs.blocks.read_chunks`), a compressed store's
    rebuilt from its factors in their own blocks.
    """
    if isinstance(store, CompressedStore):
        return compressed.open_factors(store.path, group=store.group).radiance
    return radiance.lazy_variable(store, radiance.RADIANCE,
                                  chunks(store.group, radiance.RADIANCE))[0]


__all__ += ["compressed", "fitted", "radiance", "scene", "surface", "tileset"]

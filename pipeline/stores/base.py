"""What every store shares (the store contract, docs/README.md), and the one way to create one.

Every store the project writes is a zarr v3 group that ``xarray.open_zarr`` opens, with

- attrs ``btf_kind`` (which kind of store, see :mod:`pipeline.stores`), ``source`` (the stage
  that made it) and ``provenance``;
- the direction coordinates ``theta_view``, ``phi_view`` (on ``view``) and ``theta_light``,
  ``phi_light`` (on ``light``) in degrees, and the ``channel`` labels of what it describes;
- data variables in the project's codec (:func:`codec`) with named dimensions.

:func:`create_store` writes the group, its attrs and coordinates; :func:`add_array` adds a
variable in the project's codec. Each kind's module builds on these two.
"""

from __future__ import annotations

import json
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from pipeline import checksums, storage
from pipeline.errors import BTFError
from pipeline.stores.groups import readable, stored_attrs, writable  # noqa: F401 (re-exported)
from tasks.sampling import Directions

RADIANCE = "radiance"
RADIANCE_DIMS = ("view", "light", "y", "x", "channel")
DIRECTION_COORDS = {"theta_view": "view", "phi_view": "view",
                    "theta_light": "light", "phi_light": "light"}


def location(path: str | Path) -> str:
    """A store's location as handed to tasks (:func:`pipeline.storage.parse`).

    An absolute path (workers may run in another directory) or an object-store URL.
    """
    return storage.parse(path)


def compressors() -> tuple:
    """The project's codecs for data variables: Blosc lz4 with byte shuffling, then a checksum.

    The checksum (:mod:`pipeline.checksums`) finds a chunk whose bytes changed after writing.
    """
    from zarr.codecs import BloscCodec

    # Byte shuffling groups the float32 exponents together. Measured on a generated wood ABTF
    # (one 48 MiB shard): lz4 gives 1.26x at 830 MB/s encode / 1390 MB/s decode, zstd-3 1.33x
    # at 220 / 1060 MB/s. Stores are read many times over (compression passes), so lz4.
    return BloscCodec(cname="lz4", clevel=5, shuffle="shuffle"), checksums.codec()


def create_store(path: str | Path, *, kind: str, attrs: dict[str, Any],
                 directions: Directions | None, channels: tuple[str, ...] | None):
    """Create a new store: the group, its attrs with ``btf_kind``, coordinates and channels.

    Returns the zarr group; the kind's module adds its variables with :func:`add_array`.
    """
    import zarr

    group = zarr.open_group(storage.store(location(path)), mode="w-", zarr_format=3,
                            attributes={**attrs, "btf_kind": kind})
    if directions is not None:
        for name, dim in DIRECTION_COORDS.items():
            values = np.asarray(getattr(directions, name), np.float64)
            coord = group.create_array(name, shape=values.shape, dtype="float64",
                                       dimension_names=(dim,), compressors=checksums.codec(),
                                       attributes={"units": "degree"})
            coord[:] = values
    if channels is not None:
        labels = group.create_array("channel", shape=(len(channels),), dtype=str,
                                    dimension_names=("channel",),
                                    compressors=checksums.codec())
        labels[:] = np.array(channels)
    return group


def add_array(group, name: str, *, shape: tuple[int, ...], dims: tuple[str, ...],
              chunks: tuple[int, ...] | None = None, shards: tuple[int, ...] | None = None,
              dtype: str = "float32", fill_value: Any = None, attrs: dict | None = None):
    """Add a data variable in the project's codec; returns the zarr array.

    Float variables are filled with NaN until written (``fill_value=None``), so unwritten
    chunks are never mistaken for data.
    """
    if fill_value is None:
        fill_value = np.nan if np.dtype(dtype).kind == "f" else 0
    return group.create_array(name, shape=shape, chunks=chunks or "auto", shards=shards,
                              dtype=dtype, dimension_names=dims, compressors=compressors(),
                              fill_value=fill_value, attributes=attrs or None)


def open_group(path: str | Path):
    """Open a zarr v3 group for reading, with a clear error if it is not one."""
    where = location(path)
    meta = storage.read(storage.join(where, storage.ROOT))
    if meta is None and storage.is_url(where):
        from pipeline.atomic import finish_swaps

        if finish_swaps(where, str(path)):  # a replacement a killed run had left half-swapped
            meta = storage.read(storage.join(where, storage.ROOT))
    if meta is None:
        if not storage.any_below(where):
            raise BTFError(f"{path}: no such store")
        hint = (" (a zarr v2 store: convert it to zarr v3)"
                if storage.exists(storage.join(where, ".zgroup")) else "")
        raise BTFError(f"{path}: not a zarr v3 store, there is no zarr.json{hint}")
    try:
        node_type = json.loads(meta).get("node_type")
    except ValueError as exc:
        raise BTFError(f"{path}: unreadable zarr.json ({exc})") from None
    if node_type != "group":
        raise BTFError(f"{path}: a zarr array, not a group of variables")
    # the files themselves, not the consolidated copy (written for other tools, see atomic)
    return readable(where)


def read_directions(group) -> Directions:
    """The direction coordinates of a store (small arrays)."""
    return Directions(*(np.asarray(group[name][:], np.float64) for name in DIRECTION_COORDS))


def read_channels(group) -> tuple[str, ...]:
    """The channel labels of a store."""
    return tuple(str(c) for c in group["channel"][:])


def check_kind(group, path: str | Path, name: str, what: str, made_by: str,
               dims: dict[str, tuple[str, ...]]) -> None:
    """Raise :class:`BTFError` unless ``group`` is of kind ``name`` with these variables.

    The message names the kind found and the command that makes ``what``.
    """
    if group.attrs.get("btf_kind") != name:
        raise BTFError(f"{path}: not {what} (btf_kind is {group.attrs.get('btf_kind')!r}; "
                       f"make one with {made_by})")
    check_variables(group, path, dims)


def check_variables(group, path: str | Path, dims: dict[str, tuple[str, ...]]) -> None:
    """Raise :class:`BTFError` unless every named variable exists with these dims."""
    names = set(group.array_keys())
    for name, expected in dims.items():
        if name not in names:
            raise BTFError(f"{path}: variable {name!r} is missing (found: "
                           f"{', '.join(sorted(names)) or 'none'})")
        found = tuple(group[name].metadata.dimension_names or ())
        if found != expected:
            raise BTFError(f"{path}: variable {name!r} has dims {found}, expected {expected}")


def check_coordinates(group, path: str | Path, sizes: dict[str, int], what: str) -> None:
    """Raise :class:`BTFError` unless the direction and channel coordinates match ``sizes``.

    ``sizes`` maps ``view``, ``light`` and ``channel`` to the lengths ``what`` (a variable)
    has along them.
    """
    names = set(group.array_keys())
    for name, dim in {**DIRECTION_COORDS, "channel": "channel"}.items():
        if name not in names:
            raise BTFError(f"{path}: coordinate {name!r} is missing")
        if group[name].shape != (sizes[dim],):
            raise BTFError(f"{path}: coordinate {name!r} has shape {group[name].shape}, but "
                           f"{what} has {sizes[dim]} {dim}(s)")


def check_computed(group, path: str | Path, view: int, light: int) -> None:
    """Refuse a layer that a store restricted to a scene did not compute.

    Such stores (``btf run`` with a ``scene:`` section, or ``--for-scene``) record what they
    hold in ``computed_for_scene``.
    """
    only = group.attrs.get("computed_for_scene")
    if only and [view, light] not in only["layers"]:
        raise BTFError(f"{path}: view {view}, light {light} was not computed: the store holds "
                       f"only the {len(only['layers'])} layer(s) the scene {only['scene']} "
                       "needs (btf run with a scene: section); run its stage without the "
                       "scene for every layer")


def layer_indices(selection, size: int, what: str, store: str) -> list[int]:
    """Validated, de-duplicated view or light indices (all of them when ``selection`` is None)."""
    if selection is None:
        return list(range(size))
    bad = [i for i in selection if not 0 <= i < size]
    if bad:
        raise BTFError(f"{store}: --{what} {bad[0]} is out of range (the store has {size} "
                       f"{what}s, indices 0 to {size - 1})")
    return list(dict.fromkeys(selection))


def isel(data, dims: tuple[str, ...], indexers: dict[str, list[int] | slice]):
    """``data`` (a dask array along ``dims``) at ``indexers``' positions of named dimensions.

    One axis at a time, as xarray's ``isel`` takes index lists; an indexer that keeps a
    whole axis (every index in order, or ``slice(None)``) is left out.
    """
    for axis, dim in enumerate(dims):
        index = indexers.get(dim)
        if index is None or index == slice(None) or (
                isinstance(index, list) and index == list(range(data.shape[axis]))):
            continue
        data = data[(slice(None),) * axis + (index,)]
    return data


def _rings(theta: np.ndarray) -> int:
    return len(np.unique(np.round(theta, 3)))


def sampling_summary(group) -> dict[str, Any]:
    """Counts and ranges of a store's view and light directions."""
    d = read_directions(group)
    name = group.attrs.get("sampling") or group.attrs.get("source_sampling")
    out: dict[str, Any] = {"name": name, "views": d.views, "lights": d.lights,
                           "layers": d.views * d.lights}
    for which in ("view", "light"):
        theta, phi = getattr(d, f"theta_{which}"), getattr(d, f"phi_{which}")
        out[which] = {"theta_min": float(theta.min()), "theta_max": float(theta.max()),
                      "theta_rings": _rings(theta), "phi_min": float(phi.min()),
                      "phi_max": float(phi.max())}
    return out


def sampling_lines(s: dict[str, Any]) -> list[str]:
    """Text lines of a :func:`sampling_summary`."""
    lines = [f"sampling: {s['name'] or 'unnamed'}: {s['views']} view(s) x {s['lights']} "
             f"light(s) = {s['layers']} layers"]
    for which in ("view", "light"):
        w = s[which]
        lines.append(f"  {which:<5} theta {w['theta_min']:.1f}-{w['theta_max']:.1f} deg on "
                     f"{w['theta_rings']} ring(s), phi {w['phi_min']:.1f}-"
                     f"{w['phi_max']:.1f} deg")
    return lines


class Store:
    """An opened store: where it is, its zarr group (read only) and what its attrs say.

    One subclass per kind of store, in the kind's module, with the ``btf_kind`` values it is
    written with (``names``) and its attributes as typed properties read in one place;
    :func:`pipeline.stores.open_store` opens a path as the class its ``btf_kind`` names (this
    class for a group no stage of btf wrote). Stages pass these handles, not paths and attrs.
    The kind's hooks for ``btf inspect`` are static: ``check(group, path)``,
    ``summary(group)`` and ``lines(summary)``.
    """

    names: tuple[str, ...] = ()
    what = "store"  # for messages: "a <what>"

    def __init__(self, path: str | Path, group=None):
        self.path = str(path)
        self.group = open_group(path) if group is None else group

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.path!r})"

    @staticmethod
    def check(group, path: str | Path) -> None:
        """Raise :class:`BTFError` naming what is wrong with ``group`` (nothing by default)."""

    @staticmethod
    def summary(group) -> dict[str, Any]:
        """What ``btf inspect`` reports of the kind beyond variables and attrs."""
        return {}

    @staticmethod
    def lines(summary: dict[str, Any]) -> list[str]:
        """That summary as text lines."""
        return []

    def validate(self) -> None:
        """:meth:`check` this store."""
        self.check(self.group, self.path)

    @property
    def location(self) -> str:
        """The store's location as handed to tasks (:func:`location`)."""
        return location(self.path)

    @property
    def kind(self) -> str | None:
        """The ``btf_kind`` attribute (None for a group btf did not write)."""
        return self.group.attrs.get("btf_kind")

    @property
    def attrs(self) -> dict[str, Any]:
        """A copy of the group's attributes."""
        return dict(self.group.attrs)

    @cached_property
    def directions(self) -> Directions:
        """The view and light directions (degrees)."""
        return read_directions(self.group)

    @cached_property
    def channels(self) -> tuple[str, ...]:
        """The channel labels."""
        return read_channels(self.group)

    def has(self, name: str) -> bool:
        """Whether the store holds the array ``name``."""
        return name in set(self.group.array_keys())

    def __getitem__(self, name: str):
        return self.group[name]

    def check_computed(self, view: int, light: int) -> None:
        """Refuse a layer a store restricted to a scene did not compute (:func:`check_computed`)."""
        check_computed(self.group, self.path, view, light)

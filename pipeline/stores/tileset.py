"""Tile-set stores (``tileset``, ``compressed-tileset``): quilting's and the roller's tiles.

A tile-set store holds

- ``radiance``: float32 ``(tile, view, light, y, x, channel)``, one chunk per tile and layer, so
  that rendering one layer reads nothing of the others; or, for a compressed source
  (``compressed-tileset``), the source's factors ``U``, ``S`` and the *sample's* eigentextures
  ``V`` ``(sample_y, sample_x, component)``: a tile's eigentextures are its prescription applied
  to them, ``P_t V``, computed where they are read (:func:`tile_eigentextures`,
  :func:`tile_layers`), so the store is about the size of the source's factors and
  prescriptions, whatever the number of tiles (the prescription blends the log-domain
  eigentextures, so blended texels are weighted geometric means of the radiance they join).
  Tile sets written before this (``tiles_stored: eigentextures``) hold every tile's ``V``
  ``(tile, y, x, component)`` instead, and read as before;
- ``corners`` ``(tile, corner)``: the corner types (top-left, top-right, bottom-left,
  bottom-right) of each tile, and ``corner`` labels;
- ``prescription_index`` / ``prescription_weight`` ``(tile, pixel, term)``: each tile's
  prescription (:mod:`tasks.prescription`), so it can be applied again to other data;
- ``reference`` ``(sample_y, sample_x, reference_channel)``: the image it was planned on;
- the roller's ``representative`` ``(y, x, 2)``: where each stored texel lies in the cut tile;
- the direction coordinates and ``channel`` labels of the source, and attrs with the planning
  parameters, seed and placements.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from pipeline import checksums
from pipeline.errors import BTFError
from pipeline.stores.base import (
    DIRECTION_COORDS,
    RADIANCE,
    Directions,
    Store,
    add_array,
    create_store,
    sampling_lines,
    sampling_summary,
)
from pipeline.stores.compressed import Factors
from tasks.placement import corner_code

NAMES = ("tileset", "compressed-tileset")
CORNERS = ("top_left", "top_right", "bottom_left", "bottom_right")


PRESCRIBED = "prescriptions"  # attrs["tiles_stored"] of a compressed set holding the sample's V


def create_tileset_store(path, *, directions: Directions, channels: tuple[str, ...],
                         tiles: int, tile_shape: tuple[int, int], terms: int,
                         reference: np.ndarray, attrs: dict[str, Any], rank: int | None = None,
                         v_chunk: int = 128, dtype: str = "float32"):
    """Create an empty tile-set store (``rank``: a compressed one); returns the zarr group.

    A compressed one gets the sample's ``V`` (chunks of ``v_chunk`` texels a side), not the
    tiles'. ``dtype``: the type of the tiles' radiance, or of ``V`` (the source's).
    """
    if rank is not None:
        attrs = {**attrs, "tiles_stored": PRESCRIBED}
    group = create_store(path, kind=NAMES[rank is not None], attrs=attrs,
                         directions=directions, channels=channels)
    ty, tx = tile_shape
    nv, nl, nc = directions.views, directions.lights, len(channels)
    if rank is None:
        add_array(group, RADIANCE, shape=(tiles, nv, nl, ty, tx, nc),
                  dims=("tile", "view", "light", "y", "x", "channel"),
                  chunks=(1, 1, 1, ty, tx, nc), dtype=dtype,
                  attrs={"coordinates": " ".join(DIRECTION_COORDS)})
    else:
        add_array(group, "U", shape=(nv, nl, nc, rank), chunks=(nv, nl, nc, rank),
                  dims=("view", "light", "channel", "component"))
        add_array(group, "S", shape=(rank,), dims=("component",), chunks=(rank,))
        sy, sx = reference.shape[:2]
        add_array(group, "V", shape=(sy, sx, rank),
                  chunks=(min(v_chunk, sy), min(v_chunk, sx), rank), dtype=dtype,
                  dims=("sample_y", "sample_x", "component"),
                  attrs={"long_name": "the sample's eigentextures: tile t's are P_t V"})
    pixels = ty * tx
    add_array(group, "corners", shape=(tiles, 4), dims=("tile", "corner"), dtype="int64",
              chunks=(tiles, 4))
    for name, dtype in (("prescription_index", "int32"), ("prescription_weight", "float32")):
        add_array(group, name, shape=(tiles, pixels, terms), chunks=(1, pixels, terms),
                  dims=("tile", "pixel", "term"), dtype=dtype)
    add_array(group, "reference", shape=reference.shape, chunks=reference.shape,
              dims=("sample_y", "sample_x", "reference_channel"))[...] = reference
    names = group.create_array("corner", shape=(4,), dtype=str, dimension_names=("corner",),
                               compressors=checksums.codec())
    names[:] = np.array(CORNERS)
    return group


@dataclass(frozen=True)
class Placement:
    """How a tile set's tiles cover a surface: its attributes, read and written here only.

    ``kind``: ``"corners"`` (quilting's corner tiles, ``corner_types`` types of corner, laid by
    a hash of the lattice vertices) or ``"lattice"`` (the roller's tiles on a sheared lattice,
    described by ``lattice``: its vectors, the tile vectors ``U``, ``V``, the Hermite normal
    form ``hnf`` of the stored layout, ...). ``seed`` is the placement seed.
    """

    kind: str = "corners"
    corner_types: int = 1
    seed: int = 0
    lattice: dict[str, Any] | None = None

    def __post_init__(self):
        if self.kind not in ("corners", "lattice"):
            raise ValueError(f"placement must be corners or lattice, got {self.kind!r}")
        if self.kind == "lattice" and not self.lattice:
            raise ValueError("a lattice placement needs its lattice")

    def to_dict(self) -> dict[str, Any]:
        """The store's attributes of the placement."""
        out: dict[str, Any] = {"corner_types": self.corner_types, "seed": self.seed}
        if self.kind == "lattice":
            out.update(placement="lattice", lattice=self.lattice)
        return out

    @staticmethod
    def from_dict(attrs: dict[str, Any]) -> Placement:
        """The placement a store's attributes describe (older quilt sets: the plan's seed)."""
        seed = attrs.get("seed", (attrs.get("quilt") or {}).get("seed", 0))
        kind = "lattice" if attrs.get("placement") == "lattice" else "corners"
        return Placement(kind, int(attrs.get("corner_types") or 1), int(seed),
                         attrs.get("lattice") if kind == "lattice" else None)


@dataclass(frozen=True)
class TileSet:
    """What a planner made: every tile's prescription and corner types, and its reference.

    ``index`` and ``weight`` hold one ``(pixel, term)`` array per tile (:mod:`tasks.prescription`);
    ``placement`` how they cover a surface; ``attrs`` the planner's record for the store;
    ``representative`` the roller's cut-tile position of every stored texel.
    """

    index: list[np.ndarray]
    weight: list[np.ndarray]
    tile_shape: tuple[int, int]
    corners: np.ndarray
    reference: np.ndarray
    attrs: dict[str, Any]
    placement: Placement = Placement()
    representative: np.ndarray | None = None

    @property
    def samples(self) -> int:
        """Texels of the sample the prescriptions take from."""
        return int(np.prod(self.reference.shape[:2]))

    def matrices(self) -> list:
        """The tiles' prescriptions as CSR matrices (output texels x sample texels)."""
        from tasks.prescription import rows

        return [rows(i, w, self.samples) for i, w in zip(self.index, self.weight, strict=True)]


def write_tileset_store(path, tiles: TileSet, *, source: Store):
    """Create a tile-set store for ``tiles`` planned on ``source``; returns the zarr group.

    ``source`` is the radiance or compressed store's handle. Writes everything but the tiles'
    layers (or eigentextures), which the application graph
    (:mod:`pipeline.graphs.prescriptions`) fills: the prescriptions, corner types, reference,
    and for a compressed source its ``U`` and ``S``.
    """
    from pipeline.stores.compressed import CompressedStore

    compressed = isinstance(source, CompressedStore)
    source_group = source.group
    attrs = {**tiles.attrs, **tiles.placement.to_dict(), "source_store": source.path,
             "tile_shape": list(tiles.tile_shape),
             "sample_shape": list(tiles.reference.shape[:2]),
             "source_btf_kind": source.attrs.get("source_btf_kind") if compressed
             else source.kind}
    if compressed:
        attrs["transform"] = source.attrs["transform"]
    out = create_tileset_store(path, directions=source.directions,
                               channels=source.channels, tiles=len(tiles.index),
                               tile_shape=tiles.tile_shape, terms=tiles.index[0].shape[-1],
                               reference=tiles.reference, attrs=attrs,
                               rank=source_group["S"].shape[0] if compressed else None,
                               v_chunk=source_group["V"].chunks[0] if compressed else 128,
                               dtype=str(source_group["V" if compressed else RADIANCE].dtype))
    out["corners"][...] = tiles.corners
    for t in range(len(tiles.index)):
        out["prescription_index"][t] = tiles.index[t].astype(np.int32)
        out["prescription_weight"][t] = tiles.weight[t]
    if tiles.representative is not None:
        add_array(out, "representative", shape=tiles.representative.shape,
                  chunks=tiles.representative.shape, dims=("y", "x", "vector"),
                  dtype="int64")[...] = tiles.representative
    if compressed:
        out["U"][...] = source_group["U"][...]
        out["S"][...] = source_group["S"][...]
    return out


def check_tileset(group, path: str | Path) -> None:
    """Raise :class:`BTFError` naming what is wrong if ``group`` is not a tile-set store."""
    kind = group.attrs.get("btf_kind")
    if kind not in NAMES:
        raise BTFError(f"{path}: not a tile-set store (btf_kind is {kind!r}; make one with btf "
                       "quilt or btf roller)")
    needed = [RADIANCE] if kind == "tileset" else ["U", "S", "V"]
    for name in (*needed, "corners", "prescription_index", "prescription_weight"):
        if name not in group.array_keys():
            raise BTFError(f"{path}: variable {name!r} is missing")


def read_plan(path) -> TileSet:
    """The :class:`TileSet` a tile-set store (complete or partial) was created for.

    Everything :func:`write_tileset_store` wrote: prescriptions, corner types, reference, the
    roller's representatives and the store's attrs (its own keys included).
    """
    from pipeline.stores.groups import readable

    group = readable(path)
    index, weight = group["prescription_index"][...], group["prescription_weight"][...]
    return TileSet(index=list(index), weight=list(weight),
                   tile_shape=tuple(group.attrs["tile_shape"]),
                   corners=group["corners"][...], reference=group["reference"][...],
                   attrs=dict(group.attrs), placement=Placement.from_dict(dict(group.attrs)),
                   representative=group["representative"][...]
                   if "representative" in group else None)


def corner_order(path, corners: np.ndarray, types: int) -> np.ndarray:
    """Stored tile of each corner combination, in :func:`tasks.placement.cell_tiles` order.

    Every combination of ``types`` corner types must be stored exactly once.
    """
    corners = np.asarray(corners)
    codes = corner_code(*corners.T, corners=types)
    if (corners.min(initial=0) < 0 or corners.max(initial=0) >= types
            or sorted(codes.tolist()) != list(range(types**4))):
        raise BTFError(f"{path}: variable 'corners' does not hold every combination of "
                       f"{types} corner types exactly once")
    return np.argsort(codes)


def _summary(group) -> dict[str, Any]:
    attrs = group.attrs
    source = np.prod(attrs["sample_shape"]) * group["theta_view"].shape[0] * group[
        "theta_light"].shape[0] * group["channel"].shape[0] * 4
    tiles = group["corners"].shape[0]
    return {"sampling": sampling_summary(group),
            "tileset": {"tiles": tiles, "corner_types": attrs.get("corner_types"),
                        "tile_shape": attrs.get("tile_shape"),
                        "sample_shape": attrs.get("sample_shape"),
                        "lattice": attrs.get("lattice"), "planner": attrs.get("quilt")
                        or attrs.get("roller"),
                        "size_vs_source": (tiles * np.prod(attrs["tile_shape"])
                                           / np.prod(attrs["sample_shape"])),
                        "source_bytes": int(source)}}


def _lines(summary: dict[str, Any]) -> list[str]:
    t = summary["tileset"]
    lines = sampling_lines(summary["sampling"])
    lines.append(f"tile set: {t['tiles']} tile(s) of {t['tile_shape'][0]} x "
                 f"{t['tile_shape'][1]} texels, {t['corner_types']} corner type(s), from a "
                 f"{t['sample_shape'][0]} x {t['sample_shape'][1]} sample "
                 f"({t['size_vs_source']:.2f}x its texels)")
    lat = t["lattice"]
    if lat:
        for name, vec, n, a in zip("uv", (lat["u"], lat["v"]), lat["lengths_px"],
                                   lat["angles_deg"], strict=True):
            lines.append(f"  lattice {name} = [{vec[0]:.2f}, {vec[1]:.2f}] ({n:.2f} px at "
                         f"{a:.1f} deg)")
        lines.append(f"  confidence {lat['confidence']:.2f}; each tile spans U = {lat['U']}, "
                     f"V = {lat['V']} ({lat['periods'][0]} x {lat['periods'][1]} periods), "
                     f"stored as {lat['hnf'][0]} x {lat['hnf'][1]} (Hermite layout, shear "
                     f"{lat['hnf'][2]})")
    lines.append(f"  size relative to the sample: 1 : {1 / t['size_vs_source']:.2f}")
    return lines


def _sample_values(v, coef: np.ndarray) -> np.ndarray:
    """``V coef`` ``(sample_y, sample_x, n)`` float32, reading ``V`` a band of chunk rows at a time.

    ``coef`` is ``(K, n)``: memory holds the result and one band, not the sample's ``V``.
    """
    sy, sx = v.shape[:2]
    coef = np.asarray(coef, np.float32)
    out = np.empty((sy, sx, coef.shape[1]), np.float32)
    for y0 in range(0, sy, v.chunks[0]):
        band = np.asarray(v[y0 : y0 + v.chunks[0], :, : coef.shape[0]], np.float32)
        out[y0 : y0 + len(band)] = band @ coef
    return out


class TileSetStore(Store):
    """A tile set of ``btf quilt`` or ``btf roller``: its tiles, placement and prescriptions.

    Its placement is a field: ``"corners"`` (quilting's corner tiles: ``corner_types``, laid by
    a hash of the lattice vertices) or ``"lattice"`` (the roller's tiles on a sheared lattice:
    ``lattice``, ``hnf``, ``basis``, ``representative``); ``seed`` is the placement seed.
    """

    names = (NAMES[0],)
    what = "tile set"
    check = staticmethod(check_tileset)
    summary = staticmethod(_summary)
    lines = staticmethod(_lines)

    @property
    def compressed(self) -> bool:
        """Whether its tiles are eigentextures with ``U`` and ``S`` (else radiance)."""
        return False

    @property
    def tiles(self) -> int:
        """The number of stored tiles."""
        return int(self.group["corners"].shape[0])

    @property
    def tile_shape(self) -> tuple[int, int]:
        """Texels of a stored tile ``(y, x)``."""
        return tuple(int(n) for n in self.group.attrs["tile_shape"])

    @property
    def sample_shape(self) -> tuple[int, int]:
        """Texels of the sample the tiles were planned on ``(y, x)``."""
        return tuple(int(n) for n in self.group.attrs["sample_shape"])

    @cached_property
    def layout(self) -> Placement:
        """How the tiles cover a surface (:class:`Placement`)."""
        return Placement.from_dict(dict(self.group.attrs))

    @property
    def placement(self) -> str:
        """``"lattice"`` (the roller's tiles) or ``"corners"`` (quilting's)."""
        return self.layout.kind

    @property
    def corner_types(self) -> int:
        """Corner types of a corner set (1 for a periodic tile)."""
        return self.layout.corner_types

    @property
    def seed(self) -> int:
        """The placement seed recorded with the set (older quilt sets: the planning seed)."""
        return self.layout.seed

    @property
    def lattice(self) -> dict[str, Any] | None:
        """A roller set's lattice (``u``, ``v``, ``U``, ``V``, ``hnf``, ...), else None."""
        return self.layout.lattice

    @property
    def hnf(self) -> tuple[int, int, int]:
        """A roller set's Hermite normal form ``(h, w, shear)`` of its tile lattice."""
        return tuple(self.lattice["hnf"])

    @property
    def basis(self) -> tuple[tuple, tuple]:
        """A roller set's tile vectors ``(U, V)``."""
        return (tuple(self.lattice["U"]), tuple(self.lattice["V"]))

    @property
    def representative(self) -> np.ndarray | None:
        """Where each stored texel of a roller set lies in its cut tile, or None."""
        return self.group["representative"][...] if self.has("representative") else None

    def order(self) -> np.ndarray:
        """Stored tile of each placement code: corner order, or all tiles of a lattice set."""
        if self.placement == "lattice":
            return np.arange(self.tiles)
        return corner_order(self.path, self.group["corners"][...], self.corner_types)

    def prescription(self, tile: int):
        """Tile ``tile``'s prescription as a CSR matrix (tile texels x sample texels)."""
        from tasks.prescription import rows

        sy, sx = self.sample_shape
        return rows(self.group["prescription_index"][tile],
                      self.group["prescription_weight"][tile], sy * sx)


class CompressedTileSetStore(TileSetStore, Factors):
    """A tile set of a compressed store: ``U``, ``S`` and eigentextures ``V``, its transform.

    Written now with the sample's ``V`` and the prescriptions (``prescribed``): a tile's
    eigentextures are ``P_t V`` and its layers ``P_t`` applied to the sample's values of the
    layer, computed where they are read. Older sets hold every tile's ``V``.
    """

    names = (NAMES[1],)
    what = "compressed tile set"

    @property
    def compressed(self) -> bool:
        """Always true: eigentextures with ``U`` and ``S``."""
        return True

    @property
    def prescribed(self) -> bool:
        """Whether it holds the sample's ``V`` (its tiles' computed on reading)."""
        return self.group["V"].ndim == 3

    def sample_values(self, coef: np.ndarray) -> np.ndarray:
        """``V coef`` ``(sample_y, sample_x, n)`` of the sample, reading ``V`` by bands."""
        return _sample_values(self.group["V"], coef)

    def prescribe(self, tile: int, values: np.ndarray) -> np.ndarray:
        """Tile ``tile`` of sample values ``(sample_y, sample_x, n)``: ``(y, x, n)``."""
        from tasks.prescription import apply

        return apply(self.prescription(tile), values, output=self.tile_shape)

    def tile_values(self, tiles, coef: np.ndarray) -> np.ndarray:
        """Values ``(tile, y, x, n)`` of ``n`` linear combinations of eigentextures, of ``tiles``.

        ``coef`` ``(K', n)`` with ``K' <= K``: e.g. ``diag(S) U[rows]^T`` for some layers'
        values, or the identity's first columns for the eigentextures themselves. A prescribed
        set applies each tile's prescription to the sample's values (the sample is read once);
        an older one reads the stored tiles.
        """
        tiles = list(tiles)
        coef = np.asarray(coef, np.float32)
        ty, tx = self.tile_shape
        out = np.empty((len(tiles), ty, tx, coef.shape[1]), np.float32)
        if not self.prescribed:
            for i, t in enumerate(tiles):
                v = np.asarray(self.group["V"][t, :, :, : coef.shape[0]], np.float32)
                out[i] = v @ coef
            return out
        sample = self.sample_values(coef)
        for i, t in enumerate(tiles):
            out[i] = self.prescribe(t, sample)
        return out

    def tile_eigentextures(self, tiles, rank: int | None = None) -> np.ndarray:
        """The first ``rank`` eigentextures ``(tile, y, x, rank)`` of ``tiles`` (default: all)."""
        k = self.rank if rank is None else rank
        return self.tile_values(tiles, np.eye(self.rank, k, dtype=np.float32))

    def layer_coefficients(self, u_rows: np.ndarray, rank: int | None = None) -> np.ndarray:
        """``diag(S) u^T`` ``(K', layer * channel)``: what takes eigentextures to layers' values.

        ``u_rows`` is ``(layer, channel, K)``; the first ``rank`` components (default: all).
        """
        u = np.asarray(u_rows, np.float64)
        k = u.shape[-1] if rank is None else rank
        s = np.asarray(self.group["S"][:k], np.float64)
        n, nc = u.shape[:2]
        return (s[:, None] * u[..., :k].reshape(n * nc, k).T).astype(np.float32)

    def decode(self, values: np.ndarray, layers: int,
               scale: np.ndarray | None = None) -> np.ndarray:
        """Radiance ``(..., layer, channel)`` of tile values ``(..., layer * channel)``.

        ``scale``, one per layer, multiplies them (a cosine set's layer scale).
        """
        radiance = self.transform.decode(values.reshape(*values.shape[:-1], layers, -1))
        if scale is not None:
            radiance *= np.asarray(scale, np.float32)[:, None]
        return radiance

    def tile_layers(self, tiles, u_rows: np.ndarray, *, rank: int | None = None,
                    scale: np.ndarray | None = None) -> np.ndarray:
        """Radiance ``(tile, y, x, layer, channel)`` of ``u_rows`` ``(layer, channel, K)``.

        The layers' values are formed on the sample (``V diag(S) u^T``: a few numbers per
        texel) and then prescribed, so no tile's eigentextures are ever held. ``scale``: one
        per layer (a cosine set's layer scale).
        """
        values = self.tile_values(tiles, self.layer_coefficients(u_rows, rank))
        return self.decode(values, len(u_rows), scale)


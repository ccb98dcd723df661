"""``btf view``: one self-contained HTML page that relights a compressed BTF in the browser.

The page holds the eigentextures ``V`` (half floats, four components a texture layer) and the
rows ``U diag(S)`` of every measured (view, light) pair; its WebGL2 shader computes each
texel's values as one dot product of length ``k`` per channel, decodes them with the store's
transform and tone-maps them as the report does (:func:`tasks.tonemap.tonemap`). Between
measured directions it blends measured pairs (:mod:`tasks.viewer`). The page's rank and level
of detail come from the store's spectrum and ``--budget`` (:func:`tasks.viewer.shown_rank`,
:func:`tasks.viewer.plan_page`); a level holds block means of ``V`` (exact for the values), a
region a part; of a tile set, every tile's block means, or a region of the surface btf render
lays. A radiance store is compressed on the way, into a temporary store that is removed with
the page written.
"""

from __future__ import annotations

import base64
import dataclasses
import json
import math
from importlib import resources
from pathlib import Path

import numpy as np

from pipeline.atomic import write_whole
from pipeline.errors import BTFError
from pipeline.params import ParamError, check_region, option, parse_region
from pipeline.session import Session
from pipeline.stage import Stage
from pipeline.stores import (
    CompressedStore,
    CompressedTileSetStore,
    RadianceStore,
    TileSetStore,
    open_store,
)
from pipeline.stores.base import read_channels, read_directions
from pipeline.stores.compressed import total_energy
from tasks.svd import reconstruct_layers
from tasks.tonemap import exposure
from tasks.transform import Transform
from tasks.viewer import (
    ENERGY_KEPT,
    GRID,
    MIN_DEFAULT_RANK,
    b64_bytes,
    block_means,
    mesh,
    pack_eigentextures,
    page_bytes,
    plan_page,
    shown_rank,
)

MIB = 1 << 20
MAX_RANK = 64
SLACK = 4096  # bytes the page's JSON may grow by between the estimate and the page


@dataclasses.dataclass(frozen=True)
class ViewParams:
    """Parameters of ``btf view``."""

    store: str = option(help="compressed store (btf compress, btf ingest) or compressed tile "
                             "set (btf quilt, btf roller), or a radiance store to compress on "
                             "the way", positional=True, path="in")
    out: str = option(help="HTML file to write", positional=True, path="out", metavar="OUT.html")
    rank: int | None = option(None, metavar="R",
                              help="components shown (default: the fewest keeping 99.99%% of "
                                   "the store's energy, at most 64 and what fits --budget)")
    level: int | None = option(None, metavar="N",
                               help="level of detail: texels are block means of 2^N per side "
                                    "(default: 0, or the lowest at which 8 components, or "
                                    "--rank, fit --budget)")
    region: str | None = option(None, metavar="Y0:Y1,X0:X1",
                                help="texel region of level 0, ends exclusive (default: all); "
                                     "of a tile set: of the surface btf render lays")
    budget: float = option(25.0, metavar="MB", help="largest page to write, in MB")
    exposure: float | None = option(None, help="initial exposure scale (default: automatic)")
    overwrite: bool = option(False, record=False, help="replace OUT if it exists")

    def __post_init__(self):
        check_region(self.region)
        if self.rank is not None and not 1 <= self.rank <= MAX_RANK:
            raise ParamError("rank", f"must be between 1 and {MAX_RANK} (the shader's rows of U "
                             f"are uniforms and registers), got {self.rank}")
        if self.level is not None and not 0 <= self.level <= 12:
            raise ParamError("level", f"must be between 0 and 12, got {self.level}")
        if not self.budget > 0:
            raise ParamError("budget", f"must be positive, got {self.budget}")
        if self.exposure is not None and not self.exposure > 0:
            raise ParamError("exposure", f"must be positive, got {self.exposure}")


def _initial_pair(d) -> tuple[int, int]:
    """The view nearest the normal and the light nearest the normal."""
    return int(np.argmin(d.theta_view)), int(np.argmin(d.theta_light))


def _b64(a: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(a).tobytes()).decode("ascii")


def _page(data: dict, blobs: dict[str, np.ndarray]) -> str:
    """The HTML of the page: the template with the data and the binary blobs inlined."""
    template = resources.files("pipeline").joinpath("templates/view.html").read_text()
    scripts = "\n".join(f'<script type="application/octet-stream" id="blob-{name}">'
                        f"{_b64(a)}</script>" for name, a in blobs.items())
    return template.replace("/*DATA*/null", json.dumps(data)).replace("<!--BLOBS-->", scripts)


def view(params: ViewParams, session: Session) -> Path:
    """Write the relighting page of a compressed store or tile set (radiance: compressed first)."""
    from pipeline import storage

    if not params.overwrite and storage.exists(storage.parse(params.out, what="output")):
        raise BTFError(f"{params.out}: already exists; pass --overwrite to replace it")
    store = open_store(params.store, checked=False)  # its kind first, then its checks
    if isinstance(store, CompressedStore | CompressedTileSetStore):
        store.validate()
        return _write_page(params, store, session)
    if isinstance(store, TileSetStore):
        raise BTFError(f"{params.store}: a tile set of radiance; btf view lays compressed tile "
                       "sets: quilt the compressed store (btf compress, then btf quilt "
                       "COMPRESSED.zarr TILES.zarr)")
    if not isinstance(store, RadianceStore):
        raise BTFError(f"{params.store}: btf view shows a compressed or a radiance store; this "
                       f"is a {store.kind or 'non-BTF'} store")
    store.validate()
    return _compressed_on_the_way(params, store, session)


def _compressed_on_the_way(params: ViewParams, store: RadianceStore, session: Session) -> Path:
    """Compress a radiance store into a temporary store, then write its page.

    At ``--rank``, else at the most components any level's page could hold (the page then
    keeps what the spectrum and the budget say); both checked before compressing.
    """
    import tempfile

    from pipeline.compression import CompressSettings
    from pipeline.compression import compress as compress_store

    d, _, meshes = _check_directions(params, store.group)
    nv, nl, ny, nx, nc = store.shape
    most = min(MAX_RANK, nv * nl * nc, ny * nx)
    shown = _StoreWindow(params, None, ny, nx)
    fixed = _fixed_bytes(d, meshes)
    least = _least(params, params.rank or most)
    plan = plan_page(shown.size, rows=nv * nl * nc, fixed=fixed, budget=_budget(params),
                     wanted=params.rank or most, least=least, levels=_levels(params))
    if plan is None:  # before the compression, not after it
        _refuse(params, shown.size, nv * nl * nc, fixed, least)
    # the most components a page of any level could hold: those whose rows of U diag(S) fit
    k = params.rank or max(k for k in range(1, most + 1)
                           if k == 1 or page_bytes(1, k, nv * nl * nc, fixed) <= _budget(params))
    with tempfile.TemporaryDirectory(prefix="btf-view-") as tmp:
        compressed = str(Path(tmp) / "compressed.zarr")
        session.log(f"view: {params.store} is a radiance store: compressing it at rank {k} "
                    f"first (btf compress {params.store} OUT.zarr --rank {k} keeps it)")
        compress_store(CompressSettings(store=params.store, out=compressed, rank=k), session)
        return _write_page(params, open_store(compressed, CompressedStore), session,
                           name=params.store)


def _least(params: ViewParams, wanted: int) -> int:
    """The fewest components a page may hold.

    ``--rank``'s; else, to choose the level, :data:`tasks.viewer.MIN_DEFAULT_RANK` (or
    ``wanted``, if fewer); at a given level, 1.
    """
    if params.rank:
        return params.rank
    return min(wanted, MIN_DEFAULT_RANK) if params.level is None else 1


def _budget(params: ViewParams) -> int:
    return int(params.budget * MIB)


def _levels(params: ViewParams):
    return [params.level] if params.level is not None else range(13)


def _region(params: ViewParams) -> tuple[slice, slice] | None:
    return parse_region(params.region) if params.region else None


class _StoreWindow:
    """A compressed store's texels (a region of level 0, whole blocks of the level)."""

    def __init__(self, params: ViewParams, store: str | None, ny: int, nx: int):
        self.params, self.store, self.shape = params, store, (ny, nx)
        ys, xs = _region(params) or (slice(0, ny), slice(0, nx))
        if ys.stop > ny or xs.stop > nx:
            raise BTFError(f"{params.store}: --region {params.region} reaches beyond the "
                           f"{ny} x {nx} texels")
        self.ys, self.xs = ys, xs

    def window(self, level: int) -> tuple[slice, slice]:
        f = 1 << level
        hy, hx = (self.ys.stop - self.ys.start) // f, (self.xs.stop - self.xs.start) // f
        return (slice(self.ys.start, self.ys.start + hy * f),
                slice(self.xs.start, self.xs.start + hx * f))

    def size(self, level: int) -> tuple[int, int]:
        f = 1 << level
        return ((self.ys.stop - self.ys.start) // f) * ((self.xs.stop - self.xs.start) // f), 0

    def load(self, level: int, k: int, session: Session) -> dict:
        import dask.array as da
        import zarr

        from pipeline import storage
        from pipeline.stores.base import location

        ys, xs = self.window(level)
        v = da.from_zarr(zarr.open_array(storage.store(location(self.store)), path="V",
                                         mode="r"))[ys, xs, :k]
        f = 1 << level
        if level:
            v = da.coarsen(np.mean, v.astype(np.float64), {0: f, 1: f}).astype(np.float32)
        (out,) = session.compute(v)
        ny, nx = self.shape
        note = ""
        if self.params.region or level:
            note = (f"texels {ys.start}:{ys.stop}, {xs.start}:{xs.stop} of {ny} x {nx}"
                    + (f" at level {level} (block means of {f}^2)" if level else ""))
        return {"v": np.asarray(out, np.float32)[None], "note": note}


class _TileSet:
    """A compressed tile set: its tiles laid as btf render lays them, or a region of that.

    Quilt's corner sets: tiles in corner-code order, laid by the page's hash on up to 4 x 4
    cells; at a level, every tile's block means. The roller's lattice sets: ``index``, the
    stored (tile, y, x) of every texel of a swatch of whole periods (up to 4 x 4), from
    :func:`tasks.placement.lattice_gather` itself; at a level, the block means of the swatch.
    With ``--region``: those texels of the surface, gathered as btf render gathers them.
    """

    def __init__(self, params: ViewParams, tileset: CompressedTileSetStore):
        self.params, self.tileset = params, tileset
        self.n = tileset.tiles
        self.ty, self.tx = tileset.tile_shape
        self.seed = tileset.seed
        self.lattice = tileset.placement == "lattice"
        self.region = _region(params)
        if not self.lattice:
            self.types = tileset.corner_types
            self.order = tileset.order()
        else:
            h, w, shear = tileset.hnf
            rows = h * (w // math.gcd(shear, w))  # down this far, the lattice is back in column
            self.swatch = (rows * max(1, min(4, 512 // rows)), w * max(1, min(4, 512 // w)))

    def size(self, level: int) -> tuple[int, int]:
        f = 1 << level
        if self.region:
            ys, xs = self.region
            return ((ys.stop - ys.start) // f) * ((xs.stop - xs.start) // f), 0
        if self.lattice:
            if level == 0:
                return self.n * self.ty * self.tx, b64_bytes(4 * self.swatch[0] * self.swatch[1])
            return -(-self.swatch[0] // f) * -(-self.swatch[1] // f), 0
        return self.n * -(-self.ty // f) * -(-self.tx // f), 0

    def _tiles(self, k: int, which=None) -> dict[int, np.ndarray]:
        """Tiles' eigentextures at rank ``k`` by page number.

        Quilt's sets number them by corner code, the roller's as stored; prescribed from the
        sample's where the set keeps only those
        (:func:`pipeline.stores.tileset.tile_eigentextures`).
        """
        ids = [int(i) for i in (range(self.n) if which is None else which)]
        stored = [int(self.order[i]) if not self.lattice else i for i in ids]
        return dict(zip(ids, self.tileset.tile_eigentextures(stored, k), strict=True))

    def _surface(self, k: int, y0: int, x0: int, ny: int, nx: int) -> np.ndarray:
        """Texels ``[y0, y0+ny) x [x0, x0+nx)`` of the surface btf render lays, at rank ``k``."""
        from tasks.placement import gather, lattice_gather, region_tiles

        if not self.lattice:
            need = np.unique(region_tiles(y0, x0, ny, nx, tile_shape=(self.ty, self.tx),
                                          seed=self.seed, corners=self.types))
            return gather(self._tiles(k, need), y0, x0, ny, nx, seed=self.seed,
                          corners=self.types)
        tiles = self._tiles(k)
        return lattice_gather(np.stack([tiles[i] for i in range(self.n)]), y0, x0, ny, nx,
                              hnf=self.tileset.hnf, basis=self.tileset.basis,
                              representative=self.tileset.representative, seed=self.seed)

    def load(self, level: int, k: int, session: Session) -> dict:
        from tasks.placement import lattice_gather

        f = 1 << level
        at = f" at level {level} (block means of {f}^2)" if level else ""
        if self.region:
            ys, xs = self.region
            ny, nx = ((ys.stop - ys.start) // f) * f, ((xs.stop - xs.start) // f) * f
            v = block_means(self._surface(k, ys.start, xs.start, ny, nx), f)
            return {"v": v[None], "note": f"texels {ys.start}:{ys.start + ny}, {xs.start}:"
                    f"{xs.start + nx} of the surface btf render lays (seed {self.seed}){at}"}
        if not self.lattice:
            tiles = self._tiles(k)
            v = np.stack([block_means(tiles[i], f) for i in range(self.n)])
            ty, tx = v.shape[1:3]
            cells = max(1, min(4, 512 // max(ty, tx)))
            return {"v": v, "corners": self.types, "cells": cells,
                    "note": f"{self.n} tiles of {ty} x {tx} texels{at}, {cells} x {cells} laid "
                            f"as btf render lays them (seed {self.seed})"}
        h, w = self.swatch
        what = (f"{self.n} roller tile(s) of {self.ty} x {self.tx} texels on their lattice, "
                f"{h} x {w} texels laid as btf render lays them (seed {self.seed})")
        if level:
            return {"v": block_means(self._surface(k, 0, 0, h, w), f)[None],
                    "note": what + at}
        ids = np.arange(self.n * self.ty * self.tx, dtype=np.int32).reshape(
            self.n, self.ty, self.tx)
        index = lattice_gather(ids, 0, 0, h, w, hnf=self.tileset.hnf,
                               basis=self.tileset.basis,
                               representative=self.tileset.representative, seed=self.seed)
        tiles = self._tiles(k)
        return {"v": np.stack([tiles[i] for i in range(self.n)]), "index":
                index.astype(np.int32), "note": what}


def _check_shown(params: ViewParams, group):
    """The store's directions, channels and transform, checked; the two blending meshes."""
    transform = Transform.from_attrs(group.attrs["transform"])
    d, channels, meshes = _check_directions(params, group)
    if transform.channels and len(channels) != 3:
        raise BTFError(f"{params.store}: transform {transform.name} needs 3 channels, the "
                       f"store has {len(channels)}")
    return d, channels, transform, meshes


def _check_directions(params: ViewParams, group):
    """Directions, channels and blending meshes of any store the page could show, checked."""
    d = read_directions(group)
    channels = list(read_channels(group))
    if len(channels) not in (1, 3):
        raise BTFError(f"{params.store}: the viewer shows 1 or 3 channels, the store has "
                       f"{len(channels)} ({', '.join(channels)})")
    if d.lights == 1:
        raise BTFError(f"{params.store}: 1 light direction cannot be triangulated: there is "
                       "nothing to relight (the viewer blends at least three lights)")
    try:
        meshes = (mesh(d.theta_view, d.phi_view, "view"),
                  mesh(d.theta_light, d.phi_light, "light"))
    except ValueError as exc:
        raise BTFError(f"{params.store}: {exc}") from None
    return d, channels, meshes


def _mesh_blobs(meshes) -> dict[str, np.ndarray]:
    """The sphere's per-cell triangle lists of both meshes (:func:`tasks.viewer.cell_triangles`).

    As uint16: each cell's count (the page adds them up into first items) and the items.
    """
    blobs = {}
    for side, m in zip(("view", "light"), meshes, strict=True):
        spans, items = m.cells  # GRID cells a side, computed once a mesh
        if len(m.triangles) >= 1 << 16:
            raise BTFError(f"{len(m.triangles)} {side} triangles: the page lists at most 65535")
        blobs[f"{side}Counts"] = spans[..., 1].astype(np.uint16)
        blobs[f"{side}Items"] = items.astype(np.uint16)
    return blobs


def _fixed_bytes(d, meshes) -> int:
    """Bytes of a page besides ``V``, ``U diag(S)`` and a roller's index.

    Its script, directions, meshes and their grids: measured on a page without the others,
    with :data:`SLACK` for the notes and numbers that are not known yet.
    """
    return len(_page(_directions_data(d, meshes), _mesh_blobs(meshes))) + SLACK


def _refuse(params: ViewParams, size, rows: int, fixed: int, least: int):
    """Refuse a page over ``--budget``, saying what would make it fit."""
    level = params.level or 0
    texels, extra = size(level)
    need = page_bytes(texels, least, rows, fixed + extra)
    smaller = plan_page(size, rows=rows, fixed=fixed, budget=_budget(params), wanted=least,
                        least=least, levels=range(level + 1, 13))
    advice = (f"show a level of detail (--level {smaller[0]})" if smaller
              else "the rows of U diag(S) alone are too many" if page_bytes(
                  0, least, rows, fixed) > _budget(params) else "show a region")
    raise BTFError(f"{params.store}: the page would hold {need / MIB:.2f} MB at level {level} "
                   f"and rank {least} ({fixed / MIB:.2f} MB of it its script and direction "
                   f"tables), over --budget {params.budget:g} MB; {advice}, a region "
                   "(--region Y0:Y1,X0:X1) or a lower --rank, or raise --budget")


def _channel_energy(group) -> np.ndarray:
    """Each channel's part of each component's energy, ``S_i^2 |U[..., c, i]|^2`` ``(C, K)``.

    ``U`` is read a chunk of views at a time (a tile set's ``U`` is one chunk: reading it a
    view at a time decompressed it once per view, 43 s for 151 views at rank 448).
    """
    u = group["U"]
    s = np.asarray(group["S"][...], np.float64)
    out = np.zeros((u.shape[2], u.shape[3]))
    step = u.chunks[0]
    for v0 in range(0, u.shape[0], step):
        block = np.asarray(u[v0 : v0 + step], np.float32)
        out += np.einsum("vlck,vlck->ck", block, block, dtype=np.float64)
    return out * s**2


def _percent(share: float) -> str:
    """A share near 1 with the digits that show how near."""
    if share > 1 - 5e-7:
        return "100%"
    digits = min(6, max(1, math.ceil(-math.log10(max(1 - share, 1e-9))) - 2))
    return f"{100 * share:.{digits}f}%"


def _rank_note(params: ViewParams, k: int, s: np.ndarray, total: float,
               energy_rank: int) -> str:
    """What rank the page shows against the store's, the energy kept, and what was dropped."""
    stored = len(s)
    kept = float(np.sum(s[:k].astype(np.float64) ** 2)) / total
    held = float(np.sum(s.astype(np.float64) ** 2)) / total
    if params.rank:
        why = "as --rank asks"
    elif k < min(energy_rank, MAX_RANK):
        why = f"as many as fit --budget {params.budget:g} MB"
    elif k == stored:
        why = "all of them"
    elif energy_rank > MAX_RANK:
        why = f"the shader's limit of {MAX_RANK}"
    else:
        why = f"the fewest that keep {_percent(ENERGY_KEPT)} of it, and of every channel's"
    note = (f"rank {k} of the store's {stored} ({why}): {_percent(kept)} of the energy "
            f"(sum of S^2 over ||A||^2) kept")
    if k < stored:
        note += (f"; {stored - k} component(s) dropped, {100 * (held - kept):.2g}% of the "
                 "energy")
    if held < 1:
        note += f" (the store's {stored} hold {_percent(held)})"
    return note


def _write_page(params: ViewParams, store: CompressedStore | CompressedTileSetStore,
                session: Session, *, name: str | None = None) -> Path:
    """The page of the compressed store or tile set ``store`` (``name``: the one given)."""
    group = store.group
    d, channels, transform, meshes = _check_shown(params, group)
    s = np.asarray(group["S"][...], np.float32)
    stored, total = len(s), total_energy(group, np.asarray(s, np.float64))
    if params.rank is not None and params.rank > stored:
        raise BTFError(f"{params.store}: --rank {params.rank} is larger than the store's "
                       f"rank {stored}")
    tiled = isinstance(store, CompressedTileSetStore)
    shown = _TileSet(params, store) if tiled else _StoreWindow(params, store.path,
                                                              *group["V"].shape[-3:-1])
    rows = int(np.prod(group["U"].shape[:-1]))
    blobs = _mesh_blobs(meshes)
    fixed = _fixed_bytes(d, meshes)
    energy_rank = shown_rank(s, total, most=stored, channels=_channel_energy(group))
    wanted = params.rank or min(energy_rank, MAX_RANK)
    least = _least(params, wanted)
    plan = plan_page(shown.size, rows=rows, fixed=fixed, budget=_budget(params), wanted=wanted,
                     least=least, levels=_levels(params))
    if plan is None:
        _refuse(params, shown.size, rows, fixed, least)
    level, k = plan
    us = np.asarray(group["U"][..., :k], np.float32) * s[:k]
    page = shown.load(level, k, session)
    v = page["v"]
    iv, il = _initial_pair(d)
    light_scale = transform.layer_scale(d.theta_light)  # a cosine store's; else None
    first = reconstruct_layers(us[iv, il][None], np.ones(k, np.float32), v[0],
                               transform=transform)
    scale = params.exposure or exposure(first * (1 if light_scale is None else light_scale[il]))
    rank_note = _rank_note(params, k, s, total, energy_rank)
    cells = page.get("cells", 1)
    index = page.get("index")
    height, width = (index.shape if index is not None
                     else (v.shape[1] * cells, v.shape[2] * cells))
    data = {
        "name": Path(str(name or params.store).rstrip("/")).name, "note": page["note"],
        "rankNote": rank_note[0].upper() + rank_note[1:] + ".",
        "width": int(width), "height": int(height), "rank": k, "storeRank": stored,
        "level": level, "tileWidth": int(v.shape[2]), "tileHeight": int(v.shape[1]),
        "tiles": len(v), "corners": page.get("corners", 1), "seed": str(shown.seed if tiled
                                                                      else 0),
        "indexed": index is not None, "channels": len(channels), "transform": transform.name,
        "eps": transform.eps, "exposure": float(scale), **_directions_data(d, meshes),
        "lightScale": None if light_scale is None else light_scale.tolist(),
    }
    try:
        blobs = {"V": np.concatenate([pack_eigentextures(t) for t in v]), "US": us, **blobs}
    except ValueError as exc:  # beyond half floats' range
        raise BTFError(f"{params.store}: variable 'V': {exc}") from None
    if index is not None:
        blobs["index"] = index
    html = _page(data, blobs)
    if len(html) > _budget(params):  # the estimate is exact but for the JSON's few numbers
        raise BTFError(f"{params.store}: the page holds {len(html) / MIB:.2f} MB, over "
                       f"--budget {params.budget:g} MB; lower --rank or raise --budget")
    session.log(f"view: {d.views} x {d.lights} directions, {v.shape[1]} x {v.shape[2]} texels"
                f"{f' x {len(v)} tiles' if len(v) > 1 else ''} at {rank_note} -> {params.out} "
                f"({len(html) / MIB:.1f} MB)" + (f"; {page['note']}" if page["note"] else ""))
    write_whole(params.out, html.encode("utf-8"), params.overwrite)
    return Path(params.out)


def _directions_data(d, meshes) -> dict:
    """The page's directions: angles, disk points, blending meshes, and the initial pair."""
    iv, il = _initial_pair(d)
    view_mesh, light_mesh = meshes
    return {
        "views": np.stack([d.theta_view, d.phi_view], -1).tolist(),
        "lights": np.stack([d.theta_light, d.phi_light], -1).tolist(),
        "viewDisk": view_mesh.points[:d.views].tolist(),
        "lightDisk": light_mesh.points[:d.lights].tolist(),
        "viewMesh": view_mesh.to_dict(), "lightMesh": light_mesh.to_dict(),
        "grid": GRID,
        "initial": {"view": [float(d.theta_view[iv]), float(d.phi_view[iv])],
                    "light": [float(d.theta_light[il]), float(d.phi_light[il])]},
    }


STAGE = Stage("view", ViewParams, view,
              "write an HTML page that relights a compressed store in the browser",
              "Write one self-contained HTML file (WebGL2, no network) showing the material "
              "under a light and from a view that you drag over the hemisphere, with an "
              "exposure control, as a swatch or round a sphere. Measured directions are drawn "
              "on the hemispheres; between them the page blends measured pairs (barycentric "
              "weights over a Delaunay triangulation, continued past the last measured ring). "
              "The address sets the light, view, exposure, mode and repeats: "
              "OUT.html#light=THETA,PHI&view=THETA,PHI&exposure=E&mode=M&repeat=N (degrees). "
              "Without --rank the page shows the fewest components that keep 99.99% of the "
              "store's energy, at most 64 and what fits --budget, at level 0 unless fewer than "
              "8 would fit there; it says the rank, the energy kept and what was dropped. "
              "--level shows block means, --region a part (of a tile set: of the surface btf "
              "render lays). A radiance store is compressed on the way (btf compress keeps "
              "the compressed store for other uses).")

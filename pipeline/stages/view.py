"""``btf view``: one self-contained HTML page that relights a compressed BTF in the browser.

The page holds the eigentextures ``V`` (half floats, four components a texture layer) and the
rows ``U diag(S)`` of every measured (view, light) pair; its WebGL2 shader computes each
texel's values as one dot product of length ``k`` per channel, decodes them with the store's
transform and tone-maps them as the report does (:func:`tasks.tonemap.tonemap`). Between
measured directions it blends measured pairs (:mod:`tasks.viewer`). A store too large for the
page is shown at a level of detail (``--level``: block means of ``V``, exact for the values)
or a region (``--region``). A radiance store is compressed at ``--rank`` on the way, into a
temporary store that is removed with the page written.
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
from pipeline.stores.base import open_group, read_channels, read_directions
from pipeline.stores.compressed import check_compressed
from tasks.svd import reconstruct_layers
from tasks.tonemap import exposure
from tasks.transform import Transform
from tasks.viewer import disk, pack_eigentextures, triangle_grid, triangulate

MIB = 1 << 20
DEFAULT_RANK = 16
MAX_RANK = 64
GRID = 128  # cells per side of the surface mode's direction -> triangle grids


@dataclasses.dataclass(frozen=True)
class ViewParams:
    """Parameters of ``btf view``."""

    store: str = option(help="compressed store (btf compress, btf ingest), or a radiance store "
                             "to compress at --rank on the way", positional=True, path="in")
    out: str = option(help="HTML file to write", positional=True, path="out", metavar="OUT.html")
    rank: int | None = option(None, metavar="R",
                              help="components shown (default: 16, or a compressed store's rank if "
                                   "lower)")
    level: int = option(0, help="level of detail: texels are block means of 2^level per side")
    region: str | None = option(None, metavar="Y0:Y1,X0:X1",
                                help="texel region of level 0, ends exclusive (default: all)")
    budget: float = option(25.0, metavar="MB", help="largest page to write, in MB")
    exposure: float | None = option(None, help="initial exposure scale (default: automatic)")
    overwrite: bool = option(False, record=False, help="replace OUT if it exists")

    def __post_init__(self):
        check_region(self.region)
        if self.rank is not None and not 1 <= self.rank <= MAX_RANK:
            raise ParamError("rank", f"must be between 1 and {MAX_RANK} (the shader's rows of U "
                             f"are uniforms and registers), got {self.rank}")
        if not 0 <= self.level <= 12:
            raise ParamError("level", f"must be between 0 and 12, got {self.level}")
        if not self.budget > 0:
            raise ParamError("budget", f"must be positive, got {self.budget}")
        if self.exposure is not None and not self.exposure > 0:
            raise ParamError("exposure", f"must be positive, got {self.exposure}")


def _window(params: ViewParams, ny: int, nx: int) -> tuple[slice, slice]:
    """The texel region of level 0 shown, whole blocks of the level only."""
    ys, xs = parse_region(params.region) if params.region else (slice(0, ny), slice(0, nx))
    if ys.stop > ny or xs.stop > nx:
        raise BTFError(f"{params.store}: --region {params.region} reaches beyond the "
                       f"{ny} x {nx} texels")
    f = 1 << params.level
    hy, hx = (ys.stop - ys.start) // f, (xs.stop - xs.start) // f
    if hy < 1 or hx < 1:
        raise BTFError(f"{params.store}: level {params.level} leaves no texel of the "
                       f"{ys.stop - ys.start} x {xs.stop - xs.start} region")
    return slice(ys.start, ys.start + hy * f), slice(xs.start, xs.start + hx * f)


def _eigentextures(params: ViewParams, store: str, rank: int, ys: slice, xs: slice,
                   session: Session) -> np.ndarray:
    """``V`` of the region at the level, ``(y, x, rank)`` float32, read block by block."""
    import dask.array as da
    import zarr

    from pipeline import storage
    from pipeline.stores.base import location

    v = da.from_zarr(zarr.open_array(storage.store(location(store)), path="V",
                                     mode="r"))[ys, xs, :rank]
    if params.level:
        f = 1 << params.level
        v = da.coarsen(np.mean, v.astype(np.float64), {0: f, 1: f}).astype(np.float32)
    (out,) = session.compute(v)
    return np.asarray(out, np.float32)


def _page_size(v_shape: tuple[int, int, int], us_size: int) -> int:
    """Bytes of the page's data: base64 of the half-float ``V`` and float32 ``U diag(S)``."""
    ny, nx, k = v_shape
    raw = ny * nx * -(-k // 4) * 4 * 2 + us_size * 4
    return raw * 4 // 3


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
    """Write the relighting page of a compressed store (a radiance store is compressed first)."""
    from pipeline import storage

    if not params.overwrite and storage.exists(storage.parse(params.out, what="output")):
        raise BTFError(f"{params.out}: already exists; pass --overwrite to replace it")
    group = open_group(params.store)
    kind = group.attrs.get("btf_kind")
    if kind == "compressed":
        return _write_page(params, params.store, group, session)
    if kind == "compressed-tileset":
        from pipeline.stores.tileset import check_tileset

        check_tileset(group, params.store)
        if params.level or params.region:
            raise BTFError(f"{params.store}: --level and --region apply to a store, not to a "
                           "tile set, whose tiles are shown whole")
        return _write_page(params, params.store, group, session, tiled=True)
    if kind == "tileset":
        raise BTFError(f"{params.store}: a tile set of radiance; btf view lays compressed tile "
                       "sets: quilt the compressed store (btf compress, then btf quilt "
                       "COMPRESSED.zarr TILES.zarr)")
    if kind not in ("btf", "abtf"):
        raise BTFError(f"{params.store}: btf view shows a compressed or a radiance store; this "
                       f"is a {kind or 'non-BTF'} store")
    return _compressed_on_the_way(params, group, session)


def _compressed_on_the_way(params: ViewParams, group, session: Session) -> Path:
    """Compress a radiance store at the page's rank into a temporary store, then the page."""
    import tempfile

    from pipeline.stages import STAGES  # by name, as btf run composes stages
    from pipeline.stores.radiance import check_radiance

    check_radiance(group, params.store)
    _check_directions(params, group)  # before the compression, not after it
    nv, nl, ny, nx, nc = group["radiance"].shape
    k = params.rank or min(DEFAULT_RANK, nv * nl * nc, ny * nx)
    ys, xs = _window(params, ny, nx)
    f = 1 << params.level
    size = _page_size(((ys.stop - ys.start) // f, (xs.stop - xs.start) // f, k), nv * nl * nc * k)
    _check_budget(params, size)  # before the compression, not after it
    with tempfile.TemporaryDirectory(prefix="btf-view-") as tmp:
        compressed = str(Path(tmp) / "compressed.zarr")
        session.log(f"view: {params.store} is a radiance store: compressing it at rank {k} "
                    f"first (btf compress {params.store} OUT.zarr --rank {k} keeps it)")
        compress = STAGES["compress"]
        compress.run(compress.params(store=params.store, out=compressed, rank=k), session)
        return _write_page(dataclasses.replace(params, rank=k), compressed,
                           open_group(compressed), session, name=params.store)


@dataclasses.dataclass(frozen=True)
class _Tiles:
    """A tile set as the page lays it.

    Quilt's corner sets: tiles in corner-code order, ``corners`` types, the seed, laid by the
    page's hash on ``cells`` x ``cells`` cells. The roller's lattice sets: ``index``, the
    stored (tile, y, x) of every texel of the swatch (``tile * ty * tx + y * tx + x``), from
    :func:`tasks.placement.lattice_gather` itself.
    """

    v: np.ndarray  # (tile, y, x, k) float32
    corners: int
    seed: int
    cells: int
    index: np.ndarray | None = None

    @property
    def note(self) -> str:
        """What the page shows of the set."""
        n, ty, tx = self.v.shape[:3]
        if self.index is not None:
            return (f"{n} roller tile(s) of {ty} x {tx} texels on their lattice, "
                    f"{self.index.shape[0]} x {self.index.shape[1]} texels laid as btf render "
                    f"lays them (seed {self.seed})")
        return (f"{n} tiles of {ty} x {tx} texels, {self.cells} x {self.cells} laid as btf "
                f"render lays them (seed {self.seed})")


def _tile_set(params: ViewParams, group, rank: int) -> _Tiles:
    """The page's view of a compressed tile set (btf quilt or btf roller of a compressed store)."""
    from pipeline.stores.tileset import corner_order, stored_seed, tile_eigentextures
    from tasks.placement import lattice_gather

    # every tile's first eigentextures (prescribed from the sample's): within the budget
    v = tile_eigentextures(group, range(group["corners"].shape[0]), rank)
    n, ty, tx = v.shape[:3]
    seed = stored_seed(group)
    if group.attrs.get("placement") != "lattice":
        types = int(group.attrs["corner_types"])
        order = corner_order(params.store, group["corners"][...], types)
        return _Tiles(v[order], types, seed, max(1, min(4, 512 // max(ty, tx))))
    spec = group.attrs["lattice"]
    h, w, shear = spec["hnf"]
    rows = h * (w // math.gcd(shear, w))  # down this far, the lattice is back in column
    ids = np.arange(n * ty * tx, dtype=np.int32).reshape(n, ty, tx)
    index = lattice_gather(ids, 0, 0, rows * max(1, min(4, 512 // rows)),
                           w * max(1, min(4, 512 // w)),
                           hnf=tuple(spec["hnf"]), basis=(tuple(spec["U"]), tuple(spec["V"])),
                           representative=group["representative"][...]
                           if "representative" in group.array_keys() else None, seed=seed)
    return _Tiles(v, 1, seed, 1, index.astype(np.int32))


def _check_budget(params: ViewParams, size: int, tiled: bool = False) -> None:
    """Refuse a page over ``--budget``, saying what would make it smaller."""
    if size > params.budget * MIB:
        smaller = ("lower --rank" if tiled  # a tile set is shown whole
                   else f"show a level of detail (--level {params.level + 1}) or a region "
                        "(--region Y0:Y1,X0:X1)")
        raise BTFError(f"{params.store}: the page would hold {size / MIB:.1f} MB of data, over "
                       f"--budget {params.budget:g} MB; {smaller}, or raise --budget")


def _check_shown(params: ViewParams, group, store: str, tiles: bool):
    """The store's directions, channels and transform, checked; the two triangulations."""
    if not tiles:
        check_compressed(group, store)
    transform = Transform.from_attrs(group.attrs["transform"])
    d, channels, triangles = _check_directions(params, group)
    if transform.channels and len(channels) != 3:
        raise BTFError(f"{params.store}: transform {transform.name} needs 3 channels, the "
                       f"store has {len(channels)}")
    return d, channels, transform, triangles


def _check_directions(params: ViewParams, group):
    """Directions, channels and triangulations of any store the page could show, checked."""
    d = read_directions(group)
    channels = list(read_channels(group))
    if len(channels) not in (1, 3):
        raise BTFError(f"{params.store}: the viewer shows 1 or 3 channels, the store has "
                       f"{len(channels)} ({', '.join(channels)})")
    if d.lights == 1:
        raise BTFError(f"{params.store}: 1 light direction cannot be triangulated: there is "
                       "nothing to relight (the viewer blends at least three lights)")
    try:
        triangles = (triangulate(d.theta_view, d.phi_view, "view"),
                     triangulate(d.theta_light, d.phi_light, "light"))
    except ValueError as exc:
        raise BTFError(f"{params.store}: {exc}") from None
    return d, channels, triangles


def _rank(params: ViewParams, group) -> int:
    stored = group["S"].shape[0]
    if params.rank is not None and params.rank > stored:
        raise BTFError(f"{params.store}: --rank {params.rank} is larger than the store's "
                       f"rank {stored}")
    return params.rank or min(DEFAULT_RANK, stored)


def _directions_data(d, triangles) -> dict:
    """The page's directions: angles, disk points, triangles, and the initial pair."""
    iv, il = _initial_pair(d)
    view_tris, light_tris = triangles
    return {
        "views": np.stack([d.theta_view, d.phi_view], -1).tolist(),
        "lights": np.stack([d.theta_light, d.phi_light], -1).tolist(),
        "viewDisk": disk(d.theta_view, d.phi_view).tolist(),
        "lightDisk": disk(d.theta_light, d.phi_light).tolist(),
        "viewTriangles": view_tris.tolist(), "lightTriangles": light_tris.tolist(),
        "grid": GRID,
        "initial": {"view": [float(d.theta_view[iv]), float(d.phi_view[iv])],
                    "light": [float(d.theta_light[il]), float(d.phi_light[il])]},
    }


def _write_page(params: ViewParams, store: str, group, session: Session, *,
                name: str | None = None, tiled: bool = False) -> Path:
    """The page of the compressed store or tile set ``store`` (``name``: the one given)."""
    d, channels, transform, triangles = _check_shown(params, group, store, tiled)
    k = _rank(params, group)
    ny, nx = group.attrs["tile_shape"] if tiled else group["V"].shape[:2]
    ys, xs = _window(params, ny, nx)
    f = 1 << params.level
    count = group["corners"].shape[0] if tiled else 1
    _check_budget(params, count * _page_size(
        ((ys.stop - ys.start) // f, (xs.stop - xs.start) // f, k), 0)
        + _page_size((0, 0, k), int(np.prod(group["U"].shape[:-1])) * k), tiled)
    us = np.asarray(group["U"][..., :k], np.float32) * np.asarray(group["S"][:k], np.float32)
    tiles = _tile_set(params, group, k) if tiled else None
    v = tiles.v if tiles else _eigentextures(params, store, k, ys, xs, session)[None]
    iv, il = _initial_pair(d)
    scale = params.exposure or exposure(
        reconstruct_layers(us[iv, il][None], np.ones(k, np.float32), v[0], transform=transform))
    note = tiles.note if tiles else ""
    if params.level or params.region:
        note = (f"texels {ys.start}:{ys.stop}, {xs.start}:{xs.stop} of {ny} x {nx}"
                + (f" at level {params.level} (block means of {f}^2)" if params.level else ""))
    height, width = (tiles.index.shape if tiles and tiles.index is not None
                     else (v.shape[1] * (tiles.cells if tiles else 1),
                           v.shape[2] * (tiles.cells if tiles else 1)))
    data = {
        "name": Path(str(name or params.store).rstrip("/")).name, "note": note,
        "width": int(width), "height": int(height), "rank": k,
        "tileWidth": int(v.shape[2]), "tileHeight": int(v.shape[1]), "tiles": len(v),
        "corners": tiles.corners if tiles else 1, "seed": str(tiles.seed if tiles else 0),
        "indexed": bool(tiles and tiles.index is not None),
        "channels": len(channels), "transform": transform.name, "eps": transform.eps,
        "exposure": float(scale), **_directions_data(d, triangles),
    }
    try:
        blobs = {"V": np.concatenate([pack_eigentextures(t) for t in v]), "US": us}
    except ValueError as exc:  # beyond half floats' range
        raise BTFError(f"{params.store}: variable 'V': {exc}") from None
    for side, t, p, tris in (("light", d.theta_light, d.phi_light, triangles[1]),
                             ("view", d.theta_view, d.phi_view, triangles[0])):
        blobs[f"{side}Grid"] = triangle_grid(disk(t, p), tris, GRID)
    if data["indexed"]:
        blobs["index"] = tiles.index
    html = _page(data, blobs)
    _check_budget(params, len(html), tiled)  # with what the estimate left out (grids, script)
    session.log(f"view: {d.views} x {d.lights} directions, {v.shape[1]} x {v.shape[2]} texels "
                f"at rank {k} -> {params.out} ({len(html) / MIB:.1f} MB)"
                + (f"; {note}" if note else ""))
    write_whole(params.out, html.encode("utf-8"), params.overwrite)
    return Path(params.out)


STAGE = Stage("view", ViewParams, view,
              "write an HTML page that relights a compressed store in the browser",
              "Write one self-contained HTML file (WebGL2, no network) showing the material "
              "under a light and from a view that you drag over the hemisphere, with an "
              "exposure control. Measured directions are drawn on the hemispheres; between "
              "them the page blends measured pairs (barycentric weights over a Delaunay "
              "triangulation). The initial light, view and exposure come from the URL: "
              "OUT.html#light=THETA,PHI&view=THETA,PHI&exposure=E (degrees). A store larger "
              "than --budget is refused: show a level of detail (--level) or a region "
              "(--region). A radiance store is compressed at --rank on the way (btf compress "
              "keeps the compressed store for other uses).")

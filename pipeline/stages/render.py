"""``btf render``: one layer of a surface of any size covered by a tile set.

Tiles are placed by a hash of their lattice coordinates and the seed
(:mod:`tasks.placement`), so any region of the unbounded surface can be rendered on its own and
regions that overlap agree. Only the requested layer of the tile set is read. Output: EXR (the
region in memory), PNG (tone-mapped preview) or a zarr store written block by block, for regions
too large to hold (a surface store, :mod:`pipeline.stores.surface`).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from pipeline.atomic import atomic_output
from pipeline.graphs.blocks import store_aligned
from pipeline.graphs.surface import lazy_layer
from pipeline.images import write_exr, write_png
from pipeline.params import ParamError, check_seed, option
from pipeline.provenance import provenance
from pipeline.session import Session
from pipeline.stage import Stage
from pipeline.stores import TileSetStore, open_store
from pipeline.stores.surface import create_surface_store
from tasks.tonemap import exposure, to_uint8, tonemap


@dataclasses.dataclass(frozen=True)
class RenderParams:
    """Parameters of ``btf render``."""

    store: str = option(help="tile-set store (made by btf quilt or btf roller)",
                        positional=True, path="in", metavar="TILESET")
    out: str = option(help="output: .exr, .png (tone-mapped) or .zarr (any size, written "
                           "block by block)", positional=True, path="out")
    light: int = option(metavar="I", help="light index")
    size: tuple[int, ...] = option(metavar="H,W", help="size of the region in texels")
    view: int = option(0, metavar="J", help="view index")
    origin: tuple[int, ...] = option((0, 0), metavar="Y,X",
                                     help="first texel of the region on the surface")
    seed: int | None = option(None, metavar="S",
                              help="seed of the tile placement (default: the tile set's)")
    chunk: int = option(2048, metavar="N", help="texels per side of a block computed at once")
    overwrite: bool = option(False, record=False, help="replace OUT if it exists")

    def __post_init__(self):
        if len(self.size) not in (1, 2) or min(self.size) < 1:
            raise ParamError("size", f"expected H,W (positive), got {self.size}")
        if len(self.origin) != 2:
            raise ParamError("origin", f"expected Y,X, got {self.origin}")
        suffix = Path(self.out).suffix.lower()
        if suffix not in (".exr", ".png", ".zarr"):
            raise ParamError("out", f"must end in .exr, .png or .zarr, got {self.out!r}")
        check_seed(self.seed)
        if self.chunk < 16:
            raise ParamError("chunk", f"must be at least 16, got {self.chunk}")


def render(params: RenderParams, session: Session) -> Path:
    """Render the requested region of one layer."""
    tileset = open_store(params.store, TileSetStore)
    h, w = params.size[0], params.size[-1]
    layer = lazy_layer(tileset, view=params.view, light=params.light, size=(h, w),
                       origin=tuple(params.origin), seed=params.seed, chunk=params.chunk)
    channels = tileset.channels
    suffix = Path(params.out).suffix.lower()
    session.log(f"render: light {params.light}, view {params.view}, {h} x {w} texels at "
                f"{tuple(params.origin)} -> {params.out}")
    if suffix == ".zarr":
        with atomic_output(params.out, directory=True, overwrite=params.overwrite) as tmp:
            attrs = {"source": "render", "tileset": params.store, "light": params.light,
                     "view": params.view, "origin": list(params.origin),
                     "seed": params.seed if params.seed is not None else tileset.seed,
                     "provenance": provenance("render", params)}
            target = create_surface_store(
                tmp, layer.shape, channels, chunk=params.chunk, attrs=attrs,
                directions=tileset.directions.select([params.view], [params.light]))
            session.compute(store_aligned([layer], [target]))
        return Path(params.out)
    (pixels,) = session.compute(layer)
    with atomic_output(params.out, directory=False, overwrite=params.overwrite) as tmp:
        if suffix == ".exr":
            write_exr(tmp, pixels, channels)
        else:
            image = to_uint8(tonemap(pixels, scale=exposure(pixels[::4, ::4])))
            write_png(tmp, image[..., 0] if image.shape[-1] == 1 else image)
    return Path(params.out)


STAGE = Stage("render", RenderParams, render,
              "render one layer of a surface of any size from a tile set",
              "Render one layer (--light, --view) of an unbounded surface covered by a tile "
              "set, over a region of any size (--size, --origin): each tile is chosen by a hash "
              "of its lattice position and --seed so corners always match, and only that layer "
              "of the tile set is read. EXR, tone-mapped PNG, or .zarr written block by block.")

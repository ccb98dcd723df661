"""``btf render``: one layer of a surface of any size covered by a tile set.

Tiles are placed by a hash of their lattice coordinates and the seed
(:mod:`tasks.placement`), so any region of the unbounded surface can be rendered on its own and
regions that overlap agree. Only the requested layer of the tile set is read. Output: EXR (the
region in memory), PNG (tone-mapped preview) or a zarr array written block by block, for regions
too large to hold.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from pipeline.atomic import atomic_output
from pipeline.images import write_exr, write_png
from pipeline.params import ParamError, option
from pipeline.runtime import Session
from pipeline.store import location
from pipeline.tileset import lazy_layer, open_tileset
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
        if self.seed is not None and not 0 <= self.seed < 2**63:
            raise ParamError("seed", f"must be between 0 and 2**63 - 1, got {self.seed}")
        if self.chunk < 16:
            raise ParamError("chunk", f"must be at least 16, got {self.chunk}")


def render(params: RenderParams, session: Session) -> Path:
    """Render the requested region of one layer."""
    group = open_tileset(params.store)
    h, w = params.size[0], params.size[-1]
    layer = lazy_layer(params.store, view=params.view, light=params.light, size=(h, w),
                       origin=tuple(params.origin), seed=params.seed, chunk=params.chunk)
    channels = tuple(str(c) for c in group["channel"][:])
    suffix = Path(params.out).suffix.lower()
    session.log(f"render: light {params.light}, view {params.view}, {h} x {w} texels at "
                f"{tuple(params.origin)} -> {params.out}")
    if suffix == ".zarr":
        import zarr

        from pipeline.store import store_aligned

        with atomic_output(params.out, directory=True, overwrite=params.overwrite) as tmp:
            target = zarr.create_array(location(tmp), shape=layer.shape, dtype="float32",
                                       chunks=(min(params.chunk, h), min(params.chunk, w),
                                               len(channels)),
                                       dimension_names=("y", "x", "channel"))
            target.attrs.update({"source": "render", "tileset": params.store,
                                 "light": params.light, "view": params.view,
                                 "origin": list(params.origin), "seed": params.seed,
                                 "channels": list(channels)})
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


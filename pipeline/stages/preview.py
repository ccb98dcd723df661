"""``btf preview``: a contact sheet of layers spread over the directions.

Thumbnails are block means (no aliasing), all tone-mapped with one exposure, so they stay
comparable; each is labelled with its light and view directions.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

from pipeline.atomic import atomic_output
from pipeline.graphs.blocks import read_chunks
from pipeline.graphs.thumbnails import thumbnail
from pipeline.params import ParamError, option
from pipeline.session import Session
from pipeline.stage import Stage
from pipeline.stores import CompressedStore, RadianceStore, open_store
from pipeline.stores.base import Directions
from tasks.sampling import spread_pairs
from tasks.tonemap import exposure, tonemap


@dataclasses.dataclass(frozen=True)
class PreviewParams:
    """Parameters of ``btf preview``."""

    store: str = option(help="radiance or compressed store to preview", positional=True,
                        path="in")
    out: str = option(help="PNG file for the contact sheet", positional=True, path="out")
    count: int = option(12, help="number of layers on the sheet, spread over the directions")
    size: int = option(256, help="largest side of each thumbnail in pixels")
    exposure: float | None = option(None, help="exposure scale (default: automatic)")
    overwrite: bool = option(False, record=False, help="replace OUT if it exists")

    def __post_init__(self):
        if not 1 <= self.count <= 64:
            raise ParamError("count", f"must be between 1 and 64, got {self.count}")
        if self.size < 16:
            raise ParamError("size", f"must be at least 16 pixels, got {self.size}")


def preview(params: PreviewParams, session: Session) -> Path:
    """Draw a contact sheet of a spread of layers with their directions as labels."""
    import dask.array as da
    from matplotlib.figure import Figure

    store = open_store(params.store, RadianceStore, CompressedStore)
    ds = store.dataset(read_chunks)  # a compressed store's layers: rebuilt from U, S, V
    d = Directions.of(ds)
    layers = spread_pairs(d.theta_view, d.phi_view, d.theta_light, d.phi_light, params.count)
    thumbs = da.stack([thumbnail(ds, v, li, params.size) for v, li in layers])
    session.log(f"preview: {len(layers)} layers of {params.store} -> {params.out}")
    (images,) = session.compute(thumbs)
    scale = params.exposure or exposure(images)
    cols = min(len(layers), 4 if len(layers) <= 8 else 6)
    rows = math.ceil(len(layers) / cols)
    fig = Figure(figsize=(2.6 * cols, 2.9 * rows + 0.6), dpi=100, layout="constrained")
    attrs = store.attrs
    title = f"{Path(params.store).name}: {store.kind}"
    if "material" in attrs:
        title += f", {attrs['material'].get('name', 'photo')}"
    if "sampling" in attrs:
        title += f", {attrs['sampling']}"
    fig.suptitle(f"{title} (exposure x{scale:.3g})", fontsize=11)
    for k, ((v, li), image) in enumerate(zip(layers, images, strict=True)):
        ax = fig.add_subplot(rows, cols, k + 1)
        shown = tonemap(image, scale=scale)
        ax.imshow(shown[..., 0] if shown.shape[-1] == 1 else shown,
                  cmap="gray" if shown.shape[-1] == 1 else None, vmin=0, vmax=1,
                  interpolation="nearest")
        ax.set_title(f"light θ={d.theta_light[li]:.0f}° φ={d.phi_light[li]:.0f}°\n"
                     f"view θ={d.theta_view[v]:.0f}° φ={d.phi_view[v]:.0f}°", fontsize=8)
        ax.set_axis_off()
    with atomic_output(params.out, directory=False, overwrite=params.overwrite) as tmp:
        fig.savefig(tmp, format="png")
    return Path(params.out)


STAGE = Stage("preview", PreviewParams, preview,
              "draw a contact sheet of a spread of directions",
              "Draw a contact sheet of layers spread over the directions (farthest-point "
              "sampling), labelled with their angles, all with one exposure; a compressed "
              "store's layers are rebuilt from its factors (only those shown).")

"""Thumbnails of layers: block means, so that nothing aliases."""

from __future__ import annotations

import math

from pipeline.stores.base import RADIANCE


def thumbnail(ds, view: int, light: int, size: int):
    """A layer averaged down to at most ``size`` texels a side (lazy; no aliasing)."""
    layer = ds[RADIANCE].isel(view=view, light=light)
    factor = max(1, math.ceil(max(layer.sizes["y"], layer.sizes["x"]) / size))
    if factor == 1:
        return layer.data
    return layer.coarsen(y=factor, x=factor, boundary="trim").mean().data

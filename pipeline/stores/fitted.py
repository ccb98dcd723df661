"""HLS-fit stores (``btf_kind: hls-fit``, paper 003, section 2.5), and the radiance they give.

``hue``, ``saturation`` ``(view, y, x)`` and ``lightness`` ``(view, rotation, coefficient, y,
x)``, float32, chunked like the source's texels; the source's direction coordinates and
``channel`` labels (R, G, B); attrs with the rotation azimuths and elevations, the light grid
(which light is which rotation and elevation), the fit error and the provenance.
:func:`open_fitted` rebuilds radiance lazily (:func:`tasks.hls.rebuild`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from pipeline import storage
from pipeline.stores.base import (
    DIRECTION_COORDS,
    RADIANCE,
    RADIANCE_DIMS,
    Directions,
    Store,
    add_array,
    check_kind,
    create_store,
    location,
    open_group,
    read_directions,
    sampling_lines,
    sampling_summary,
)
from tasks.hls import PARAMETERS, rebuild

NAME = "hls-fit"
CHANNELS = ("R", "G", "B")
DIMS = {"hue": ("view", "y", "x"), "saturation": ("view", "y", "x"),
        "lightness": ("view", "rotation", "coefficient", "y", "x")}


def create_fitted_store(path, *, directions: Directions, ny: int, nx: int, rotations: int,
                        chunk: tuple[int, int], attrs: dict[str, Any]):
    """Create an empty HLS-fit store; returns the zarr group."""
    group = create_store(path, kind=NAME, attrs=attrs, directions=directions,
                         channels=CHANNELS)
    nv = directions.views
    add_array(group, "hue", shape=(nv, ny, nx), dims=DIMS["hue"], chunks=(1, *chunk))
    add_array(group, "saturation", shape=(nv, ny, nx), dims=DIMS["saturation"],
              chunks=(1, *chunk))
    add_array(group, "lightness", shape=(nv, rotations, PARAMETERS, ny, nx),
              dims=DIMS["lightness"], chunks=(1, rotations, PARAMETERS, *chunk))
    return group


def check_fitted(group, path: str | Path) -> None:
    """Raise :class:`BTFError` naming what is wrong if ``group`` is not an HLS-fit store."""
    check_kind(group, path, NAME, "an HLS-fit store", "btf fit", DIMS)


def _rebuild_block(h, s, coef, *, grid, elevations):
    return rebuild(h[0], s[0], coef[0], grid, elevations)[None]


def open_fitted(path: str | Path):
    """A fitted store as a Dataset with a lazy ``radiance`` ``(view, light, y, x, channel)``."""
    import dask.array as da
    import xarray as xr
    import zarr

    group = open_group(path)
    check_fitted(group, path)
    store = storage.store(location(path))
    arrays = {n: da.from_zarr(zarr.open_array(store, path=n, mode="r")) for n in DIMS}
    grid = np.asarray(group.attrs["light_grid"])
    elevations = np.asarray(group.attrs["elevations"])
    radiance = da.blockwise(
        _rebuild_block, "vlyxc", arrays["hue"], "vyx", arrays["saturation"], "vyx",
        arrays["lightness"], "vrpyx", new_axes={"l": grid.size, "c": 3}, concatenate=True,
        align_arrays=False, dtype=np.float32, meta=np.empty((0,) * 5, np.float32), grid=grid,
        elevations=elevations)
    d = read_directions(group)
    coords = {name: (dim, getattr(d, name)) for name, dim in DIRECTION_COORDS.items()}
    coords["channel"] = ("channel", list(CHANNELS))
    data = {RADIANCE: (RADIANCE_DIMS, radiance)}
    data.update({n: (DIMS[n], a) for n, a in arrays.items()})
    return xr.Dataset(data, coords=coords, attrs=dict(group.attrs))


def _summary(group) -> dict[str, Any]:
    attrs = group.attrs
    return {"sampling": sampling_summary(group),
            "fit": {"rotations": len(attrs["rotations"]), "elevations": len(attrs["elevations"]),
                    "parameters": attrs["parameters"], "error": attrs.get("fit_error"),
                    "size_ratio": attrs.get("size_ratio")}}


def _lines(summary: dict[str, Any]) -> list[str]:
    f = summary["fit"]
    err = f["error"] or {}
    ratio = f["size_ratio"] or 1.0
    size = f"{ratio:.2f}x smaller than" if ratio >= 1 else f"{1 / ratio:.2f}x larger than"
    return [*sampling_lines(summary["sampling"]),
            f"HLS fit: {f['rotations']} rotations x {f['elevations']} elevations, "
            f"{f['parameters']} parameters per rotation; {size} the input; error (linear RGB) "
            f"RMSE {err.get('rmse', 0):.4g}, max {err.get('max', 0):.4g}"]


class FittedStore(Store):
    """An HLS fit of an ABTF (``btf fit``): hue, saturation and lightness coefficients."""

    names = (NAME,)
    what = "HLS-fit store"
    check = staticmethod(check_fitted)
    summary = staticmethod(_summary)
    lines = staticmethod(_lines)

    def dataset(self):
        """The lazy Dataset of :func:`open_fitted` (radiance rebuilt on demand)."""
        return open_fitted(self.path)


"""``btf fit``: HLS fitting of an ABTF (paper 003, section 2.5), and the radiance it gives back.

Per texel: hue and saturation constant over the lights, lightness a polynomial of six
parameters over elevation for every light rotation (:mod:`tasks.hls`). The lights must form a
grid of rotations x elevations (as ``abtf:R,E`` does). One task per (view, spatial block) reads
that block's layers, fits them, writes the parameters, and measures the fit's error against the
input (RMSE and maximum, linear RGB); :func:`open_fitted` rebuilds radiance lazily.

Fitted store (``btf_kind: hls-fit``): ``hue``, ``saturation`` ``(view, y, x)`` and
``lightness`` ``(view, rotation, coefficient, y, x)``, float32, with the rotation azimuths and
elevations, the light grid, and the source's direction coordinates.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from pipeline.atomic import atomic_output
from pipeline.errors import BTFError
from pipeline.params import option
from pipeline.provenance import provenance
from pipeline.runtime import Session
from pipeline.store import (
    DIRECTION_COORDS,
    RADIANCE,
    blocks,
    location,
    open_group,
    open_radiance,
    read_directions,
)
from tasks.hls import PARAMETERS, fit_block, light_grid, rebuild

KIND = "hls-fit"


@dataclasses.dataclass(frozen=True)
class FitParams:
    """Parameters of ``btf fit``."""

    store: str = option(help="radiance store with lights on rotations x elevations",
                        positional=True, path="in", metavar="IN")
    out: str = option(help="output fitted store (a .zarr directory)", positional=True,
                      path="out")
    overwrite: bool = option(False, record=False, help="replace OUT if it exists")


def _fit_task(store: str, out: str, view: int, ys: slice, xs: slice, grid, elevations):
    import zarr

    layers = zarr.open_array(store, path=RADIANCE, mode="r")[view, :, ys, xs]
    bad = int(np.count_nonzero(~np.isfinite(layers)))
    if bad:
        return None, (f"{bad} NaN or Inf values in view {view}, y {ys.start}:{ys.stop}, "
                      f"x {xs.start}:{xs.stop}")
    h, s, coef, errors = fit_block(layers, grid, elevations)
    target = zarr.open_group(out, mode="r+")
    target["hue"][view, ys, xs] = h
    target["saturation"][view, ys, xs] = s
    target["lightness"][view, :, :, ys, xs] = coef
    return errors, None


def fit(params: FitParams, session: Session) -> Path:
    """Fit the store of ``params``; write the fitted store."""
    import dask
    import zarr

    ds = open_radiance(params.store)
    group = open_group(params.store)
    d = read_directions(group)
    if ds.sizes["channel"] != 3:
        raise BTFError(f"{params.store}: HLS fitting needs RGB layers, the store has "
                       f"{ds.sizes['channel']} channel(s)")
    try:
        rotations, elevations, grid = light_grid(d.phi_light, d.theta_light)
    except ValueError as err:
        raise BTFError(f"{params.store}: {err}") from None
    nv, nl, ny, nx, nc = group[RADIANCE].shape
    attrs = {"btf_kind": KIND, "source": "fit", "source_store": params.store,
             "source_btf_kind": group.attrs.get("btf_kind"), "rotations": rotations.tolist(),
             "elevations": elevations.tolist(), "light_grid": grid.tolist(),
             "parameters": PARAMETERS, "provenance": provenance("fit", params)}
    with atomic_output(params.out, directory=True, overwrite=params.overwrite) as tmp:
        out = zarr.open_group(location(tmp), mode="w-", zarr_format=3)
        chunk = group[RADIANCE].chunks[2:4]
        for name, shape, dims, chunks in (
                ("hue", (nv, ny, nx), ("view", "y", "x"), (1, *chunk)),
                ("saturation", (nv, ny, nx), ("view", "y", "x"), (1, *chunk)),
                ("lightness", (nv, rotations.size, PARAMETERS, ny, nx),
                 ("view", "rotation", "coefficient", "y", "x"),
                 (1, rotations.size, PARAMETERS, *chunk))):
            out.create_array(name, shape=shape, chunks=chunks, dtype="float32",
                             dimension_names=dims, fill_value=np.nan)
        for name, dim in DIRECTION_COORDS.items():
            values = getattr(d, name)
            out.create_array(name, shape=values.shape, dtype="float64",
                             dimension_names=(dim,))[:] = values
        # one stored chunk per task: fitting works in float64 on every light of its texels
        ych = tuple(min(chunk[0], ny - y) for y in range(0, ny, chunk[0]))
        xch = tuple(min(chunk[1], nx - x) for x in range(0, nx, chunk[1]))
        tasks = [dask.delayed(_fit_task)(location(params.store), location(tmp), v,
                                         slice(y0, y0 + h), slice(x0, x0 + w), grid, elevations)
                 for v in range(nv) for y0, h in blocks(ych) for x0, w in blocks(xch)]
        session.log(f"fit: {nv} view(s) x {rotations.size} rotations x {elevations.size} "
                    f"elevations, {len(tasks)} blocks -> {params.out}")
        results = session.compute(*tasks)
        problems = [p for _, p in results if p is not None]
        if problems:
            raise BTFError(f"{params.store}: variable 'radiance' has {problems[0]}"
                           + (f" (and {len(problems) - 1} more blocks)" if len(problems) > 1
                              else ""))
        errors = [e for e, _ in results]
        sse = sum(e[0] for e in errors)
        count = sum(e[2] for e in errors)
        original = nv * nl * ny * nx * nc
        fitted = nv * ny * nx * (2 + rotations.size * PARAMETERS)
        out.attrs.update({**attrs, "fit_error": {
            "rmse": math.sqrt(sse / count), "max": max(e[1] for e in errors),
            "space": "linear RGB radiance, against the input"},
            "size_ratio": original / fitted})
    return Path(params.out)


def _rebuild_block(h, s, coef, *, grid, elevations):
    return rebuild(h[0], s[0], coef[0], grid, elevations)[None]


def open_fitted(path: str | Path):
    """A fitted store as a Dataset with a lazy ``radiance`` ``(view, light, y, x, channel)``."""
    import dask.array as da
    import xarray as xr
    import zarr

    group = open_group(path)
    if group.attrs.get("btf_kind") != KIND:
        raise BTFError(f"{path}: not an HLS-fit store (btf_kind is "
                       f"{group.attrs.get('btf_kind')!r}; make one with btf fit)")
    arrays = {n: da.from_zarr(zarr.open_array(location(path), path=n, mode="r"))
              for n in ("hue", "saturation", "lightness")}
    grid = np.asarray(group.attrs["light_grid"])
    elevations = np.asarray(group.attrs["elevations"])
    radiance = da.blockwise(
        _rebuild_block, "vlyxc", arrays["hue"], "vyx", arrays["saturation"], "vyx",
        arrays["lightness"], "vrpyx", new_axes={"l": grid.size, "c": 3}, concatenate=True,
        align_arrays=False, dtype=np.float32, meta=np.empty((0,) * 5, np.float32), grid=grid,
        elevations=elevations)
    d = read_directions(group)
    coords = {name: (dim, getattr(d, name)) for name, dim in DIRECTION_COORDS.items()}
    coords["channel"] = ("channel", ["R", "G", "B"])
    data = {RADIANCE: (("view", "light", "y", "x", "channel"), radiance)}
    data.update({n: (tuple(group[n].metadata.dimension_names), a) for n, a in arrays.items()})
    return xr.Dataset(data, coords=coords, attrs=dict(group.attrs))

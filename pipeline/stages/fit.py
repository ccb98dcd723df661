"""``btf fit``: HLS fitting of an ABTF (paper 003, section 2.5), and the radiance it gives back.

Per texel: hue and saturation constant over the lights, lightness a polynomial of six
parameters over elevation for every light rotation (:mod:`tasks.hls`). The lights must form a
grid of rotations x elevations (as ``abtf:R,E`` does). One task per (view, spatial block) reads
that block's layers, fits them, writes the parameters, and measures the fit's error against the
input (RMSE and maximum, linear RGB); :func:`pipeline.stores.fitted.open_fitted` rebuilds
radiance lazily.

The fitted store is described in :mod:`pipeline.stores.fitted`.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from pipeline import storage
from pipeline.atomic import atomic_output
from pipeline.errors import BTFError
from pipeline.params import option
from pipeline.provenance import provenance
from pipeline.session import Session
from pipeline.stage import Stage
from pipeline.stores import RadianceStore, open_store
from pipeline.stores.base import RADIANCE, location, writable
from pipeline.stores.fitted import create_fitted_store
from tasks.hls import PARAMETERS, fit_block, light_grid


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

    layers = zarr.open_array(storage.store(store), path=RADIANCE, mode="r")[view, :, ys, xs]
    bad = int(np.count_nonzero(~np.isfinite(layers)))
    if bad:
        return None, (f"{bad} NaN or Inf values in view {view}, y {ys.start}:{ys.stop}, "
                      f"x {xs.start}:{xs.stop}")
    h, s, coef, errors = fit_block(layers, grid, elevations)
    target = writable(out)
    target["hue"][view, ys, xs] = h
    target["saturation"][view, ys, xs] = s
    target["lightness"][view, :, :, ys, xs] = coef
    return errors, None


def fit(params: FitParams, session: Session) -> Path:
    """Fit the store of ``params``; write the fitted store."""
    import dask
    from dask.array.core import normalize_chunks, slices_from_chunks

    store = open_store(params.store, RadianceStore)
    group = store.group
    d = store.directions
    nv, nl, ny, nx, nc = store.shape
    if nc != 3:
        raise BTFError(f"{params.store}: HLS fitting needs RGB layers, the store has {nc} "
                       "channel(s)")
    try:
        rotations, elevations, grid = light_grid(d.phi_light, d.theta_light)
    except ValueError as err:
        raise BTFError(f"{params.store}: {err}") from None
    attrs = {"source": "fit", "source_store": params.store,
             "source_btf_kind": store.kind, "rotations": rotations.tolist(),
             "elevations": elevations.tolist(), "light_grid": grid.tolist(),
             "parameters": PARAMETERS, "provenance": provenance("fit", params)}
    with atomic_output(params.out, directory=True, overwrite=params.overwrite) as tmp:
        chunk = group[RADIANCE].chunks[2:4]
        out = create_fitted_store(tmp, directions=d, ny=ny, nx=nx, rotations=rotations.size,
                                  chunk=chunk, attrs=attrs)
        # one stored chunk per task: fitting works in float64 on every light of its texels
        tasks = [dask.delayed(_fit_task)(location(params.store), location(tmp), v, ys, xs, grid,
                                         elevations)
                 for v in range(nv)
                 for ys, xs in slices_from_chunks(normalize_chunks(chunk, (ny, nx)))]
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
        out.attrs.update({"fit_error": {
            "rmse": math.sqrt(sse / count), "max": max(e[1] for e in errors),
            "space": "linear RGB radiance, against the input"},
            "size_ratio": original / fitted})
    return Path(params.out)


STAGE = Stage("fit", FitParams, fit,
              "fit an ABTF in HLS: constant hue/saturation, lightness per rotation",
              "HLS fitting (paper 003, 2.5): per texel, hue and saturation constant over the "
              "lights and lightness fitted, for every light rotation, by six parameters over "
              "elevation. Reports the fit error (RMSE and maximum, linear RGB) and the size "
              "ratio; the fitted store rebuilds radiance lazily.", makes_store=True,
              whole="fits every texel over all lights")

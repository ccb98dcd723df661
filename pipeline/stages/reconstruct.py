"""``btf reconstruct``: exactly the layers, region and rank asked for, from a compressed store.

The selection is made on the lazy radiance of :func:`pipeline.stores.compressed.open_factors`, so
only the ``U`` chunks and ``V`` tiles it touches are read. The result is a radiance store (the
default) or one EXR per layer with a manifest, as ``btf export`` writes them.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from pipeline.atomic import atomic_output
from pipeline.errors import BTFError
from pipeline.graphs.blocks import aligned_chunks, store_aligned
from pipeline.images import write_exr
from pipeline.layer_files import layer_name, write_manifest
from pipeline.params import ParamError, check_region, option, parse_region
from pipeline.provenance import provenance
from pipeline.resume import Progress
from pipeline.session import Session
from pipeline.stage import Stage, for_scene_option, selected_directions
from pipeline.stores.base import RADIANCE, RADIANCE_DIMS, isel, layer_indices
from pipeline.stores.compressed import open_factors, radiance_in
from pipeline.stores.radiance import LayoutOptions, create_radiance_store


@dataclasses.dataclass(frozen=True)
class ReconstructParams(LayoutOptions):
    """Parameters of ``btf reconstruct``."""

    store: str = option(help="compressed store (made by btf compress)", positional=True,
                        path="in", metavar="COMPRESSED")
    out: str = option(help="output radiance store, or folder of EXR files with --format exr",
                      positional=True, path="out")
    light: tuple[int, ...] | None = option(None, metavar="I,..", repeatable=True,
                                           help="light indices (default: all)")
    view: tuple[int, ...] | None = option(None, metavar="J,..", repeatable=True,
                                          help="view indices (default: all)")
    region: str | None = option(None, metavar="Y0:Y1,X0:X1",
                                help="texel region, ends exclusive (default: everything)")
    rank: int | None = option(None, metavar="R", help="components to use (default: all)")
    format: str = option("zarr", choices=("zarr", "exr"),
                         help="zarr: a radiance store; exr: one float32 EXR per layer")
    for_scene: str | None = for_scene_option()
    overwrite: bool = option(False, record=False, help="replace OUT if it exists")

    def __post_init__(self):
        check_region(self.region)
        if self.rank is not None and self.rank < 1:
            raise ParamError("rank", f"must be at least 1, got {self.rank}")
        self.layout()  # raises ParamError naming the bad option
        if self.for_scene is not None:
            for name in ("light", "view", "region"):
                if getattr(self, name) is not None:
                    raise ParamError(name, "cannot be combined with --for-scene (the scene "
                                           "says which layers and texels to compute)")
            if self.format != "zarr":
                raise ParamError("for_scene", "needs --format zarr")


def select(params: ReconstructParams):
    """``(factors, radiance, directions)``: exactly the requested layers, region and rank.

    The store's :func:`~pipeline.stores.compressed.open_factors`, the lazy radiance of the
    selection, and the selection's directions.
    """
    factors = open_factors(params.store, rank=params.rank)
    nv, nl, ny, nx, _ = factors.radiance.shape
    views = layer_indices(params.view, nv, "view", params.store)
    lights = layer_indices(params.light, nl, "light", params.store)
    ys, xs = slice(None), slice(None)
    if params.region is not None:
        ys, xs = parse_region(params.region)
        if ys.stop > ny or xs.stop > nx:
            raise BTFError(f"{params.store}: --region {params.region} reaches beyond the "
                           f"{ny} x {nx} texels of the store")
    radiance = isel(factors.radiance, RADIANCE_DIMS,
                    {"view": views, "light": lights, "y": ys, "x": xs})
    return factors, radiance, factors.directions.select(views, lights)


def _write_layer(pixels: np.ndarray, path: str, channels: tuple[str, ...]) -> None:
    write_exr(path, pixels, channels)


def reconstruct(params: ReconstructParams, session: Session) -> Path:
    """Write the reconstruction requested by ``params``; returns the output path."""
    import dask

    factors, sel, d = select(params)
    channels = factors.channels
    nv, nl, ny, nx, _ = sel.shape
    session.log(f"reconstruct: {nv} x {nl} layers of {ny} x {nx} texels at rank "
                f"{factors.rank} -> {params.out}")
    needs = None
    if params.for_scene is not None:
        from pipeline.scene_needs import needs_of, spec_for_output

        needs = needs_of(spec_for_output(params.for_scene, params.out), d, (ny, nx))
        session.log(f"reconstruct: only what {params.for_scene} needs: {len(needs.layers)} "
                    f"of {needs.of} layers, texels {needs.window}")
    attrs = {"source": "reconstruct",
             "reconstructed_from": {"store": params.store, "rank": factors.rank,
                                    "error": factors.attrs.get("error")},
             "provenance": provenance("reconstruct", params)}
    if needs is not None:
        attrs["computed_for_scene"] = needs.record(params.for_scene)
    with atomic_output(params.out, directory=True, overwrite=params.overwrite,
                       resume=attrs["provenance"] if params.format != "exr" else None) as tmp:
        if params.format == "exr":
            tmp.mkdir()
            rows, writes = [], []
            for v in range(nv):
                for li in range(nl):
                    name = layer_name(d.theta_light[li], d.phi_light[li], d.theta_view[v],
                                      d.phi_view[v], "exr")
                    rows.append((name, d.theta_light[li], d.phi_light[li], d.theta_view[v],
                                 d.phi_view[v]))
                    writes.append(dask.delayed(_write_layer)(sel[v, li], str(tmp / name),
                                                             channels))
            write_manifest(tmp, rows)
            session.compute(*writes)
        else:
            progress = Progress(tmp)
            group = progress.skeleton(lambda: create_radiance_store(
                tmp, directions=d, ny=ny, nx=nx, channels=channels,
                layout=params.layout(), attrs=attrs))
            if progress.count():
                session.log(f"reconstruct: resuming: {progress.count()} blocks already written")
            chunks = aligned_chunks(group[RADIANCE])
            whole = all(getattr(params, n) is None for n in ("light", "view", "region"))
            # the whole store's blocks rebuilt in place; a selection's cut blocks rechunked
            data = (radiance_in(factors, chunks, params.store) if whole
                    else sel.rechunk(chunks))
            keep = None if needs is None else (lambda r: needs.keeps(
                r[0].start, range(r[1].start, r[1].stop), r[2], r[3]))
            session.compute(store_aligned([data], [group[RADIANCE]], progress=progress,
                                          keep=keep))
    return Path(params.out)


STAGE = Stage("reconstruct", ReconstructParams, reconstruct,
              "rebuild chosen layers, region and rank from a compressed store",
              "Rebuild exactly the requested layers (--light, --view), texel region (--region) "
              "and rank (--rank) as exp(U S V^T) - eps, reading only the U chunks and V tiles "
              "they need, into a radiance store or EXR files (--format exr).",
              for_scene=True, directions=selected_directions)

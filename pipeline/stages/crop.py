"""``btf crop``: a region, and optionally some layers, of a store, as a new store.

A generic cut: a sample of a measurement, the constraint photos of an enlargement, a
ground-truth region for evaluation. The selection is made on the store's lazy arrays
(:func:`pipeline.stores.radiance.lazy_variable`) and written block by block in the output's
task blocks, so memory is bounded by a few blocks whatever the sizes. Ground-truth fields of a
generated store (``height``, ``albedo``, ...) are cropped along. The output records where it
came from (``cropped_from``) and its provenance. A compressed store is cut in its factors and
re-factored exactly into a compressed store (nothing is expanded to radiance).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from pipeline.atomic import atomic_output
from pipeline.errors import BTFError
from pipeline.graphs.blocks import aligned_chunks, read_chunks, store_aligned, task_side, write_unit
from pipeline.params import check_region, option, parse_region
from pipeline.planning import Shape, StageEstimate, rate
from pipeline.provenance import provenance
from pipeline.resume import Progress
from pipeline.session import Session
from pipeline.stage import Stage, selected_directions
from pipeline.stores import CompressedStore, RadianceStore, open_store
from pipeline.stores.base import RADIANCE, isel, layer_indices, read_channels
from pipeline.stores.radiance import TRUTH_DIMS, LayoutOptions, create_radiance_store, lazy_variable


@dataclasses.dataclass(frozen=True)
class CropParams(LayoutOptions):
    """Parameters of ``btf crop``."""

    store: str = option(help="radiance or compressed store to cut from", positional=True,
                        path="in", metavar="IN")
    out: str = option(help="output store (a .zarr directory) of the input's kind",
                      positional=True, path="out")
    region: str | None = option(None, metavar="Y0:Y1,X0:X1",
                                help="texel region, ends exclusive (default: all texels)")
    light: tuple[int, ...] | None = option(None, metavar="I,..", repeatable=True,
                                           help="light indices to keep (default: all)")
    view: tuple[int, ...] | None = option(None, metavar="J,..", repeatable=True,
                                          help="view indices to keep (default: all)")
    overwrite: bool = option(False, record=False, help="replace OUT if it exists")

    def __post_init__(self):
        check_region(self.region)
        self.layout()  # raises ParamError naming the bad option


def _crop_factors(params: CropParams, store, session: Session) -> Path:
    """A part of a compressed store as a compressed store: an exact SVD of the part.

    The selected rows of ``U`` and the region of ``V`` are re-factored exactly
    (:mod:`pipeline.graphs.factors`): nothing is expanded to radiance, and the result is a
    compressed store like any other (orthonormal ``U`` and ``V``, decreasing ``S``, at most
    the source's rank), with the source's transform.
    """
    import dask.array as da
    import numpy as np
    import zarr

    from pipeline import storage
    from pipeline.graphs.factors import gram, mapped_v
    from pipeline.stores.base import location
    from pipeline.stores.compressed import create_compressed_store
    from tasks.dfmf import svd_map

    group = store.group
    nv, nl, nc, k = group["U"].shape
    ny, nx = group["V"].shape[:2]
    views = layer_indices(params.view, nv, "view", params.store)
    lights = layer_indices(params.light, nl, "light", params.store)
    ys, xs = slice(0, ny), slice(0, nx)
    if params.region is not None:
        ys, xs = parse_region(params.region)
        if ys.stop > ny or xs.stop > nx:
            raise BTFError(f"{params.store}: --region {params.region} reaches beyond the "
                           f"{ny} x {nx} texels of the store")
    d = store.directions.select(views, lights)
    u = np.asarray(group["U"][...], np.float64)[np.ix_(views, lights)].reshape(-1, k)
    s = np.asarray(group["S"][...], np.float64)
    chunk = params.chunk or group["V"].chunks[0]
    v = da.from_zarr(zarr.open_array(storage.store(location(params.store)), path="V",
                                     mode="r"))[ys, xs].rechunk((chunk, chunk, k))
    h, w = ys.stop - ys.start, xs.stop - xs.start
    session.log(f"crop: {d.views} x {d.lights} layers of {h} x {w} texels at ({ys.start}, "
                f"{xs.start}) of a compressed store (rank {k}): its factors, re-factored "
                f"exactly -> {params.out}")
    new_u, new_s, vmap = svd_map(u, gram(v, s, session))
    rank = len(new_s)
    attrs = {key: group.attrs[key] for key in ("source_btf_kind", "transform", "dfmf",
                                               "source_sampling", "source_material")
             if key in group.attrs}
    attrs.update({
        "source": "crop", "provenance": provenance("crop", params),
        "source_shape": [d.views, d.lights, h, w, nc],
        "cropped_from": {"store": params.store, "y": [ys.start, ys.stop],
                         "x": [xs.start, xs.stop], "views": views, "lights": lights},
        "svd": {"rank": rank, "method": f"exact re-factorisation of the selected rows of U "
                                        f"and region of V of {params.store} (rank {k})"},
        "error": {"frobenius_norm": float(np.sqrt(np.sum(new_s**2))),
                  "dropped_relative_frobenius": 0.0,
                  "of_source": group.attrs.get("error")}})
    with atomic_output(params.out, directory=True, overwrite=params.overwrite,
                       resume=attrs["provenance"]) as tmp:
        out = create_compressed_store(
            tmp, directions=d, channels=read_channels(group), ny=h, nx=w, rank=rank,
            chunk=chunk, dir_chunk=params.dir_chunk or group["U"].chunks[1], attrs=attrs,
            v_dtype=params.dtype or str(group["V"].dtype))
        out["U"][...] = new_u.reshape(d.views, d.lights, nc, rank).astype(np.float32)
        out["S"][...] = new_s.astype(np.float32)
        session.compute(store_aligned([mapped_v(v, s[:, None] * vmap)], [out["V"]]))
    return Path(params.out)


def crop(params: CropParams, session: Session) -> Path:
    """Write the requested part of a store as a new store of its kind (radiance or factors)."""
    store = open_store(params.store, RadianceStore, CompressedStore)
    if isinstance(store, CompressedStore):
        return _crop_factors(params, store, session)
    group = store.group
    nv, nl, height, width, _ = store.shape
    views = layer_indices(params.view, nv, "view", params.store)
    lights = layer_indices(params.light, nl, "light", params.store)
    ys, xs = slice(0, height), slice(0, width)
    if params.region is not None:
        ys, xs = parse_region(params.region)
        if ys.stop > height or xs.stop > width:
            raise BTFError(f"{params.store}: --region {params.region} reaches beyond the "
                           f"{height} x {width} texels of the store")
    d = store.directions.select(views, lights)
    layout = params.layout(like=store.layout)
    attrs = {"source": "crop", "provenance": provenance("crop", params),
             "cropped_from": {"store": params.store, "y": [ys.start, ys.stop],
                              "x": [xs.start, xs.stop], "views": views, "lights": lights}}
    for key in ("material", "shading"):
        if key in group.attrs:
            attrs[key] = group.attrs[key]
    if params.light is None and params.view is None and "sampling" in group.attrs:
        attrs["sampling"] = group.attrs["sampling"]
    truth = [name for name in TRUTH_DIMS if store.has(name)]
    ny, nx = ys.stop - ys.start, xs.stop - xs.start
    session.log(f"crop: {d.views} x {d.lights} layers of {ny} x {nx} texels at "
                f"({ys.start}, {xs.start}) -> {params.out}")
    with atomic_output(params.out, directory=True, overwrite=params.overwrite,
                       resume=attrs["provenance"]) as tmp:
        progress = Progress(tmp)
        out = progress.skeleton(lambda: create_radiance_store(
            tmp, directions=d, ny=ny, nx=nx, channels=read_channels(group), layout=layout,
            attrs=attrs, truth=len(truth) == len(TRUTH_DIMS)))
        if progress.count():
            session.log(f"crop: resuming: {progress.count()} blocks already written")
        names = [RADIANCE, *(truth if len(truth) == len(TRUTH_DIMS) else [])]
        whole = views == list(range(nv)) and lights == list(range(nl))
        dims = {n: tuple(group[n].metadata.dimension_names or ()) for n in names}
        reads = {n: _read_blocks(group[n], out[n], dims[n], ys, xs) for n in names} \
            if whole else {}
        # in the output's blocks cut at the region where they fall on the source's write
        # units (_read_blocks), else in the source's own task blocks
        if not (reads and all(reads.values())):
            reads = {n: read_chunks(group, n) for n in names}
        where = {"view": views, "light": lights, "y": ys, "x": xs}
        sources = [isel(*lazy_variable(store, n, reads[n]), where) for n in names]
        sources = [data.rechunk(aligned_chunks(out[n])) for data, n in zip(sources, names,
                                                                           strict=True)]
        session.compute(store_aligned(sources, [out[n] for n in names], progress=progress))
    return Path(params.out)


def _read_blocks(source, target, dims: tuple, ys: slice, xs: slice) -> dict | None:
    """Read blocks of ``source`` along ``dims``: ``target``'s task blocks, cut at the region.

    Each block of the region is then read as one piece, exactly the texels of one output
    block. (In the source's own task blocks, a block that straddled two output blocks was
    read whole, cut and put together: reads of texels outside the region, and one more copy
    of every value.) None where two output blocks meet inside one of the source's write units
    (a region off its chunk grid, another ``--chunk``): that unit would be read and decoded
    by two tasks, so the source is read in its own blocks, as before. For the whole of the
    view and light axes only.
    """
    chunks = {}
    for dim, blocks, size, unit in zip(dims, aligned_chunks(target), source.shape,
                                       write_unit(source), strict=True):
        cut = {"y": ys, "x": xs}.get(dim, slice(0, size))
        if np.any((cut.start + np.cumsum(blocks)[:-1]) % unit):  # a unit read by two tasks
            return None
        chunks[dim] = tuple(n for n in (cut.start, *blocks, size - cut.stop) if n)
    return chunks


def _estimate(params, shapes: dict) -> tuple[StageEstimate, Shape]:
    src = shapes[params.store]
    nv, nl, ny, nx, nc = src.radiance
    if params.region is not None:
        from pipeline.params import parse_region

        ys, xs = parse_region(params.region)
        ny, nx = ys.stop - ys.start, xs.stop - xs.start
    nv = len(set(params.view)) if params.view else nv
    nl = len(set(params.light)) if params.light else nl
    itemsize = np.dtype(params.dtype).itemsize if params.dtype else src.itemsize
    if src.kind == "compressed":  # the factors: V's region read twice, the new V written
        k, chunk = src.rank or 1, params.chunk or src.chunk
        v_bytes = ny * nx * k * itemsize
        per_core, source = rate("compress_bytes_per_core_second")
        plan = StageEstimate("crop", "", bytes_read=2 * v_bytes, bytes_written=v_bytes,
                             tasks=2 * max(1, (ny // chunk) * (nx // chunk)), passes=2,
                             input_reads=2, task_bytes=2 * chunk * chunk * k * 8,
                             client_bytes=3 * nv * nl * nc * k * 8,
                             core_seconds=2 * v_bytes / per_core, rate_source=source,
                             option="--chunk", note="a compressed store: its factors")
        return plan, Shape("compressed", (nv, nl, ny, nx, nc), chunk, src.dir_chunk, rank=k,
                           unit=chunk, itemsize=itemsize)
    values = nv * nl * ny * nx * nc
    truth = ny * nx * 6 * 4 if src.truth else 0  # height, albedo (3), roughness, specular
    chunk = params.chunk or src.chunk
    dir_chunk = params.dir_chunk or src.dir_chunk
    side = task_side(chunk)
    per_core, source = rate("compress_bytes_per_core_second")  # a read-and-write pass
    plan = StageEstimate("crop", "", bytes_read=values * src.itemsize + truth,
                         bytes_written=values * itemsize + truth,
                         tasks=max(1, values // (side * side * dir_chunk * nc)), passes=1,
                         input_reads=1,
                         task_bytes=2 * max(side, src.side) ** 2 * dir_chunk * nc * 4,
                         core_seconds=values * 4 / per_core, rate_source=source, option="--chunk")
    return plan, Shape(src.kind, (nv, nl, ny, nx, nc), chunk, dir_chunk, unit=chunk,
                       truth=src.truth, itemsize=itemsize)


STAGE = Stage("crop", CropParams, crop,
              "cut a region and some layers of a store into a new store",
              "Write a texel region (--region Y0:Y1,X0:X1) and optionally some lights "
              "(--light) and views (--view) of a radiance store as a new radiance store, "
              "streamed block by block; ground-truth fields of a generated store are cut "
              "along. For samples, constraint photos and ground-truth regions. A compressed "
              "store (btf compress, btf ingest FILE.btf) is cut in its factors, re-factored "
              "exactly into a compressed store: nothing is expanded to radiance.",
              makes_store=True,
              estimate=_estimate, whole="cuts what its own region, light and view say",
              directions=selected_directions)

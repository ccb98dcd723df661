"""Scenes: exactly the directions, region, level and rank a scene spec asks of a store.

The spec (:mod:`pipeline.scene_spec`) is resolved against its source: requested directions
become interpolation terms over the measured layers (:mod:`tasks.directions`), the region and
level a window of level-n texels, and the graph (:mod:`pipeline.graphs.scene`) reads only the
chunks those touch. The chunks read, out of all, are logged and recorded in the output's attrs
(``reads``).

Output: ``format: zarr`` writes a scene store (``direction, y, x, channel``), or a radiance
store when the scene asks for ``all`` directions; ``exr`` and ``png`` write one image per
direction into the folder OUT, named by its angles, with a ``manifest.csv`` of the angles
(``btf ingest`` reads an EXR folder back when its directions form a full view x light grid,
as ``all`` gives). PNGs are tone-mapped with one exposure for the whole scene. EXR and PNG
output holds the images in memory; zarr output is written block by block.
"""

from __future__ import annotations

import shlex
from pathlib import Path
from typing import Any

import numpy as np

from pipeline import storage
from pipeline.atomic import atomic_output
from pipeline.errors import BTFError
from pipeline.scene_needs import level_window, resolve, say_widened
from pipeline.scene_spec import SceneSpec
from pipeline.session import Session
from pipeline.stores import (
    CompressedStore,
    RadianceStore,
    Store,
    SurfaceStore,
    TileSetStore,
    open_store,
)
from pipeline.stores.base import RADIANCE
from pipeline.stores.levels import levels_of
from pipeline.stores.radiance import lazy_float32
from tasks.transform import Transform

# what a scene reads, by the source's class (a compressed tile set is a tile set)
SOURCES = ((RadianceStore, "radiance"), (CompressedStore, "compressed"),
           (TileSetStore, "tileset"), (SurfaceStore, "surface"))


def _restricted_region(group, spec: SceneSpec, request) -> None:
    """Refuse texels a store restricted to another scene's region did not compute."""
    restriction = group.attrs.get("computed_for_scene") or {}
    only = restriction.get("region")
    if only:
        ys, xs = request.level0()
        if ys.start < only[0] or ys.stop > only[1] or xs.start < only[2] or xs.stop > only[3]:
            raise spec.error("region", f"{spec.source} was computed only for the texels "
                                       f"{only} (of the scene {restriction['scene']}); this "
                                       "scene reads beyond them")


def _open_source(spec: SceneSpec):
    try:
        source = storage.parse(spec.source, what="source")
    except BTFError as exc:
        raise spec.error("source", str(exc)) from None
    if not storage.any_below(source):
        raise spec.error("source", f"{spec.source!r} does not exist")
    try:
        store = open_store(source)
    except BTFError as exc:
        raise spec.error("source", str(exc)) from None
    for cls, kind in SOURCES:
        if isinstance(store, cls):
            return store, kind
    raise spec.error("source", f"{spec.source}: a {store.kind or 'non-btf'} store; a scene "
                               "takes a radiance, compressed (or enlarged), tile-set or "
                               "surface store")


def _pyramid_level(spec: SceneSpec, group, variable: str, session: Session) -> str | None:
    """The path of the stored level, None for level 0 or a store without a pyramid."""
    if spec.level == 0:
        return None
    levels = [lv for lv in levels_of(group) if lv["shape"] is not None]
    if not levels:
        session.log(f"scene: {spec.source} has no pyramid (btf pyramid adds one); level "
                    f"{spec.level} is computed on the fly from level 0, which reads "
                    f"{4**spec.level}x the texels")
        return None
    most = max(lv["level"] for lv in levels)
    if spec.level > most:
        raise spec.error("level", f"level {spec.level} is beyond the pyramid of "
                                  f"{spec.source} (levels 0 to {most}; btf pyramid --levels "
                                  "N --overwrite makes more)")
    return next(lv["path"] for lv in levels if lv["level"] == spec.level)


def _layer_scale(transform: Transform, group, layers) -> np.ndarray | None:
    """A cosine store's scale of each of the scene's measured layers (else None)."""
    theta = np.asarray(group["theta_light"][...], np.float64)
    return transform.layer_scale(theta[[li for _, li in layers]])


def _check_keys(spec: SceneSpec, kind: str, store: Store) -> None:
    group = store.group
    tiles = kind == "tileset"
    if tiles and spec.region is not None:
        raise spec.error("region", "a tile set covers an unbounded surface: give its part "
                                   "with size: [H, W] and origin: [Y, X]")
    if tiles and spec.size is None:
        raise spec.error("size", "is required for a tile set (the surface's texels to "
                                 "render, [H, W])")
    if not tiles:
        for key in ("size", "seed"):
            if getattr(spec, key) is not None:
                raise spec.error(key, f"applies to tile sets only; {spec.source} is a "
                                      f"{store.kind} store (use region)")
        if spec.origin != (0, 0):
            raise spec.error("origin", f"applies to tile sets only; {spec.source} is a "
                                       f"{store.kind} store (use region)")
    if spec.rank is not None:
        if "S" not in group.array_keys():
            raise spec.error("rank", f"applies to compressed sources only; {spec.source} is "
                                     f"a {store.kind} store")
        stored = group["S"].shape[0]
        if spec.rank > stored:
            raise spec.error("rank", f"{spec.rank} is above the {stored} components "
                                     f"{spec.source} holds")


def _radiance_reads(kind: str, source, layers, req) -> dict:
    """The chunks of a radiance or surface array a request reads, and all of them."""
    from pipeline.graphs import scene as graphs

    ys, xs = req.read_window()
    if kind == "surface":
        return {RADIANCE: [graphs.chunks_touched(
            source.shape, source.chunks, (ys, xs, slice(None))),
            graphs.total_chunks(source.shape, source.chunks)]}
    spatial = graphs.chunks_touched(source.shape[2:], source.chunks[2:],
                                    (ys, xs, slice(None)))
    return {source.path: [
        graphs.layer_chunks(layers, source.chunks[1]) * spatial,
        graphs.total_chunks(source.shape, source.chunks)]}


def _radiance(spec: SceneSpec, group, kind: str, path: str, layers, request,
              session: Session):
    """The graph of a radiance or surface store (its level, if stored) and its reads."""
    import dask.array as da
    import zarr

    from pipeline.graphs import scene as graphs

    rad = group[RADIANCE]
    ny, nx = rad.shape[-3:-1]
    stored = _pyramid_level(spec, group, RADIANCE, session) if kind == "radiance" else None
    if kind == "surface" and spec.level:
        session.log(f"scene: level {spec.level} of a surface store is computed on the fly")
    req = request(level_window(spec, ny, nx, spec.level, session), stored is not None)
    _restricted_region(group, spec, req)
    source = zarr.open_array(storage.store(path), path=stored or RADIANCE, mode="r")
    data = lazy_float32(da.from_zarr(source))
    if kind == "surface":
        data = data[None, None]
    out = graphs.radiance_graph(data, req)
    return out, _radiance_reads(kind, source, layers, req)


def _compressed(spec: SceneSpec, group, path: str, layers, request, session: Session):
    """The graph of a compressed store at the scene's rank (its level, if stored); its reads."""
    import dask.array as da
    import zarr

    from pipeline.graphs import scene as graphs

    rank = spec.rank or group["S"].shape[0]
    ny, nx = group["V"].shape[:2]
    stored = _pyramid_level(spec, group, "V", session)
    req = request(level_window(spec, ny, nx, spec.level, session), stored is not None,
                  rank=rank)
    u = group["U"]
    u_rows, u_read = graphs.read_u_rows(u, layers, rank)
    s = np.asarray(group["S"][:rank])
    v = zarr.open_array(storage.store(path), path=stored or "V", mode="r")
    transform = Transform.from_attrs(group.attrs["transform"])
    out = graphs.compressed_graph(lazy_float32(da.from_zarr(v)), u_rows, s, transform, req,
                                  scale=_layer_scale(transform, group, layers))
    ys, xs = req.read_window()
    return out, {
        v.path: [graphs.chunks_touched(v.shape, v.chunks, (ys, xs, slice(None))),
                 graphs.total_chunks(v.shape, v.chunks)],
        "U": [u_read, graphs.total_chunks(u.shape, u.chunks)]}


def build(spec: SceneSpec, session: Session):
    """The scene's lazy ``(direction, y, x, channel)`` array and what it reads.

    Returns ``(array, directions, info)``: ``info`` holds the source's kind, the channels,
    the window, the layers, weights and the chunks read out of all (``reads``).
    """
    from pipeline.graphs import scene as graphs

    store, kind = _open_source(spec)
    group = store.group
    _check_keys(spec, kind, store)
    directions, weights, layers = resolve(spec, store.directions)
    for v, li in layers:
        store.check_computed(v, li)
    info: dict[str, Any] = {"kind": store.kind, "channels": store.channels,
                            "layers": layers, "weights": weights, "level": spec.level}
    path = store.location

    def request(window, stored, **extra):
        return graphs.Request(layers=layers, weights=weights, window=window, level=spec.level,
                              stored_level=stored, chunk=spec.chunk, **extra)

    if kind in ("radiance", "surface"):
        out, info["reads"] = _radiance(spec, group, kind, path, layers, request, session)
    elif kind == "compressed":
        out, info["reads"] = _compressed(spec, group, path, layers, request, session)
    else:
        out, info["reads"] = _tileset(spec, store, path, layers, request, session)
    return out, directions, info


def _tileset(spec: SceneSpec, store: TileSetStore, path: str, layers, request,
             session: Session):
    from pipeline.graphs import scene as graphs

    group = store.group
    f = 2**spec.level
    (h, w), (oy, ox) = spec.size, spec.origin
    window = (oy // f, -(-(oy + h) // f), ox // f, -(-(ox + w) // f))
    say_widened(session, f"size {list(spec.size)} at origin {list(spec.origin)}",
                spec.level, window, (oy, oy + h, ox, ox + w))
    n = store.tiles
    lattice = store.placement == "lattice"
    placement = {"lattice": lattice, "tiles": n, "order": store.order(),
                 "seed": spec.seed if spec.seed is not None else store.seed}
    if lattice:
        placement.update(hnf=store.hnf, basis=store.basis,
                         representative=store.representative)
    else:
        placement.update(corners=store.corner_types)
    compressed = store.compressed
    prescribed = compressed and store.prescribed
    variable = "V" if compressed else RADIANCE
    stored = None
    if lattice and spec.level:
        session.log(f"scene: a roller tile set has no pyramid (its tiles lie on a sheared "
                    f"lattice): level {spec.level} is computed on the fly from level 0, which "
                    f"reads {4**spec.level}x the texels")
    elif prescribed and spec.level:
        session.log(f"scene: level {spec.level} of a compressed tile set's tiles is computed "
                    "on the fly from its prescriptions")
    elif not lattice:
        stored = _pyramid_level(spec, group, variable, session)
    rank = spec.rank or (group["S"].shape[0] if compressed else None)
    req = request(window, stored is not None, rank=rank)
    extra, u_read = {}, 0
    if compressed:
        u = group["U"]
        u_rows, u_read = graphs.read_u_rows(u, layers, rank)
        transform = Transform.from_attrs(group.attrs["transform"])
        extra = {"u_rows": u_rows, "s": np.asarray(group["S"][:rank]), "transform": transform,
                 "scale": _layer_scale(transform, group, layers)}
    out, read = graphs.tileset_graph(store, req, placement, level_path=stored, **extra)
    if prescribed:  # the sample's V whole, and the tiles' prescriptions
        v = group["V"]
        total = graphs.total_chunks(v.shape, v.chunks)
        reads = {"V": [total, total],
                 "prescription_index": [len({t for t, _ in read}), n],
                 "U": [u_read, graphs.total_chunks(u.shape, u.chunks)]}
    elif compressed:
        reads = {stored or "V": [len(read), n],
                 "U": [u_read, graphs.total_chunks(u.shape, u.chunks)]}
    else:
        nv, nl = group[RADIANCE].shape[1:3]
        chunks = sum(len(lay) for _, lay in read)
        reads = {stored or RADIANCE: [chunks, n * nv * nl]}
    return out, reads


def write_scene(spec: SceneSpec, out: str, session: Session, *, overwrite: bool = False
                ) -> Path:
    """Compute the scene of ``spec`` into ``out`` (see the module docstring)."""
    from pipeline import __version__
    from pipeline.provenance import digest

    suffix = Path(out).suffix.lower()
    if spec.format == "zarr" and suffix != ".zarr":
        raise spec.error("format", f"zarr output goes to a .zarr path, got {out!r}")
    if spec.format != "zarr" and suffix == ".zarr":
        raise spec.error("format", f"{spec.format} output is a folder of images; {out!r} "
                                   "ends in .zarr")
    # before computing (atomic_output checks again)
    if storage.any_below(storage.parse(out)) and not overwrite:
        raise BTFError(f"{out}: already exists; pass --overwrite to replace it")
    data, directions, info = build(spec, session)
    nd, ny, nx, _ = data.shape
    reads = ", ".join(f"{a}/{b} {name} chunks" for name, (a, b) in info["reads"].items())
    session.log(f"scene: {nd} direction(s) from {len(info['layers'])} measured layer(s), "
                f"{ny} x {nx} texels at level {spec.level} -> {out}; reads {reads}")
    w = info["weights"]
    terms = [[[int(info["layers"][k][0]), int(info["layers"][k][1]), float(x)]
              for k, x in zip(w.indices[w.indptr[d]:w.indptr[d + 1]],
                              w.data[w.indptr[d]:w.indptr[d + 1]], strict=True)]
             for d in range(w.shape[0])] if spec.directions is not None else None
    attrs = {"source": "scene", "source_store": spec.source, "level": spec.level,
             "scene": spec.record(), "reads": info["reads"],
             "provenance": {"stage": "scene", "command": shlex.join(["btf", "scene", spec.path,
                                                                     str(out)]),
                            "scene": spec.record(),
                            "inputs": {spec.source: digest(spec.source)},
                            "version": __version__}}
    if terms is not None:
        attrs["terms"] = terms
    channels = info["channels"]
    if spec.format == "zarr":
        with atomic_output(out, directory=True, overwrite=overwrite) as tmp:
            target = _zarr_target(tmp, spec, directions, (ny, nx), channels, attrs, data,
                                  source=spec.source)
            _store(session, data, target, spec)
        return Path(out)
    images = session.compute(data)[0]
    _write_images(out, images, directions, channels, spec.format, overwrite)
    return Path(out)


def _zarr_target(tmp, spec, directions, shape, channels, attrs, data, *, source):
    if spec.directions is not None:
        from pipeline.stores.scene import create_scene_store

        return create_scene_store(tmp, directions=directions, shape=shape, channels=channels,
                                  chunk=spec.chunk, attrs=attrs)
    from pipeline.stores.radiance import Layout, create_radiance_store

    d = open_store(source).directions
    group = create_radiance_store(tmp, directions=d, ny=shape[0], nx=shape[1],
                                  channels=channels, layout=Layout(chunk=min(spec.chunk, 512)),
                                  attrs=attrs)
    return group[RADIANCE]


def _store(session: Session, data, target, spec: SceneSpec) -> None:
    from pipeline.graphs.blocks import aligned_chunks, store_aligned

    if target.ndim == 5:
        data = data.reshape(target.shape[0], target.shape[1], *data.shape[1:])
    session.compute(store_aligned([data.rechunk(aligned_chunks(target))], [target]))


def _write_images(out, images, directions, channels, fmt, overwrite) -> None:
    from pipeline.images import write_exr, write_png
    from pipeline.layer_files import layer_name, write_manifest
    from tasks.tonemap import exposure, to_uint8, tonemap

    scale = exposure(images[:, ::4, ::4]) if fmt == "png" else None
    with atomic_output(out, directory=True, overwrite=overwrite) as tmp:
        tmp.mkdir()
        rows = []
        for pixels, (tl, pl, tv, pv) in zip(images, directions, strict=True):
            name = layer_name(tl, pl, tv, pv, fmt)
            if fmt == "exr":
                write_exr(tmp / name, pixels, channels)
            else:
                image = to_uint8(tonemap(pixels, scale=scale))
                write_png(tmp / name, image[..., 0] if image.shape[-1] == 1 else image)
            rows.append((name, tl, pl, tv, pv))
        write_manifest(tmp, rows)

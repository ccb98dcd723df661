"""Compressed stores (``btf_kind: compressed``): ``U``, ``S``, ``V`` and radiance on demand.

A compressed store (made by ``btf compress``) holds

- ``U``: float32, dims ``(view, light, channel, component)``: the eigen-ABRDFs;
- ``S``: float32, dims ``(component,)``: singular values, decreasing;
- ``V``: float32, dims ``(y, x, component)``: the eigentextures, chunked in spatial tiles;
- the direction coordinates and ``channel`` labels of the radiance it describes;
- attrs: the range reduction (``transform``: ``log(radiance + eps)``), the SVD's parameters,
  its measured error and the provenance.

:func:`open_compressed` gives a Dataset whose ``radiance`` is a lazy dask array with the dims,
coordinates and chunking of a radiance store (:func:`open_factors`: the same arrays, without
xarray). Each of its blocks is
``exp(U[rows] diag(S) V[tile]^T) - eps`` and depends on one chunk of ``U`` and one tile of
``V``, so ``sel``/``isel`` followed by ``compute`` reads only what the selection needs.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from pipeline import storage
from pipeline.blockwise import blockwise
from pipeline.errors import BTFError
from pipeline.stores.base import (
    DIRECTION_COORDS,
    RADIANCE,
    RADIANCE_DIMS,
    Directions,
    Store,
    add_array,
    check_coordinates,
    check_kind,
    create_store,
    location,
    open_group,
    read_channels,
    read_directions,
    sampling_lines,
    sampling_summary,
)
from pipeline.stores.radiance import lazy_float32
from tasks.svd import reconstruct_layers
from tasks.transform import DFMF_MODELS, Transform

NAME = "compressed"
FACTOR_DIMS = {"U": ("view", "light", "channel", "component"), "S": ("component",),
               "V": ("y", "x", "component")}


def create_compressed_store(path: str | Path, *, directions: Directions,
                            channels: tuple[str, ...], ny: int, nx: int, rank: int,
                            chunk: int, dir_chunk: int, attrs: dict[str, Any],
                            v_dtype: str = "float32"):
    """Create an empty compressed store with its coordinates; returns the zarr group.

    ``v_dtype``: the eigentextures' type, float32 or float16 (``U`` and ``S`` are small and
    stay float32).
    """
    group = create_store(path, kind=NAME, attrs=attrs, directions=directions, channels=channels)
    nv, nl, nc = directions.views, directions.lights, len(channels)
    add_array(group, "U", shape=(nv, nl, nc, rank), dims=FACTOR_DIMS["U"],
              chunks=(1, min(dir_chunk, nl), nc, rank),
              attrs={"long_name": "eigen-ABRDFs", "coordinates": " ".join(DIRECTION_COORDS)})
    add_array(group, "S", shape=(rank,), dims=FACTOR_DIMS["S"], chunks=(rank,),
              attrs={"long_name": "singular values"})
    add_array(group, "V", shape=(ny, nx, rank), dims=FACTOR_DIMS["V"],
              chunks=(min(chunk, ny), min(chunk, nx), rank), dtype=v_dtype,
              attrs={"long_name": "eigentextures"})
    return group


def check_compressed(group, path: str | Path) -> None:
    """Raise :class:`BTFError` naming what is wrong if ``group`` is not a compressed store."""
    check_kind(group, path, NAME, "a compressed store", "btf compress", FACTOR_DIMS)
    if "transform" not in group.attrs or "eps" not in group.attrs["transform"]:
        raise BTFError(f"{path}: attrs lack the range reduction ('transform' with 'eps')")
    u, s, v = (group[n].shape for n in ("U", "S", "V"))
    if not u[-1] == s[0] == v[-1]:
        raise BTFError(f"{path}: U, S and V disagree on the rank: {u[-1]}, {s[0]}, {v[-1]}")
    check_coordinates(group, path, {"view": u[0], "light": u[1], "channel": u[2]}, "U")


def _rebuild(u, s, v, *scale, transform: Transform) -> np.ndarray:
    return reconstruct_layers(u, s, v, transform=transform, scale=scale[0] if scale else None)


def lazy_radiance(u, s, v, *, transform: Transform, theta_light=None):
    """Dask radiance ``(view, light, y, x, channel)`` from dask factors.

    There is one block per pair of a ``U`` chunk and a ``V`` tile. A cosine store needs
    ``theta_light`` (degrees, one per light): each layer is divided by its light's cosine.
    """
    extra = _layer_scale(u, transform, theta_light)
    return blockwise(_rebuild, "vlyxc", u, "vlck", s, "k", v, "yxk", *extra,
                     align_arrays=False, dtype=np.float32,
                     meta=np.empty((0,) * 5, np.float32), transform=transform)


def radiance_in(factors: LazyFactors, chunks, path: str | Path | None = None):
    """The lazy radiance of :func:`open_factors`'s ``factors`` in dask ``chunks``.

    ``chunks``: per axis of ``(view, light, y, x, channel)``. Where every chunk is made of
    whole blocks of :func:`lazy_radiance` (one per ``U`` chunk and ``V`` tile), each chunk
    is rebuilt block by block into one array (:func:`tasks.svd.reconstruct_pieces`): the
    same bits as the radiance rechunked, without dask concatenating the blocks (one more
    copy of every value). Elsewhere it is that rechunk.

    The radiance is the whole store's (a selection of it would cut the factors where the
    radiance's blocks were computed whole and then cut, and a product's last bit depends on
    its shape).

    With ``path`` (the store ``factors`` were opened from, on a local disk), ``U`` and ``V`` are
    read in the chunks the blocks need, each in one task per block, rather than in their
    stored chunks and rechunked: at 64 lights per chunk a 151 x 151 store's reconstruct had
    4,384 tasks, 1,510 of them reads of 9 KB of ``U`` and 1,963 cutting and joining them,
    for 453 blocks. The values read are the same, and so is every bit rebuilt.
    """
    transform, theta = factors.transform, factors.directions.theta_light
    u, s, v = factors.u, factors.s, factors.v
    pieces = (*u.chunks[:2], *v.chunks[:2])
    # pieces of one size (the last may be shorter), and blocks made of whole pieces: each
    # block's pieces then follow from its size alone
    regular = all(len(set(p[:-1])) <= 1 and p[-1] <= p[0] for p in pieces)
    if not regular or tuple(chunks[4]) != u.chunks[2] or not all(
            set(np.cumsum(c)) <= set(np.cumsum(p)) for c, p in zip(chunks[:4], pieces,
                                                                    strict=True)):
        return factors.radiance.rechunk(chunks)
    u = _factor_in(u, path, "U", (*chunks[:2], chunks[4], -1))
    v = _factor_in(v, path, "V", (*chunks[2:4], -1))
    extra = _layer_scale(u, transform, theta)
    return blockwise(_rebuild_pieces, "vlyxc", u, "vlck", s, "k", v, "yxk", *extra,
                     align_arrays=False, dtype=np.float32, meta=np.empty((0,) * 5, np.float32),
                     transform=transform, sizes=tuple(int(p[0]) for p in pieces))


def _factor_in(factor, path, name: str, chunks):
    """``factor`` (the lazy factor ``name``) in ``chunks``.

    Read so from the store at ``path`` where its chunks are read here (:mod:`pipeline.chunk_io`),
    else rechunked.
    """
    if path is not None:
        import zarr

        from pipeline import chunk_io

        array = zarr.open_array(storage.store(location(path)), path=name, mode="r")
        if chunk_io.here(array):
            whole = chunk_io.dask_array(array, location(path), chunks)
            return lazy_float32(whole[..., : factor.shape[-1]])  # the rank in use
    return factor.rechunk(chunks)


def _rebuild_pieces(u, s, v, *scale, transform: Transform, sizes: tuple[int, ...]):
    """:func:`radiance_in`'s block, its pieces ``sizes`` (view, light, y, x) apart."""
    from tasks.svd import reconstruct_pieces

    extents = (u.shape[0], u.shape[1], v.shape[0], v.shape[1])
    cuts = tuple([(a, min(a + size, n)) for a in range(0, n, size)]
                 for size, n in zip(sizes, extents, strict=True))
    return reconstruct_pieces(u, s, v, transform=transform, cuts=cuts,
                              scale=scale[0] if scale else None)


def _layer_scale(u, transform: Transform, theta_light) -> tuple:
    """A cosine store's per-layer scale as a blockwise argument in ``u``'s chunks (or none)."""
    import dask.array as da

    if not transform.cosine:
        return ()
    if theta_light is None:
        raise ValueError("a cosine store's radiance needs its lights' theta")
    scale = transform.layer_scale(theta_light)
    return da.from_array(np.broadcast_to(scale, u.shape[:2]).copy(), chunks=u.chunks[:2]), "vl"


FACTOR_PIECE = 4 << 20  # bytes of U read at once (whole chunks; split again in memory)


def _factor(array, where: str):
    """A factor as a dask array in its stored chunks.

    On a local disk each chunk is read in its task's thread (:mod:`pipeline.chunk_io`: a
    reconstruct's 1,510 chunks of ``U`` cost no more than their bytes); elsewhere ``U``'s
    small chunks are read a few MB at a time (:func:`_read_in_pieces`).
    """
    import dask.array as da

    from pipeline import chunk_io

    if chunk_io.here(array):
        return chunk_io.dask_array(array, where, array.chunks)
    return _read_in_pieces(array) if array.path == "U" else da.from_zarr(array)


def _read_in_pieces(array):
    """``U`` as a dask array in its stored chunks, read a few MB at a time.

    Its chunks are small (a view's block of lights: 9 KB for 16 lights at rank 48), and
    a read per chunk costs a millisecond of zarr's bookkeeping whatever its size: 1,510
    reads took 2.1 s of a 151 x 151 store's reconstruct. Whole views of it are read at once
    (about :data:`FACTOR_PIECE`, whole chunks) and split back into the stored chunks, so the
    blocks built on them are those of the stored chunks.
    """
    import dask.array as da

    if array.shape[0] == 0:
        return da.from_zarr(array)
    per_view = max(1, array.nbytes // array.shape[0])
    views = max(array.chunks[0], FACTOR_PIECE // per_view // array.chunks[0] * array.chunks[0])
    pieces = da.from_zarr(array, chunks=(min(views, array.shape[0]), *array.shape[1:]))
    return pieces.rechunk(array.chunks)


@dataclass(frozen=True)
class LazyFactors:
    """A compressed store's factors and lazy radiance as dask arrays, without xarray.

    What :func:`open_compressed`'s Dataset holds, for stages that need no labelled arrays:
    importing xarray (and pandas with it) is 0.6-0.7 s of a process, a quarter of a
    ``btf reconstruct`` of one layer.
    """

    u: Any  # (view, light, channel, component), the first ``rank`` components, float32
    s: Any  # (component,)
    v: Any  # (y, x, component)
    radiance: Any  # (view, light, y, x, channel): lazy_radiance of the three
    transform: Transform
    directions: Directions
    channels: tuple[str, ...]
    rank: int
    attrs: dict[str, Any]  # the store's


def open_factors(path: str | Path, *, rank: int | None = None, group=None) -> LazyFactors:
    """Open a compressed store's factors and lazy radiance (see :class:`LazyFactors`).

    Parameters
    ----------
    path
        The compressed store.
    rank
        Use only the first ``rank`` components (default: all).
    group
        Its zarr group, if already open.
    """
    import zarr

    group = open_group(path) if group is None else group
    check_compressed(group, path)
    full = group["S"].shape[0]
    rank = full if rank is None else rank
    if not 1 <= rank <= full:
        raise BTFError(f"{path}: --rank {rank} is not between 1 and the stored rank {full}")
    # zarr arrays, not a path: dask would open a path through fsspec instead of zarr's store
    store = storage.store(location(path))
    arrays = {name: zarr.open_array(store, path=name, mode="r") for name in FACTOR_DIMS}
    u, s, v = (lazy_float32(_factor(a, location(path))[..., :rank]) for a in arrays.values())
    transform = Transform.from_attrs(group.attrs["transform"])
    d = read_directions(group)
    return LazyFactors(u, s, v, lazy_radiance(u, s, v, transform=transform,
                                              theta_light=d.theta_light),
                       transform, d, tuple(read_channels(group)), rank, dict(group.attrs))


def open_compressed(path: str | Path, *, rank: int | None = None, group=None):
    """Open a compressed store as a Dataset with a lazy ``radiance`` (and ``U``, ``S``, ``V``).

    The arrays of :func:`open_factors` (its parameters), labelled.
    """
    import xarray as xr

    f = open_factors(path, rank=rank, group=group)
    coords = {name: (dim, getattr(f.directions, name)) for name, dim in DIRECTION_COORDS.items()}
    coords["channel"] = ("channel", list(f.channels))
    attrs = {**f.attrs, "rank_used": f.rank}
    data = {RADIANCE: (RADIANCE_DIMS, f.radiance,
                       {"rank_used": f.rank, "transform": f.transform.name,
                        "eps": f.transform.eps, "error": attrs.get("error"),
                        "long_name": f"radiance rebuilt as {f.transform.name} of U S V^T"})}
    data.update({name: (dims, getattr(f, name.lower())) for name, dims in FACTOR_DIMS.items()})
    return xr.Dataset(data, coords=coords, attrs=attrs)


def total_energy(group, s: np.ndarray) -> float:
    """``||A||_F^2`` of the compressed matrix (from the stored error), else ``sum S^2``."""
    norm = (group.attrs.get("error") or {}).get("frobenius_norm")
    return float(norm) ** 2 if norm else max(float(np.sum(s**2)), 1e-300)


def _summary(group) -> dict[str, Any]:
    s = np.asarray(group["S"][:], np.float64)
    energy = np.cumsum(s**2) / total_energy(group, s)
    nv, nl, ny, nx, nc = group.attrs.get("source_shape", [0] * 5)
    rank = int(s.size)
    original = nv * nl * ny * nx * nc * 4
    factors = (nv * nl * nc + ny * nx + 1) * rank * 4
    stored = sum(int(group[n].nbytes_stored()) for n in ("U", "S", "V"))
    return {
        "sampling": sampling_summary(group),
        "compression": {
            "rank": rank,
            "singular_values": s.tolist(),
            "energy_captured": {str(k): float(energy[k - 1]) for k in
                                sorted({1, 2, 4, 8, 16, 32, 64, 128, 256, rank}) if k <= rank},
            "error": group.attrs.get("error"),
            "svd": group.attrs.get("svd"),
            "transform": group.attrs.get("transform"),
            "original_bytes": original,
            "factor_bytes": factors,
            "ratio": original / factors if factors else None,
            "ratio_on_disk": original / stored if stored else None,
        },
        # the descriptive header of the DFMF file a store was ingested from
        "dfmf": group.attrs.get("dfmf"),
    }


def _lines(summary: dict[str, Any]) -> list[str]:
    c = summary["compression"]
    s = c["singular_values"]
    err = c["error"] or {}
    lines = sampling_lines(summary["sampling"])
    lines.append(f"compression: rank {c['rank']}, {c['ratio']:.1f}x smaller than the float32 "
                 f"radiance ({c['ratio_on_disk']:.1f}x on disk)")
    lines.append(f"  singular values {s[0]:.4g} ... {s[-1]:.4g}; share of ||A||^2 captured: "
                 + ", ".join(f"{k}: {v:.6f}" for k, v in c["energy_captured"].items()))
    if "log_relative_frobenius" in err:
        lines.append(f"  relative error (log domain): {err['log_relative_frobenius']:.4g}"
                     + (f"; average ABRDF RMSE (linear): {err['abrdf_rmse']:.4g}"
                        if "abrdf_rmse" in err else ""))
    if c["svd"]:
        lines.append("  " + ", ".join(f"{k}={v}" for k, v in c["svd"].items()))
    if c["transform"]:
        lines.append(transform_line(c["transform"]))
    if summary.get("dfmf"):
        lines += dfmf_lines(summary["dfmf"], what="source file")
    return lines


def transform_line(transform: dict[str, Any]) -> str:
    """How a store's values decode to radiance (its ``transform`` attrs), one line."""
    name, eps = transform.get("name", "log"), transform.get("eps")
    model = transform.get("dfmf_colour_model")
    formula = (DFMF_MODELS[model][1] if model in DFMF_MODELS
               else transform.get("formula") or ("radiance = values" if name == "linear"
                                                 else "radiance = exp(values) - eps"))
    return (f"transform: {name}" + (f", eps {eps:g}" if name != "linear" and eps else "")
            + (f"; DFMF colour model {model}" if model is not None else "")
            + f": {formula}")


def dfmf_lines(meta: dict[str, Any], *, what: str = "file") -> list[str]:
    """Text lines of a DFMF file's descriptive header (:meth:`tasks.dfmf.DfmfHeader.metadata`)."""
    xml = meta.get("xml") or ""
    first = xml.strip().splitlines()[0] if xml.strip() else ""
    scalar = {2: "float16", 4: "float32", 8: "float64"}.get(meta.get("scalar_bytes"), "?")
    ks = meta.get("components") or []
    lines = [f"{what} header (DFMF metadata version {meta.get('version')}): measurement setup "
             f"{meta.get('measurement_setup')!r}, image sensor {meta.get('image_sensor')!r}, "
             f"light source {meta.get('light_source')!r}",
             f"  {meta.get('ppmm', 0):g} ppmm, RGB scale "
             + ", ".join(f"{v:g}" for v in meta.get("rgb_scale") or ())
             + f", channels {','.join(meta.get('channel_names') or ())}, colour model "
             f"{meta.get('colour_model')}, components per channel "
             f"{'+'.join(map(str, ks))} = {sum(ks)} ({scalar}), cosine flag "
             f"{'set' if meta.get('cosine') else 'not set'}"
             + (f", {meta['rotations']} rotation matrices" if meta.get("rotations") else ""),
             f"  XML: {len(xml)} characters" + (f", first line {first[:100]!r}"
                                                + ("..." if len(first) > 100 else "")
                                                if first else "")]
    lines += [f"  read as btflib reads it: {note}" for note in meta.get("notes") or ()]
    return lines


class Factors(Store):
    """What every store of factors has: ``U`` and ``S``, and the transform of its values."""

    @cached_property
    def transform(self) -> Transform:
        """How its values become radiance (:class:`tasks.transform.Transform`)."""
        return Transform.from_attrs(self.group.attrs["transform"])

    @property
    def rank(self) -> int:
        """Components stored."""
        return int(self.group["S"].shape[0])

    def layer_scale(self, lights) -> np.ndarray | None:
        """A cosine store's scale of layers lit by ``lights`` (indices), else None."""
        return self.transform.layer_scale(self.directions.theta_light[np.asarray(lights)])


class CompressedStore(Factors):
    """A compressed store: ``U``, ``S``, ``V`` of the range-reduced BTF matrix, its transform."""

    names = (NAME,)
    what = "compressed store"
    check = staticmethod(check_compressed)
    summary = staticmethod(_summary)
    lines = staticmethod(_lines)

    @property
    def shape(self) -> tuple[int, ...]:
        """``(view, light, y, x, channel)`` of the radiance it describes."""
        nv, nl, nc, _ = self.group["U"].shape
        ny, nx = self.group["V"].shape[:2]
        return (nv, nl, ny, nx, nc)

    @property
    def error(self) -> dict[str, Any]:
        """The recorded errors (``error`` attribute; empty if none)."""
        return dict(self.group.attrs.get("error") or {})

    def dataset(self, chunks=None, rank: int | None = None):
        """The lazy Dataset of :func:`open_compressed` (``radiance`` rebuilt on demand).

        ``chunks`` is for radiance stores' interface: a compressed store's blocks are its own.
        """
        return open_compressed(self.path, rank=rank, group=self.group)


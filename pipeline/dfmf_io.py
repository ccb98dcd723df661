"""Bonn DFMF ``.btf`` files in and out: ``btf ingest FILE.btf OUT``, ``btf export STORE OUT.btf``.

A DFMF file is already a factorization (:mod:`tasks.dfmf`), so it becomes a compressed store
without ever expanding it to radiance: its per-channel factors are re-expressed exactly, up to
float32 rounding, as the store's one orthonormal ``U``, decreasing ``S`` and ``V``
(:func:`tasks.dfmf.joint_u`, :func:`tasks.dfmf.svd_map`), and the colour model becomes the
store's ``transform`` (:mod:`tasks.transform`). Two passes over the file's ``S V`` by texel
tiles (its Gram matrix, then ``V`` itself) read it twice and hold one tile at a time; ``U`` is
small (rows x components) and read whole. ``btf ingest`` comes here through the DFMF entry of
:mod:`pipeline.sources`; what it makes of the colour model is said in one line
(:func:`dfmf_colour_note`), as export says what the readers make of it
(:func:`dfmf_readers_note`).

Export writes a compressed store as a DFMF file that Bonn's readers (btflib, ``btf.hh``,
btf-extractor) open: each channel's values ``U_c S V^T`` at the channel's own rank
(:func:`tasks.dfmf.per_channel`), in float32 (exact) or float16 (``--half``), the transform as
its colour model. ``V`` is read once, a chunk at a time.

**Rows.** A file's texel ``y * width + x`` counts its rows from the *bottom* of the picture (an
OpenGL-style image: btf-extractor reverses them to make an image, and its images are upright
under Bonn's directions). A store's row 0 is the top row (docs/formats.md, "The frame"), so
store row ``y`` is file row ``height - 1 - y``, both ways (:func:`file_rows`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import mmap
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from pipeline.atomic import atomic_output
from pipeline.errors import BTFError
from pipeline.provenance import provenance
from pipeline.resume import Progress
from pipeline.session import Session
from pipeline.stores.base import RADIANCE, Directions
from pipeline.stores.compressed import create_compressed_store
from tasks.dfmf import (
    ChannelBlock,
    DfmfError,
    DfmfHeader,
    channel_head,
    degrees,
    header_bytes,
    joint_u,
    layout,
    parse_header,
    per_channel,
    radians,
    svd_map,
)
from tasks.sampling import known_sampling
from tasks.transform import DFMF_EPS, DFMF_MODELS

HALF_MAX = float(np.finfo(np.float16).max)
# From this many images on, a band of S V is converted to float32 once and multiplied by BLAS
# (faster than the compiled product, which converts inside it and wins for a few images).
GEMM_ROWS = 8
# transform name -> DFMF colour model written by export
COLOUR_MODEL = {"log": 12, "linear": 0, "ylog-uv": 9, "ylog-ulog-vlog": 10,
                "ylog-uv-over-y": 11}
# the colour models' values in a few words (tasks.transform.DFMF_MODELS has the formulas)
DFMF_MODEL_WORDS = {
    0: "RGB, linear", 1: "YUV, linear", 3: "PCA, linear", 4: "YCoCg, linear",
    9: "Y log, U/V linear; YUV to linear RGB", 10: "Y log, U/V signed log; YUV to linear RGB",
    11: "Y log, U/V over Y; YUV to linear RGB", 12: "log of each channel",
}


def read_header(path: str | Path) -> DfmfHeader:
    """The header of a DFMF file, or one :class:`BTFError` naming the file and the fault."""
    path = Path(path)
    if not path.is_file():
        raise BTFError(f"{path}: no such file")
    fd = os.open(path, os.O_RDONLY)
    try:
        return parse_header(lambda offset, n: os.pread(fd, n, offset), os.fstat(fd).st_size)
    except DfmfError as exc:
        raise BTFError(f"{path}: {exc}") from None
    finally:
        os.close(fd)


def channel_u(path: str, block: ChannelBlock) -> np.ndarray:
    """One channel's ``U`` (rows x k) as float64."""
    values = np.fromfile(path, dtype=block.dtype, count=block.rows * block.k,
                         offset=block.u_offset)
    return values.reshape(block.rows, block.k).astype(np.float64)


def file_rows(ys: slice, height: int) -> slice:
    """The file's texel rows that hold store rows ``ys``, in the file's (bottom-up) order."""
    return slice(height - ys.stop, height - ys.start)


def _read_rows(f, block: ChannelBlock, width: int, ys: slice, xs: slice) -> np.ndarray:
    """Channel ``block``'s ``S V`` rows of texels ``ys x xs`` from an open file.

    Read into a fresh buffer (no memory map: mapped pages would count towards the process's
    memory as the file is read), one read for whole rows, else one per texel row.
    """
    k, item = block.k, block.scalar
    if xs.start == 0 and xs.stop == width:
        f.seek(block.sxv_offset + ys.start * width * k * item)
        data = np.fromfile(f, block.dtype, (ys.stop - ys.start) * width * k)
        return data.reshape(-1, k)
    out = np.empty((ys.stop - ys.start, xs.stop - xs.start, k), block.dtype)
    for i, y in enumerate(range(ys.start, ys.stop)):
        f.seek(block.sxv_offset + (y * width + xs.start) * k * item)
        f.readinto(memoryview(out[i]).cast("B"))
    return out.reshape(-1, k)


def sxv_tile(path: str, header: DfmfHeader, ys: slice, xs: slice, *, ones: bool = False,
             dtype=np.float64) -> np.ndarray:
    """The file's ``S V`` rows of a texel tile, channels side by side: ``(texels, sum k_c)``.

    ``ys`` are store rows (top first); the texels come in the store's order, row-major from the
    tile's top row. With ``ones`` a last column of 1 (a linear colour model's mean) is added.
    Only the tile's bytes are read.
    """
    rows, cols = ys.stop - ys.start, xs.stop - xs.start
    with open(path, "rb") as f:
        parts = [_as_float(_read_rows(f, b, header.width, file_rows(ys, header.height), xs)
                           .reshape(rows, cols, b.k)[::-1].reshape(rows * cols, b.k), dtype)
                 for b in header.channels]
    if ones:
        parts.append(np.ones((parts[0].shape[0], 1), dtype))
    return np.concatenate(parts, axis=1)


def _as_float(values: np.ndarray, dtype) -> np.ndarray:
    """``values`` as ``dtype``; float16 through the compiled converter (numpy's is 10x slower)."""
    if values.dtype.itemsize != 2:
        return values.astype(dtype)
    from tasks.dfmf_kernel import halves_to_float32

    out = np.empty(values.shape, np.float32)
    halves_to_float32(np.ascontiguousarray(values).view("<u2"), out)
    return out.astype(dtype, copy=False)


def decode_pairs(path: str, header: DfmfHeader, pairs: list[tuple[int, int]], *,
                 band: int | None = None, threads: int = 2) -> np.ndarray:
    """Radiance images ``(n, height, width, channel)`` of (view, light) pairs, from the file.

    The images are upright, row 0 the top row as in a store (the file's rows reversed: a view,
    not a copy).

    Decoded as Bonn's readers do (:mod:`tasks.transform`'s colour models, a cosine flag
    divided out), without a store: per band of ``band`` texels (default: two bands per thread
    for a few images, bands of a few MiB of output for many), each channel's ``S V`` rows are
    multiplied where the file is mapped with the pairs' rows of ``U`` (float16 converted by
    the CPU inside the compiled product, :mod:`tasks.dfmf_kernel`), then decoded in place;
    bands run on the calling thread and ``threads - 1`` others. Memory holds the images and
    the bands in flight, whatever the file's size: a band's pages of the file are dropped from
    the process once it is done.
    """
    from threadpoolctl import threadpool_limits

    from tasks.dfmf_kernel import decode_colour, halves_product

    lights, texels = len(header.theta_light), header.width * header.height
    rows = np.array([v * lights + li for v, li in pairs], np.int64)
    model, eps, matrix, mean = _kernel_model(header)
    scale = (1.0 / np.maximum(np.cos(np.asarray(header.theta_light)[rows % lights]), 1e-6)
             if header.cosine else np.ones(len(rows))).astype(np.float32)
    out = np.empty((len(rows), texels, len(header.channels)), np.float32)
    if band is None:
        band = max(4096, min(-(-texels // (2 * threads)),
                             (4 << 20) // (4 * len(rows) * len(header.channels))))

    # The file is mapped, not read: a band's S V is multiplied where the page cache holds it
    # (no copy), and its pages leave this process once the band is done, so resident memory
    # holds the images and the bands in flight, whatever the file's size.
    with open(path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as mapped:
        if len(mapped) < header.end:
            raise BTFError(f"{path}: truncated: {len(mapped)} bytes where the header "
                           f"promises {header.end}")
        u_rows = [_as_float(np.frombuffer(mapped, b.dtype, b.rows * b.k, b.u_offset)
                            .reshape(b.rows, b.k)[rows], np.float32) for b in header.channels]

        def one_band(t0: int) -> None:
            t1 = min(t0 + band, texels)
            for c, b in enumerate(header.channels):
                start, size = b.sxv_offset + t0 * b.k * b.scalar, (t1 - t0) * b.k * b.scalar
                sxv = np.frombuffer(mapped, b.dtype, (t1 - t0) * b.k, start)
                sxv = sxv.reshape(t1 - t0, b.k)
                if b.scalar == 2 and len(rows) < GEMM_ROWS:  # converted inside the product
                    halves_product(u_rows[c], sxv.view("<u2"), out[:, t0:t1, c])
                else:  # converted once, then BLAS
                    out[:, t0:t1, c] = u_rows[c] @ _as_float(sxv, np.float32).T
                del sxv  # the buffer export ends before the pages are dropped
                _release(mapped, start, size)
            decode_colour(out[:, t0:t1], model, eps, matrix, mean, scale)

        # the bands are the parallelism: BLAS (many images only) on one thread in each
        with (threadpool_limits(1, user_api="blas") if len(rows) >= GEMM_ROWS
              else contextlib.nullcontext()):
            _run_shared(one_band, range(0, texels, band), threads)
    return out.reshape(len(rows), header.height, header.width, -1)[:, ::-1]


@functools.cache
def _pool(threads: int) -> ThreadPoolExecutor:
    """Threads that decode bands, kept between calls.

    Starting them costs about a tenth of a millisecond, a fair part of one small image's time.
    """
    return ThreadPoolExecutor(threads, thread_name_prefix="btf-dfmf")


def _run_shared(work, items, threads: int) -> None:
    """``work(item)`` for every item, on the calling thread and ``threads - 1`` kept ones.

    Each takes the next item when it is free: the caller works instead of waiting.
    """
    lock, todo = threading.Lock(), iter(items)

    def drain() -> None:
        while True:
            with lock:
                item = next(todo, None)
            if item is None:
                return
            work(item)

    helpers = [_pool(threads - 1).submit(drain) for _ in range(threads - 1)]
    drain()
    for helper in helpers:
        helper.result()


def _release(mapped: mmap.mmap, start: int, size: int) -> None:
    """Drop the pages of ``mapped[start:start + size]`` from this process, not the page cache.

    Only the whole pages inside the range: a neighbouring band's are kept.
    """
    first = -(-start // mmap.PAGESIZE) * mmap.PAGESIZE
    last = (start + size) // mmap.PAGESIZE * mmap.PAGESIZE
    if last > first:
        mapped.madvise(mmap.MADV_DONTNEED, first, last - first)


def _kernel_model(header: DfmfHeader) -> tuple[int, float, np.ndarray, np.ndarray]:
    """The colour model as :func:`tasks.dfmf_kernel.decode_colour` takes it."""
    from tasks.dfmf_kernel import CODES, LINEAR
    from tasks.transform import dfmf_colour_matrix

    name = DFMF_MODELS[header.colour_model][0]
    nc = len(header.channels)
    if name == "linear":
        m, mean = dfmf_colour_matrix(header.colour_model, np.asarray(header.colour_matrix),
                                     np.asarray(header.colour_mean), nc)
        return LINEAR, 0.0, m.astype(np.float32), mean.astype(np.float32)
    return CODES[name], DFMF_EPS, np.eye(nc, dtype=np.float32), np.zeros(nc, np.float32)


def _gram(path: str, header: DfmfHeader, ys: slice, xs: slice, ones: bool) -> np.ndarray:
    c = sxv_tile(path, header, ys, xs, ones=ones)
    return c.T @ c


def _v_tile(path: str, header: DfmfHeader, ones: bool, vmap: np.ndarray, *,
            block_info=None) -> np.ndarray:
    (y0, y1), (x0, x1), _ = block_info[None]["array-location"]
    c = sxv_tile(path, header, slice(y0, y1), slice(x0, x1), ones=ones)
    return (c @ vmap).astype(np.float32).reshape(y1 - y0, x1 - x0, -1)


def store_transform(header: DfmfHeader) -> dict:
    """The ``transform`` attrs of a store ingested from a file with this header."""
    name, formula = DFMF_MODELS[header.colour_model]
    eps = DFMF_EPS if name != "linear" else 0.0
    out = {"name": name, "formula": formula, "eps": eps, "clamp": False,
           "dfmf_colour_model": header.colour_model}
    if header.cosine and name != "linear":  # the linear models fold it into U
        out.update(cosine=True, formula=f"({formula}) / cos(theta_light): the file's cosine "
                                        "flag")
    return out


def dfmf_colour_note(model: int, *, cosine: bool = False) -> str:
    """What ingest does with a DFMF file's colour model ``model`` (one line)."""
    name, formula = DFMF_MODELS[model]
    words = DFMF_MODEL_WORDS.get(model, formula)
    if name == "linear":
        note = (f"DFMF colour model {model} ({words}) kept as linear values (transform linear)"
                if model == 0 else
                f"DFMF colour model {model} ({words}) folded into U: the store holds linear "
                "RGB (transform linear)")
    else:
        note = (f"DFMF colour model {model} ({words}, eps {DFMF_EPS:g}) kept as the store's "
                f"transform ({name})")
    if cosine:
        note += "; the file's cosine flag is set: values divided by cos(theta_light)"
    return note


def _joint_u(params, src: str, header: DfmfHeader) -> tuple[np.ndarray, bool]:
    """The file's per-channel ``U`` as one (:func:`tasks.dfmf.joint_u`), errors naming the file."""
    try:
        return joint_u(header, [channel_u(src, b) for b in header.channels])
    except DfmfError as exc:
        raise BTFError(f"{params.src}: {exc}") from None


def _log_file(session: Session, header: DfmfHeader, out: str) -> None:
    """Log the file's sampling, size, channels, components and colour model, and its reading.

    The colour line says what ingest makes of the model (:func:`dfmf_colour_note`).
    """
    ks = [b.k for b in header.channels]
    session.log(f"ingest: Bonn DFMF file, {len(header.theta_view)} views x "
                f"{len(header.theta_light)} lights, {header.height} x "
                f"{header.width} texels, channels {','.join(header.channel_names)} with "
                f"{'+'.join(map(str, ks))} components ({header.channels[0].dtype.name}), "
                f"colour model {header.colour_model} -> {out}")
    session.log("ingest: colour: " + dfmf_colour_note(header.colour_model,
                                                      cosine=header.cosine))
    for note in header.notes:
        session.log(f"ingest: note: {note}")


def _ingest_attrs(params, header: DfmfHeader, directions: Directions) -> dict:
    """The store's attrs before the SVD: source, shape, transform, file metadata, provenance."""
    views, lights = len(header.theta_view), len(header.theta_light)
    return {"source": "ingest",
            "source_btf_kind": directions.kind,
            "source_shape": [views, lights, header.height, header.width,
                             len(header.channels)],
            "transform": store_transform(header), "dfmf": header.metadata(),
            "source_sampling": known_sampling(directions.theta_view, directions.phi_view,
                                              directions.theta_light, directions.phi_light)
            or "dfmf file",
            "provenance": provenance("ingest", params)}


def _file_gram(src: str, header: DfmfHeader, regions, ones: bool,
               session: Session) -> np.ndarray:
    """The Gram matrix of the file's ``S V``, one read of the file.

    Again on a resumed run: summed over tiles in a fixed tree, it gives the same ``V`` bit
    for bit, and the client gets one matrix.
    """
    import dask

    from pipeline.graphs.factors import pairwise_sum

    grams = [dask.delayed(_gram, pure=True)(src, header, ys, xs, ones)
             for ys, xs in regions]
    (g,) = session.compute(pairwise_sum(grams))
    return g


def _svd_attrs(u: np.ndarray, g: np.ndarray, s: np.ndarray, ks: list[int]) -> dict:
    """The ``svd`` and ``error`` attrs: the rank, and the norm the dropped components had."""
    total = float(np.trace(u.T @ u @ g))  # ||U (SV)^T||_F^2 of the file's values
    return {"svd": {"rank": len(s), "method": "exact SVD of the file's per-channel factors "
                    "(QR of U, Gram matrix of S V)", "file_components": ks},
            "error": {"frobenius_norm": float(np.sqrt(max(total, 0.0))),
                      "dropped_relative_frobenius": float(np.sqrt(
                          max(total - float(np.sum(s**2)), 0.0) / max(total, 1e-300)))}}


def _directions_channels(header: DfmfHeader) -> tuple[Directions, tuple[str, ...]]:
    """The store's directions (degrees) and channel names for a file's header."""
    directions = Directions(*degrees(header.theta_view, header.phi_view),
                            *degrees(header.theta_light, header.phi_light))
    # models 0 and 12 keep the file's channels (any number: multispectral); the others are RGB
    channels = header.channel_names if header.colour_model in (0, 12) else ("R", "G", "B")
    return directions, channels


def ingest_dfmf(params, session: Session) -> Path:
    """``btf ingest FILE.btf OUT``: a DFMF file as a compressed store, without expansion."""
    import dask.array as da
    from dask.array.core import normalize_chunks, slices_from_chunks

    from pipeline import chunk_io

    if params.shard:
        raise BTFError(f"{params.src}: --shard does not apply to a DFMF file (its compressed "
                       "store is small: U, S and V in chunks of --chunk texels)")
    src = str(Path(params.src).absolute())
    header = read_header(src)
    views, lights = len(header.theta_view), len(header.theta_light)
    nc = len(header.channels)
    directions, channels = _directions_channels(header)
    u, ones = _joint_u(params, src, header)
    _log_file(session, header, params.out)
    layout = params.layout()  # V in --dtype: float32 unless asked
    chunk = min(layout.chunk, header.height, header.width)
    tiles = normalize_chunks((chunk, chunk), (header.height, header.width))
    attrs = _ingest_attrs(params, header, directions)
    with atomic_output(params.out, directory=True, overwrite=params.overwrite,
                       resume=attrs["provenance"]) as tmp:
        progress = Progress(tmp)
        g = _file_gram(src, header, slices_from_chunks(tiles), ones, session)
        new_u, s, vmap = svd_map(u, g)
        rank = len(s)
        attrs.update(_svd_attrs(u, g, s, [b.k for b in header.channels]))

        def create():
            group = create_compressed_store(
                tmp, directions=directions, channels=channels, ny=header.height,
                nx=header.width, rank=rank, chunk=chunk, dir_chunk=layout.dir_chunk,
                attrs=attrs, v_dtype=layout.dtype)
            # chunk by chunk in this thread (pipeline.chunk_io): through zarr's event loop the
            # 1,510 small chunks of a 151 x 151 dome's U took 1.5 s
            chunk_io.write(group["U"], (slice(None),) * 4,
                           new_u.reshape(views, lights, nc, rank).astype(np.float32))
            group["S"][...] = s.astype(np.float32)
            return group

        group = progress.skeleton(create)
        joint = da.map_blocks(_v_tile, src, header, ones, vmap, dtype=np.float32,
                              chunks=(*tiles, (rank,)), meta=np.empty((0, 0, 0), np.float32))
        from pipeline.graphs.blocks import store_aligned

        session.compute(store_aligned([joint], [group["V"]], progress=progress))
    return Path(params.out)


DECODE_BYTES = 16 << 20  # float32 layers a --radiance ingest task decodes at once, at most


def _decoded_block(src: str, header: DfmfHeader, view: int, lights: tuple[int, int],
                   dtype: str) -> np.ndarray:
    """Layers ``lights`` of ``view`` decoded, ``(1, lights, height, width, channel)``."""
    from pipeline.stores.radiance import stored

    images = decode_pairs(src, header, [(view, li) for li in range(*lights)], threads=1)
    # one pass, no mask: a float64 sum of finite float32 values is finite
    with np.errstate(invalid="ignore"):  # Inf - Inf: NaN, found below
        finite = np.isfinite(np.sum(images, dtype=np.float64))
    if not finite:
        bad = ~np.isfinite(images)
        i, y, x, c = np.argwhere(bad)[0]
        raise BTFError(f"{src}: {int(bad.sum())} layer value(s) decode to NaN or Inf, the "
                       f"first at view={view}, light={lights[0] + i}, y={y}, x={x}, "
                       f"channel={c}")
    where = f"{src}: view {view}, lights {lights[0]}-{lights[1] - 1}"
    return np.ascontiguousarray(stored(images[None], np.dtype(dtype), where))


def ingest_dfmf_radiance(params, session: Session) -> Path:
    """``btf ingest FILE.btf OUT --radiance``: every layer decoded into a radiance store.

    One task per view and block of lights decodes its layers from the mapped file
    (:func:`decode_pairs`, on the task's thread) and writes them, in the store's layout;
    memory per task is its block. No SVD: the layers are those Bonn's readers decode, not
    ``btf ingest`` then ``btf reconstruct`` (whose factors are the file's rotated into one
    joint basis, the same values to float32 rounding).
    """
    import dask
    import dask.array as da
    from dask.base import tokenize

    from pipeline.graphs.blocks import aligned_chunks, store_aligned
    from pipeline.stores.radiance import create_radiance_store

    src = str(Path(params.src).absolute())
    header = read_header(src)
    views = len(header.theta_view)
    _joint_u(params, src, header)  # what the factor ingest refuses, refused here too
    directions, channels = _directions_channels(header)
    _log_file(session, header, params.out)
    layout = params.layout()
    attrs = {"source": "ingest", "source_btf_kind": directions.kind,
             "ingest": {"format": "dfmf", "decoded": True,
                        "colour": dfmf_colour_note(header.colour_model, cosine=header.cosine)},
             "dfmf": header.metadata(), "provenance": provenance("ingest", params)}
    with atomic_output(params.out, directory=True, overwrite=params.overwrite,
                       resume=attrs["provenance"]) as tmp:
        progress = Progress(tmp)
        group = progress.skeleton(lambda: create_radiance_store(
            tmp, directions=directions, ny=header.height, nx=header.width, channels=channels,
            layout=layout, attrs=attrs))
        radiance = group[RADIANCE]
        session.log(f"ingest: decoding every layer into radiance ({layout.dtype})")
        if progress.count():
            session.log(f"ingest: resuming: {progress.count()} blocks already written")
        chunks = aligned_chunks(radiance)
        shape = (header.height, header.width, len(channels))
        # tasks of whole light chunks, of up to DECODE_BYTES of float32 decoded (or one chunk,
        # if larger): a decode's fixed cost (mapping the file, its bands) is paid once for
        # several chunks; a task holds its decoded layers and their copy in the store's dtype
        layer = int(np.prod(shape)) * 4
        step = max(1, DECODE_BYTES // max(1, layer * chunks[1][0]))
        lights = [sum(chunks[1][i:i + step]) for i in range(0, len(chunks[1]), step)]
        name = "dfmf-decode-" + tokenize(src, header.metadata(), radiance.dtype.str, lights)
        # no chunk of decoded radiance is all fill value (NaN is refused): zarr's check for
        # empty chunks skipped, as the image ingest does
        target = radiance.with_config({"write_empty_chunks": True})
        rows = []
        for v in range(views):
            blocks, start = [], 0
            for i, n in enumerate(lights):
                block = dask.delayed(_decoded_block, traverse=False)(
                    src, header, v, (start, start + n), radiance.dtype.str,
                    dask_key_name=(name, v, i))
                blocks.append(da.from_delayed(block, (1, n, *shape), dtype=radiance.dtype))
                start += n
            rows.append(da.concatenate(blocks, axis=1))
        layers = da.concatenate(rows, axis=0).rechunk(chunks)  # whole images: cut into tiles
        session.compute(store_aligned([layers], [target], progress=progress))
    return Path(params.out)


def dfmf_readers_note(model: int) -> str:
    """What the common DFMF readers return for colour model ``model`` (one line, for export).

    From their code (docs/formats.md, "Which reader opens what"): btflib decodes every model;
    ``btf.hh`` and btf-extractor (the Mitsuba BTF plugin's reader) decode models 0 and 11
    only, clamp model 11 to [0, 1] and return the channel sums of any other model.
    """
    words = DFMF_MODEL_WORDS.get(model, DFMF_MODELS[model][1])
    if model == 0:
        return (f"colour model 0 ({words}): btflib, btf.hh and btf-extractor (the Mitsuba BTF "
                "plugin's reader) all return the values as they are")
    if model == 11:
        return (f"colour model 11 ({words}): btflib, btf.hh and btf-extractor (the Mitsuba BTF "
                "plugin's reader) decode it, but btf-extractor clamps RGB to [0, 1] (values "
                "above 1 are lost), writes U = a1 Y + eps for btflib's a1 (Y + eps) (up to "
                "2.5e-5 apart) and returns BGR")
    if model == 12:
        return (f"colour model 12 ({words}): btflib decodes it; btf.hh, btf-extractor and the "
                "Mitsuba BTF plugin decode only models 0 and 11 and return this model's "
                "channel sums a without the exp: radiance is exp(a) - "
                f"{DFMF_EPS:g} per channel; or export the layers as EXR for them "
                "(btf export STORE FOLDER)")
    return (f"colour model {model} ({words}): btflib decodes it; btf.hh, btf-extractor and the "
            "Mitsuba BTF plugin decode only models 0 and 11 and return this model's channel "
            "sums undecoded (log Y and U, V, not RGB); export the layers as EXR for them "
            "(btf export STORE FOLDER)")


def _written_header(group, directions: Directions, channels: tuple[str, ...], model: int,
                    ks: list[int], scalar: int, ny: int, nx: int, *, cosine: bool = False
                    ) -> DfmfHeader:
    """The header export writes: the store's directions, channels, size and colour model.

    The descriptive fields of a store ingested from a DFMF file are written back, and a
    cosine store's flag (its values are radiance x cos(theta_light), as the file's were).
    """
    meta = dict(group.attrs.get("dfmf") or {})
    tv, pv = radians(directions.theta_view, directions.phi_view)
    tl, pl = radians(directions.theta_light, directions.phi_light)
    header = DfmfHeader(
        version=4, rotations=0,
        measurement_setup=meta.get("measurement_setup", "btf-pipeline export"),
        image_sensor=meta.get("image_sensor", ""), light_source=meta.get("light_source", ""),
        ppmm=float(meta.get("ppmm", 0.0)),
        rgb_scale=tuple(meta.get("rgb_scale", (1.0, 1.0, 1.0))), cosine=cosine,
        xml=meta.get("xml", ""), channel_names=channels, theta_view=tv, phi_view=pv,
        theta_light=tl, phi_light=pl, width=nx, height=ny, components=max(ks),
        colour_model=model, colour_mean=(0.0, 0.0, 0.0),
        colour_matrix=((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)), channels=())
    return dataclasses.replace(header, channels=layout(
        len(header_bytes(header)), scalar, ks, directions.views * directions.lights, ny * nx))


def export_dfmf(store: str, out: str, *, half: bool, overwrite: bool,
                session: Session) -> Path:
    """``btf export STORE OUT.btf``: a compressed store as a DFMF file for renderers.

    ``V`` is read a chunk at a time; each chunk's rows of every channel's ``S V`` are written at
    their offsets, so memory holds one chunk whatever the store's size.
    """
    from dask.array.core import normalize_chunks, slices_from_chunks

    from pipeline.stores import CompressedStore, open_store

    source = open_store(store, checked=False)
    if not isinstance(source, CompressedStore):
        raise BTFError(f"{store}: a {source.kind!r} store; a DFMF file holds "
                       "factors: compress it first (btf compress STORE OUT.zarr), then export "
                       "the compressed store")
    source.validate()
    group = source.group
    transform = source.transform
    model = COLOUR_MODEL[transform.name]
    d = source.directions
    channels = source.channels
    u = np.asarray(group["U"][...], np.float64)  # small: rows x channels x K
    s = np.asarray(group["S"][...], np.float64)
    v = group["V"]
    ny, nx, k = v.shape
    per = [per_channel(u[:, :, c, :].reshape(-1, k), s) for c in range(len(channels))]
    ks = [p[0].shape[1] for p in per]
    scalar = 2 if half else 4
    dtype = np.dtype("<f2" if half else "<f4")
    if half and max(float(p[1][0]) for p in per) > HALF_MAX:
        session.log(f"export: note: singular values above {HALF_MAX:g} are written as "
                    f"{HALF_MAX:g} in float16 (Bonn's readers do not use them)")
    header = _written_header(group, d, channels, model, ks, scalar, ny, nx,
                             cosine=transform.cosine)
    session.log(f"export: {d.views} views x {d.lights} lights, {ny} x {nx} texels as a DFMF "
                f"file, colour model {model} ({transform.name}), components "
                f"{'+'.join(map(str, ks))}, {'float16' if half else 'float32'} -> {out}")
    session.log(f"export: readers: {dfmf_readers_note(model)}")
    if transform.name != "linear" and transform.eps != DFMF_EPS:
        session.log(f"export: note: the store's eps is {transform.eps:g}, Bonn's readers "
                    f"subtract {DFMF_EPS:g}: every decoded value is "
                    f"{transform.eps - DFMF_EPS:+.3g} off (compress with --eps {DFMF_EPS:g} "
                    "for an exact file)")
    if d.views != d.lights:
        session.log(f"export: note: {d.views} view(s) and {d.lights} lights: btf.hh and "
                    "btf-extractor open only files with as many views as lights (btflib "
                    "opens any)")
    with atomic_output(out, directory=False, overwrite=overwrite) as tmp:
        with open(tmp, "wb") as f:
            f.write(header_bytes(header))
            f.truncate(header.end)
            for block, (pc, sigma, _) in zip(header.channels, per, strict=True):
                f.seek(block.s_offset - len(channel_head(block)))
                f.write(channel_head(block))
                top = HALF_MAX if half else np.inf
                f.write(np.minimum(sigma, top).astype(dtype).tobytes())
                f.write(pc.astype(dtype).tobytes())
            for ys, xs, _ in slices_from_chunks(normalize_chunks(v.chunks, v.shape)):
                _write_tile(f, np.asarray(v[ys, xs]), ys, xs, nx,
                            header.channels, [p[2] for p in per], dtype, store)
    return Path(out)


def _write_tile(f, tile: np.ndarray, ys: slice, xs: slice, width: int,
                blocks: tuple[ChannelBlock, ...], maps: list[np.ndarray], dtype, store: str
                ) -> None:
    """Each channel's ``S V`` rows of one ``V`` tile, written at their offsets in the file.

    A tile's rows are runs of ``x`` in the file (texel ``y * width + x``, rows from the
    bottom: store row ``y`` is file row ``height - 1 - y``): one write per row.
    """
    height = blocks[0].columns // width
    h, w, k = tile.shape
    flat = tile.reshape(-1, k).astype(np.float64)
    for block, vmap in zip(blocks, maps, strict=True):
        values = flat @ vmap
        if dtype.itemsize == 2 and np.abs(values).max(initial=0.0) > HALF_MAX:
            raise BTFError(f"{store}: S V values up to {np.abs(values).max():g} (texels "
                           f"{ys.start}:{ys.stop}, {xs.start}:{xs.stop}) do not fit float16; "
                           "export without --half")
        rows = values.astype(dtype).reshape(h, w * block.k)
        for i, y in enumerate(range(ys.start, ys.stop)):
            row = height - 1 - y
            f.seek(block.sxv_offset + (row * width + xs.start) * block.k * block.scalar)
            f.write(rows[i].tobytes())

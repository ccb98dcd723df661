"""Compression: out-of-core randomized SVD of a radiance store (paper 000, section 2.1).

The engine of ``btf compress`` (:mod:`pipeline.stages.compress` declares the stage) and of the
compression ``btf view`` does on the way.

The store is streamed one pass at a time as the driver (:mod:`tasks.rsvd`) asks for passes;
between passes only a sketch lives on the client, where it is re-orthonormalised. The sketch is
kept on one side of the BTF matrix (``--sketch``):

- texels (:func:`tasks.rsvd.randomized_svd`): texels x (rank + oversampling), streamed in row
  blocks (:mod:`pipeline.graphs.row_passes`); ``power_iters + 1`` passes. Client memory grows
  with the texels.
- one view (``--passes 1``, :func:`tasks.rsvd.randomized_svd` with ``one_pass``): one read of
  the store by texel tiles (:mod:`pipeline.graphs.tile_passes`), the texel-side co-range sketch
  written to a scratch array in the partial output and ``V`` formed from it tile by tile. The
  client holds rows x k; nothing grows with the texels.
- rows (:func:`tasks.rsvd.randomized_svd_rows`): rows x (rank + oversampling), streamed in
  texel tiles (:mod:`pipeline.graphs.tile_passes`), ``V`` written tile by tile;
  ``power_iters + 2`` passes. Client memory grows with the rows only.

``auto`` (for the multi-pass modes) keeps the texel side (one pass fewer) while its sketches
stay under :data:`TEXEL_SIDE_BYTES`, and takes the row side beyond that when there are fewer
rows than texels. ``--verify`` adds one pass, by texel tiles, against the stored factors.

Every pass's result is checkpointed in the partial output (:mod:`pipeline.resume`): a run
killed between passes is resumed by the same command from the pass it was in.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
from pathlib import Path

import numpy as np

from pipeline import storage
from pipeline.atomic import atomic_output
from pipeline.errors import BTFError
from pipeline.graphs.row_passes import (
    FAN_IN,
    RowBlock,
    memory_estimate,
    parts_kept,
    pass_graph,
    plan_row_blocks,
    raise_on_bad_data,
)
from pipeline.graphs.tile_passes import (
    SKETCH_FAN_IN,
    TexelTile,
    create_scratch,
    plan_tile_rows,
    plan_tiles,
    sketch_memory,
    sketch_pass_graph,
    sketch_vectors_graph,
    tile_memory,
    tile_pass_graph,
)
from pipeline.params import ParamError, check_seed, option
from pipeline.provenance import provenance
from pipeline.resume import PassCheckpoint, Progress
from pipeline.session import Session
from pipeline.stores import CompressedStore, RadianceStore, open_store
from pipeline.stores.base import RADIANCE, location
from pipeline.stores.compressed import create_compressed_store
from pipeline.stores.radiance import DTYPES
from tasks.rsvd import SIDES, randomized_svd, randomized_svd_rows
from tasks.svd import PassPart, Sketch

TEXEL_SIDE_BYTES = 256 << 20  # auto: the texel side while its client sketches stay below this
ONE_PASS_RANGE = 6  # --passes 1: range sketch columns per component (BENCHMARKS.md, issue 27)
SCRATCH = "sketch-scratch"  # the one-view co-range sketch, inside the partial output
# the scratch's layout, in the name the sketch pass's sums are kept under: sums kept by a btf
# that wrote another layout (such as (y, x, s)) are not taken, and the pass runs again
SCRATCH_LAYOUT = "s-y-x"


@dataclasses.dataclass(frozen=True)
class CompressSettings:
    """What a compression is asked: the store, the output and the SVD's options.

    ``btf compress``'s parameters (:class:`pipeline.stages.compress.CompressParams`, which
    adds nothing) and what ``btf view`` compresses a radiance store with on the way.
    """

    store: str = option(help="radiance store to compress, or a compressed store to bring to a "
                             "lower --rank (its factors truncated, or re-factored exactly)",
                        positional=True, path="in", metavar="IN")
    out: str = option(help="output compressed store (a .zarr directory)", positional=True,
                      path="out")
    rank: int = option(help="components to keep (K)", metavar="K")
    oversample: int | None = option(
        None, metavar="P", help="extra sketch columns (default: 10; with --passes 1: 5K + 1, "
                                "a range sketch of k = 6K + 1 columns and a co-range sketch of "
                                "2k + 1 rows, each at most the BTF matrix's rows)")
    power_iters: int | None = option(
        None, metavar="Q", help="power iterations, each one fused pass over the data "
                                "(default: 2, i.e. 3 passes)")
    passes: str = option("auto", metavar="auto|N", numbers_as_text=True,
                         help="passes over the data: auto (power iterations + 1, or + 2 with the "
                              "row-side sketch), 1 (a one-view sketch for stores too large to "
                              "read twice: one read by texel tiles, a scratch sketch of s x "
                              "texels float32 written and read once) or N >= 2")
    sketch: str = option("auto", metavar="auto|texels|rows",
                         help="which side of the BTF matrix the multi-pass sketches live on: "
                              "texels (client memory grows with the texels), rows (it grows "
                              "with the textures only; one pass more) or auto (texels while "
                              "that stays under 256 MiB, else the smaller side; an explicit "
                              "--passes keeps the texel side). --passes 1 has its own layout: "
                              "rows x k on the client, tiles of the co-range sketch in a "
                              "scratch array")
    tile_cache: str = option(
        "256MiB", metavar="SIZE", record=False,
        help="row side: keep a texel tile's whole column of the matrix in memory between the "
             "two products of a pass if it fits SIZE (e.g. 6GiB), so that the pass reads the "
             "store once instead of twice; each worker thread may then hold that much more "
             "(btf run --plan checks it against the workers' memory)")
    eps: float = option(1e-3, help="range reduction log(radiance + eps)")
    v_dtype: str | None = option(
        None, choices=DTYPES,
        help="the eigentextures' stored type: float16 halves V's bytes (the bulk of a "
             "compressed store) and rounds each value by at most 2^-11 of it (BENCHMARKS.md, "
             "'Precision'); default: float32, or a compressed input's own")
    seed: int = option(0, metavar="S", help="seed of the random test matrices")
    clamp: bool = option(False, help="clamp negative radiance to 0 instead of refusing it")
    verify: bool = option(False, help="one more pass: average ABRDF RMSE (paper 000, eq. 11) "
                                      "in linear radiance")
    overwrite: bool = option(False, record=False, help="replace OUT if it exists")

    def __post_init__(self):
        if self.rank < 1:
            raise ParamError("rank", f"must be at least 1, got {self.rank}")
        if self.oversample is not None and self.oversample < 0:
            raise ParamError("oversample", f"must be non-negative, got {self.oversample}")
        if self.power_iters is not None and self.power_iters < 0:
            raise ParamError("power_iters", f"must be non-negative, got {self.power_iters}")
        if not self.eps > 0:
            raise ParamError("eps", f"must be positive (it keeps log finite), got {self.eps}")
        check_seed(self.seed)
        self.tile_cache_bytes  # noqa: B018 (validates the size)
        if self.sketch not in ("auto", *SIDES):
            raise ParamError("sketch", f"must be auto, texels or rows, got {self.sketch!r}")
        if self.sketch == "rows" and self.passes == "1":
            raise ParamError("sketch", "the one-view sketch (--passes 1) has its own layout (by "
                                       "texel tiles, nothing grows with the texels); use "
                                       "--sketch auto")
        if self.passes != "auto":
            if not self.passes.isdigit() or int(self.passes) < 1:
                raise ParamError("passes", f"must be auto or a positive integer, got "
                                           f"{self.passes!r}")
            if int(self.passes) == 1 and self.power_iters:
                raise ParamError("power_iters", "cannot be combined with --passes 1")
            more = 2 if self.sketch == "rows" else 1  # the projection (and the V pass)
            if (int(self.passes) > 1 and self.power_iters is not None
                    and self.power_iters != int(self.passes) - more):
                raise ParamError("power_iters", f"{self.power_iters} power iterations take "
                                                f"{self.power_iters + more} passes, not "
                                                f"{self.passes}")

    @property
    def tile_cache_bytes(self) -> int:
        """``--tile-cache`` in bytes."""
        from dask.utils import parse_bytes

        try:
            value = parse_bytes(self.tile_cache)
        except (ValueError, TypeError):
            raise ParamError("tile_cache", f"expected a size such as 6GiB or 500MB, got "
                                           f"{self.tile_cache!r}") from None
        if value < 0:
            raise ParamError("tile_cache", f"must not be negative, got {self.tile_cache!r}")
        return value

    @property
    def one_pass(self) -> bool:
        """Whether to use the one-view sketch."""
        return self.passes == "1"

    def iterations(self, side: str = "texels") -> int:
        """Power iterations: passes before the projection pass (and the V pass on the rows)."""
        if self.passes != "auto":
            return max(int(self.passes) - (2 if side == "rows" else 1), 0)
        return 2 if self.power_iters is None else self.power_iters

    def side(self, rows: int, texels: int) -> str:
        """The side of the ``rows x texels`` BTF matrix the sketches live on."""
        if self.sketch != "auto":
            return self.sketch
        if self.passes != "auto" or texels <= rows:  # an exact pass count means the texel side
            return "texels"
        return "texels" if 6 * 8 * texels * (self.rank + self.extra) <= TEXEL_SIDE_BYTES \
            else "rows"

    @property
    def extra(self) -> int:
        """Oversampling actually used."""
        if self.oversample is not None:
            return self.oversample
        return (ONE_PASS_RANGE - 1) * self.rank + 1 if self.one_pass else 10


class _Passes:
    """The ``run_pass`` of :mod:`tasks.rsvd`: one pass over the store each call.

    Counts the passes over the store, logs them, and stops after the first if the data must be
    refused. Texel-side kinds run over row blocks; row-side kinds, the one-view sketch and the
    verification over texel tiles; ``sketch-vectors`` reads the scratch sketch, not the store.
    """

    def __init__(self, store: str, blocks: list[RowBlock], tiles: list[TexelTile],
                 tile_rows: list[RowBlock], out: str, planned: int, params: CompressSettings,
                 session: Session):
        self.store, self.blocks, self.params, self.session = store, blocks, params, session
        self.tiles, self.tile_rows, self.out, self.planned = tiles, tile_rows, out, planned
        self.scratch = storage.join(out, SCRATCH)
        self.progress = Progress(out)
        self.count = 0

    def __call__(self, kind: str, **arrays) -> PassPart:
        if kind == "sketch-vectors":  # from the scratch array: not a pass over the store
            # named after the map, so that V written from other factors is never kept
            digest = hashlib.sha256(np.ascontiguousarray(arrays["m"]).tobytes()).hexdigest()
            name = f"{kind}-{digest[:16]}"
            result, _ = self.progress.memo(name, lambda: self._vectors(name, arrays["m"]))
            return result
        self.count += 1
        what = {"power": f"power iteration {self.count}", "project": "projection",
                "sketch": "one-view sketch", "verify": "verification",
                "row-power": f"power iteration {self.count}", "row-gram": "projection",
                "row-vectors": "eigentextures"}[kind]
        by_tiles = kind.startswith("row-") or kind in ("verify", "sketch")
        name = f"pass-{self.count}-{kind}" + (f"-{SCRATCH_LAYOUT}" if kind == "sketch" else "")
        result, stored = self.progress.memo(name, lambda: self._run(name, kind, what,
                                                                    by_tiles, arrays))
        if stored:
            self.session.log(f"compress: pass {self.count}/{self.planned} ({what}): kept from "
                             "the interrupted run")
        if self.count == 1:
            raise_on_bad_data(result.check, self.params.store, self.params.clamp)
        return result

    def _run(self, name: str, kind: str, what: str, by_tiles: bool, arrays: dict) -> PassPart:
        # the bytes a part reads: a tile's column, or a row block of every texel
        last = self.tiles[-1]
        read = 4 * (self.tiles[0].texels * sum(b.rows for b in self.tile_rows) if by_tiles
                    else max(b.rows for b in self.blocks) * last.y1 * last.x1)
        fan_in = SKETCH_FAN_IN if kind == "sketch" else FAN_IN
        kept = PassCheckpoint.of(self.progress, name, (fan_in - 1) * read, sorted(arrays.items()))
        parts = len(self.tiles) if by_tiles else len(self.blocks)
        done = parts_kept(kept, parts, fan_in=fan_in)
        self.session.log(f"compress: pass {self.count}/{self.planned} ({what}, "
                         + (f"{parts} texel tiles" if by_tiles else f"{parts} row blocks")
                         + (f"; {done} kept from the interrupted run)" if done else ")"))
        common = {"eps": self.params.eps, "clamp": self.params.clamp, "first": self.count == 1,
                  "kept": kept}
        if kind == "sketch":
            sketch = arrays["sketch"]
            first, last = self.tiles[0], self.tiles[-1]
            if not done:  # else the killed run made it, and wrote the tiles kept
                create_scratch(self.scratch, last.y1, last.x1, sketch.s,
                               (first.y1 - first.y0, first.x1 - first.x0))
            graph = sketch_pass_graph(self.store, self.tiles, self.tile_rows, sketch=sketch,
                                      seed=arrays["seed"], scratch=self.scratch, **common)
        else:
            shared = {k: self.session.share(v) for k, v in arrays.items()}
            graph = tile_pass_graph(kind, self.store, self.tiles, self.tile_rows, shared=shared,
                                    out=self.out, cache=self.params.tile_cache_bytes, **common
                                    ) if by_tiles else \
                pass_graph(kind, self.store, self.blocks, shared=shared, **common)
        (result,) = self.session.compute(graph, reads=True)
        return result

    def _vectors(self, name: str, to_v: np.ndarray) -> PassPart:
        kept = PassCheckpoint.of(self.progress, name, (FAN_IN - 1) * 4 * self.tiles[0].texels
                                 * to_v.shape[0], to_v)
        done = parts_kept(kept, len(self.tiles))
        self.session.log(f"compress: eigentextures from the scratch sketch ({len(self.tiles)} "
                         "texel tiles; no read of the store"
                         + (f"; {done} kept from the interrupted run)" if done else ")"))
        graph = sketch_vectors_graph(self.scratch, self.tiles, self.session.share(to_v),
                                     self.out, kept=kept)
        (result,) = self.session.compute(graph, reads=True)
        return result


def peak_memory(params: CompressSettings, shape: tuple[int, ...], dir_chunk: int,
            tile: tuple[int, int], workers: int) -> dict[str, int]:
    """Peak memory of compressing a store of ``shape``, in bytes.

    The client's sketches, one task, and their total with ``workers`` tasks at once: the run
    logs it and ``btf run --plan`` checks it (one formula for both).
    """
    nv, nl, ny, nx, nc = shape
    m, n = nv * nl * nc, ny * nx
    extra = min(params.extra, min(m, n) - params.rank)
    texels = tile[0] * tile[1]
    tile_rows = plan_tile_rows(shape, dir_chunk, tile, sketch=params.one_pass)
    if params.one_pass:
        return sketch_memory(m, texels, Sketch.for_rank(params.rank, extra, m), tile_rows,
                             workers=workers)
    if params.side(m, n) == "rows":
        width = params.rank + extra
        client = 8 * 6 * m * width + FAN_IN * 8 * m * width  # sketches; shares being summed
        task = tile_memory(m, texels, width, tile_rows, cache=params.tile_cache_bytes)
        return {"client": client, "task": task, "total": client + workers * task}
    return memory_estimate(shape, plan_row_blocks(shape, dir_chunk), rank=params.rank,
                           extra=extra, workers=workers)


def _output_attrs(params: CompressSettings, store: RadianceStore, shape: tuple[int, ...]
                  ) -> dict:
    """The compressed store's attrs before the SVD: its source, transform and provenance."""
    source = store.attrs
    attrs = {
        "source": "compress",
        "source_btf_kind": store.kind,
        "source_shape": list(shape),
        "transform": {"name": "log", "formula": "log(radiance + eps)", "eps": params.eps,
                      "clamp": params.clamp},
        "provenance": provenance("compress", params),
    }
    for key in ("sampling", "material"):
        if key in source:
            attrs[f"source_{key}"] = source[key]
    return attrs


def _method(params: CompressSettings, side: str) -> str:
    """The ``svd.method`` attribute: how the factors were found."""
    if params.one_pass:
        return "one-view sketch"
    if side == "texels":
        return ("randomized SVD with fused power iterations, projected on the block Krylov "
                "space of the last two iterates")
    return ("randomized SVD with row-side fused power iterations (A A^T Q), projected on the "
            "Gram-orthonormalised A^T Q of the last")


def _verified(passes: _Passes, u: np.ndarray, s: np.ndarray, n: int, norm: float) -> dict:
    """``--verify``: one more pass for the average ABRDF RMSE and the measured error."""
    part = passes("verify", u=u, s=s)
    return {"abrdf_rmse": float(part.sums["rmse"][0]) / n,
            "log_relative_frobenius_measured": math.sqrt(part.frobenius2) / norm if norm
            else 0.0,
            "abrdf_rmse_definition": (
                "paper 000 eq. 11: mean over texels of the RMS difference of the texel's "
                "ABRDF (all view x light x channel values), linear radiance")}


def _say_plan(params: CompressSettings, session: Session, m: int, n: int, side: str,
              sketch: Sketch, memory: dict[str, int]) -> None:
    """Log the matrix, the sketch and the expected peak memory before the passes."""
    session.log(f"compress: {m} x {n} BTF matrix ({m * n * 4 / 2**30:.2f} GiB float32) to "
                f"rank {params.rank}, "
                + ("one pass by texel tiles" if params.one_pass
                   else f"sketches on the {side} side") + f" -> {params.out}")
    if params.one_pass:
        session.log(f"compress: one-view sketch k = {sketch.k}, s = {sketch.s}, t = "
                    f"{sketch.t}; scratch {n * sketch.s * 4 / 2**30:.2f} GiB written once and "
                    "read once (not the store)")
    session.log(f"compress: expected peak memory ~{memory['total'] / 2**30:.2f} GiB "
                f"(sketches {memory['client'] / 2**30:.2f} GiB, each task "
                f"{memory['task'] / 2**30:.2f} GiB)")


def _factor_attrs(params: CompressSettings, source: dict) -> dict:
    """The attrs of a compressed store made from a compressed one: its transform kept."""
    attrs = {key: source[key] for key in ("source_btf_kind", "source_shape", "transform",
                                          "dfmf", "source_sampling", "source_material")
             if key in source}
    return {**attrs, "source": "compress", "source_store": params.store,
            "provenance": provenance("compress", params)}


def _combined_error(source: dict, norm: float, part: float) -> dict:
    """The new store's error: the dropped share, and the source's error carried along."""
    out = {"frobenius_norm": norm, "dropped_relative_frobenius": part,
           "of_source": source or None}
    if source and "log_relative_frobenius" in source and source.get("frobenius_norm"):
        # relative to the matrix the source was compressed from; the truncation's share is
        # orthogonal to the source's own error for an exact SVD (Eckart-Young), so they add
        # in quadrature (an estimate for a randomized one)
        scale = norm / float(source["frobenius_norm"])
        out["log_relative_frobenius"] = math.hypot(float(source["log_relative_frobenius"]),
                                                   part * scale)
        out["log_relative_frobenius_note"] = (
            "the source's error and this truncation's, added in quadrature")
    return out


def compress_factors(params: CompressSettings, store: CompressedStore, session: Session
                     ) -> Path:
    """``btf compress`` of a compressed store: its first components, as an exact SVD.

    If ``U`` and ``V`` are orthonormal and ``S`` sorted (what ``btf compress`` and ``btf
    ingest FILE.btf`` write), the stored factors are an SVD already: the first ``--rank``
    components are the best approximation of that rank of the stored values, and are copied
    (truncation). Otherwise (an enlarged or cropped store, a store edited by hand) they are
    re-factored exactly first (:mod:`pipeline.graphs.factors`). One read of ``V`` either way,
    and one more to write the new ``V``.
    """
    import dask.array as da
    import zarr

    from pipeline.graphs.blocks import store_aligned
    from pipeline.graphs.factors import dropped, gram, is_svd, mapped_v
    from pipeline.stores.compressed import create_compressed_store
    from tasks.dfmf import svd_map

    group = store.group
    nv, nl, nc, k = group["U"].shape
    ny, nx = group["V"].shape[:2]
    name = group.attrs["transform"].get("name", "log")
    if params.rank > k:
        raise BTFError(f"{params.store}: --rank {params.rank} is more than the {k} components "
                       "this compressed store holds: its factors can only lose components "
                       "(compress the radiance it came from for more)")
    u = np.asarray(group["U"][...], np.float64).reshape(-1, k)
    s = np.asarray(group["S"][...], np.float64)
    v = da.from_zarr(zarr.open_array(storage.store(location(params.store)), path="V",
                                     mode="r"))
    session.log(f"compress: {params.store} is a compressed store (rank {k}, transform "
                f"{name}): its factors are used as they are; --eps, --clamp, --passes, "
                "--sketch, --power-iters, --oversample and --verify apply to radiance stores")
    g_v = gram(v, np.ones(k), session)
    if is_svd(u, s, g_v):
        how = "truncated (the stored U and V are orthonormal: an SVD already)"
        s_all, new_u, new_v = s, u[:, :params.rank], v[..., :params.rank]
    else:
        s_all_u, s_all, vmap = svd_map(u, g_v * np.outer(s, s))
        how = (f"re-factored exactly (QR of U, Gram matrix of V: {len(s_all)} components) and "
               "truncated")
        new_u = s_all_u[:, :params.rank]
        new_v = mapped_v(v, s[:, None] * vmap[:, :params.rank])
    rank = min(params.rank, len(s_all))
    norm = float(np.sqrt(np.sum(s_all**2)))
    part = dropped(s_all, rank)
    source = dict(group.attrs)
    attrs = _factor_attrs(params, source)
    attrs.update({"svd": {"rank": rank, "method": f"{how} from {params.store} (rank {k})"},
                  "error": _combined_error(source.get("error") or {}, norm, part)})
    chunk, dir_chunk = group["V"].chunks[0], group["U"].chunks[1]
    with atomic_output(params.out, directory=True, overwrite=params.overwrite,
                       resume=attrs["provenance"]) as tmp:
        out = create_compressed_store(tmp, directions=store.directions,
                                      channels=store.channels, ny=ny, nx=nx, rank=rank,
                                      chunk=chunk, dir_chunk=dir_chunk, attrs=attrs,
                                      v_dtype=params.v_dtype or str(group["V"].dtype))
        out["U"][...] = new_u[:, :rank].reshape(nv, nl, nc, rank).astype(np.float32)
        out["S"][...] = s_all[:rank].astype(np.float32)
        session.compute(store_aligned([new_v[..., :rank].astype(np.float32)], [out["V"]]))
    session.log(f"compress: rank {k} -> {rank}, {how}: the dropped components hold "
                f"{part:.4g} of the stored values' Frobenius norm")
    return Path(params.out)


def compress(params: CompressSettings, session: Session) -> Path:
    """Compress the store of ``params`` into U, S, V; returns the output path."""
    store = open_store(params.store, RadianceStore, CompressedStore)  # metadata only
    if isinstance(store, CompressedStore):
        return compress_factors(params, store, session)
    group = store.group
    shape = store.shape
    nv, nl, ny, nx, nc = shape
    m, n = nv * nl * nc, ny * nx
    if params.rank > min(m, n):
        raise BTFError(f"{params.store}: --rank {params.rank} is larger than the BTF matrix "
                       f"allows: min(rows, columns) = min({m}, {n}) = {min(m, n)}")
    extra = min(params.extra, min(m, n) - params.rank)  # the sketch cannot outgrow the matrix
    side = params.side(m, n)
    iterations = params.iterations(side)
    array = group[RADIANCE]
    dir_chunk, chunk = array.chunks[1], array.chunks[2]
    blocks = plan_row_blocks(shape, dir_chunk)
    v_chunk = (min(chunk, ny), min(chunk, nx))  # the V chunks of create_compressed_store
    tiles, tile_rows = plan_tiles(ny, nx, v_chunk), plan_tile_rows(
        shape, dir_chunk, v_chunk, sketch=params.one_pass)
    attrs = _output_attrs(params, store, shape)
    sketch = Sketch.for_rank(params.rank, extra, m)
    _say_plan(params, session, m, n, side, sketch,
              peak_memory(params, shape, dir_chunk, v_chunk, workers=session.read_parallelism))
    planned = (1 if params.one_pass else iterations + (2 if side == "rows" else 1)) \
        + params.verify
    with atomic_output(params.out, directory=True, overwrite=params.overwrite,
                       resume=attrs["provenance"]) as tmp, session.blas_pinned_in_tasks():
        progress = Progress(tmp)
        progress.distrust_damaged(lambda line: session.log(f"compress: {line}"))
        out = progress.skeleton(lambda: create_compressed_store(  # passes: see _Passes
            tmp, directions=store.directions, channels=store.channels,
            ny=ny, nx=nx, rank=params.rank, chunk=chunk, dir_chunk=dir_chunk, attrs=attrs,
            v_dtype=params.v_dtype or "float32"))
        passes = _Passes(location(params.store), blocks, tiles, tile_rows, location(tmp),
                         planned, params, session)
        if side == "rows":
            f = randomized_svd_rows(passes, rows=m, texels=n, rank=params.rank, extra=extra,
                                    iterations=iterations, seed=params.seed)
        else:
            f = randomized_svd(passes, rows=m, texels=n, rank=params.rank, extra=extra,
                               iterations=iterations, seed=params.seed,
                               one_pass=params.one_pass)
            if params.one_pass:  # its V was written tile by tile from the scratch sketch
                storage.remove(passes.scratch)
            else:
                out["V"][...] = f.v.reshape(ny, nx, params.rank).astype(np.float32)
        u, s, error = f.u.astype(np.float32), f.s.astype(np.float32), f.error
        out["U"][...] = u.reshape(nv, nl, nc, params.rank)
        out["S"][...] = s
        if params.verify:
            error.update(_verified(passes, u, s, n, error["frobenius_norm"]))
        svd = {"rank": params.rank, "oversample": extra, **f.widths,
               "sketch_side": "one view by texel tiles" if params.one_pass else side,
               "power_iterations": 0 if params.one_pass else iterations,
               "passes": passes.count, "seed": params.seed,
               **({"scratch_bytes": n * sketch.s * 4} if params.one_pass else {}),
               "method": _method(params, side)}
        out.attrs.update({"svd": svd, "error": error,
                          "singular_values_energy": float(np.sum(f.s**2))})
        session.log(f"compress: relative error in the log domain "
                    f"{error['log_relative_frobenius']:.4g}"
                    + (f", average ABRDF RMSE {error['abrdf_rmse']:.4g}"
                       if params.verify else ""))
    return Path(params.out)

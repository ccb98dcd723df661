"""Passes over a radiance store's BTF matrix by texel tiles (compression of wide matrices).

A texel tile is one chunk of the output's eigentextures ``V`` (so a task writing its tile of
``V`` writes whole chunks: no two tasks share a file). One task per tile reads the tile's
columns of the BTF matrix, row block by row block (each read one stored chunk, or a few), and
returns its share of the pass (:class:`tasks.svd.PassPart`), summed in the same fixed order as
the row-block passes. A tile's texel-side products (``A_t^T Q``, tile texels x l) never leave
its task, so nothing the size of the texels is ever gathered: memory is a few row blocks of a
tile, a tile's products and the row-side sketch (rows x l), whatever the number of texels.

The one-view sketch (``--passes 1``) reads each tile's column once: its range and error
sketches (rows x k) are summed like any pass, its co-range sketch ``W_t = Psi A_t`` (s x tile
texels) is written to a scratch array (one chunk per tile, :func:`create_scratch`) and only its
Gram matrix and ``W_t Phi_t`` are summed; ``V`` is then formed tile by tile from the scratch,
without reading the store again.

The row-side passes read each tile's rows twice (``Z = A_t^T Q``, then ``A_t Z``) unless the
tile's whole column fits the cache (``btf compress --tile-cache``, default
:data:`TILE_CACHE_BYTES`), in which case it is kept between the two.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from pipeline import checksums, storage
from pipeline.graphs.row_passes import (
    ROW_BLOCK_BYTES,
    RowBlock,
    plan_row_blocks,
    read_rows,
    running_sum,
    transformed_rows,
)
from pipeline.resume import PassCheckpoint
from pipeline.stores.radiance import as_float32
from tasks.svd import (
    SPARSITY,
    BlockCheck,
    PassPart,
    Sketch,
    TileSketch,
    co_project,
    log_transform,
    row_product,
    verification,
)

TILE_CACHE_BYTES = 256 << 20  # default: a tile's whole column of the matrix is kept if it fits


@dataclasses.dataclass(frozen=True)
class TexelTile:
    """A (y, x) window of texels: one chunk of ``V``."""

    y0: int
    y1: int
    x0: int
    x1: int

    @property
    def region(self) -> tuple[slice, slice]:
        """The (y, x) slices of the tile."""
        return slice(self.y0, self.y1), slice(self.x0, self.x1)

    @property
    def texels(self) -> int:
        """Texels in the tile."""
        return (self.y1 - self.y0) * (self.x1 - self.x0)


def plan_tiles(ny: int, nx: int, chunk: tuple[int, int]) -> list[TexelTile]:
    """The tiles of a ``ny x nx`` texture in ``chunk``-sized windows, in C order."""
    cy, cx = chunk
    return [TexelTile(y, min(y + cy, ny), x, min(x + cx, nx))
            for y in range(0, ny, cy) for x in range(0, nx, cx)]


# float32 radiance a one-view sketch's task reads at once: its loops take 32 rows at a time, so
# a smaller block costs no speed, and three tasks' blocks of 128 MiB (ROW_BLOCK_BYTES) were most
# of the gap between a store of 25 texel tiles and one of 4 (BENCHMARKS.md, "A store larger
# than memory")
SKETCH_BLOCK_BYTES = 32 << 20
# a tile's share of the one-view sketch (rows x k) is added to the running total as soon as it
# is done: at 25 tiles its peak fell from 0.98-1.01 GiB (4, three runs) to 0.88-0.98 GiB (six
# runs; BENCHMARKS.md, "A store larger than memory")
SKETCH_FAN_IN = 2


def plan_tile_rows(shape: tuple[int, ...], dir_chunk: int, tile: tuple[int, int], *,
                   sketch: bool = False) -> list[RowBlock]:
    """Row blocks of one tile's column: whole stored light chunks, within the block budget.

    The budget is :data:`SKETCH_BLOCK_BYTES` for the one-view ``sketch``, else
    :data:`ROW_BLOCK_BYTES`.
    """
    nv, nl, _, _, nc = shape
    budget = SKETCH_BLOCK_BYTES if sketch else ROW_BLOCK_BYTES
    return plan_row_blocks((nv, nl, *tile, nc), dir_chunk, budget=budget, minimum=1)


def _row_power_task(store: str, tile: TexelTile, blocks: list[RowBlock], q: np.ndarray, *,
                    exact: bool, cache: int, eps: float, clamp: bool, first: bool) -> PassPart:
    """A tile's share ``A_t (A_t^T q)`` of a row-side pass (with ``exact``: and ``Z^T Z``).

    The tile's column is read once if it fits ``cache`` bytes, else twice.
    """
    rows = sum(b.rows for b in blocks)
    keep = rows * tile.texels * 4 <= cache
    z = np.zeros((tile.texels, q.shape[1]))
    cached, check, f2, refused = [], BlockCheck(), 0.0, False
    for b in blocks:
        a, found, f = transformed_rows(store, b, eps=eps, clamp=clamp, first=first,
                                       norm=exact, region=tile.region)
        check = check.merge(found)
        refused = refused or a is None
        if refused:  # data to refuse: the rest is only checked (the caller raises)
            continue
        f2 += f
        z += co_project(a, q[b.row0 : b.row0 + b.rows], exact=exact)
        cached.append(a if keep else None)
    if refused:
        return PassPart({"y": np.zeros((rows, q.shape[1]))} | (
            {"g": np.zeros((q.shape[1],) * 2)} if exact else {}), {}, check, 0.0)
    y = np.empty((rows, q.shape[1]))
    for b, a in zip(blocks, cached, strict=True):
        if a is None:
            a, _, _ = transformed_rows(store, b, eps=eps, clamp=clamp, first=False, norm=False,
                                       region=tile.region)
        y[b.row0 : b.row0 + b.rows] = row_product(a, z, exact=exact)
    sums = {"y": y}
    if exact:
        sums["g"] = z.T @ z
    return PassPart(sums, {}, check, f2)


def _row_vectors_task(store: str, tile: TexelTile, blocks: list[RowBlock], q: np.ndarray,
                      to_v: np.ndarray, out: str, *, eps: float, clamp: bool,
                      first: bool) -> PassPart:
    """Write the tile's eigentextures ``V_t = A_t^T q M`` (float64 products) to ``out``."""
    import zarr

    z = np.zeros((tile.texels, q.shape[1]))
    for b in blocks:
        a, _, _ = transformed_rows(store, b, eps=eps, clamp=clamp, first=False, norm=False,
                                   region=tile.region)
        z += co_project(a, q[b.row0 : b.row0 + b.rows], exact=True)
    v = (z @ to_v).astype(np.float32)
    target = zarr.open_array(storage.store(out), path="V", mode="r+")
    target[tile.region] = v.reshape(tile.y1 - tile.y0, tile.x1 - tile.x0, -1)
    return PassPart({}, {}, BlockCheck(), 0.0)


def create_scratch(location: str, ny: int, nx: int, s: int, chunk: tuple[int, int]) -> None:
    """The scratch array of a one-view sketch's ``W``: ``(s, y, x)`` float32, a chunk a tile.

    A tile's ``W_t`` (``s x texels``, C order) is a chunk as it is, with no transposed copy.
    Uncompressed (signed sums of the data compress little) but checksummed; overwritten if
    present.
    """
    import zarr

    zarr.create_array(storage.store(location), shape=(s, ny, nx), chunks=(s, *chunk),
                      dtype="float32", compressors=checksums.codec(), fill_value=0.0,
                      overwrite=True)


def _sketch_task(store: str, tile: TexelTile, blocks: list[RowBlock], sketch: Sketch,
                 seed: int, scratch: str, *, eps: float, clamp: bool, first: bool) -> PassPart:
    """A tile's share of the one-view sketch (:class:`tasks.svd.TileSketch`).

    Writes its co-range sketch ``W_t`` to ``scratch``; returns its sums.
    """
    import zarr

    part = TileSketch(sketch, seed, (tile.y0, tile.x0), tile.texels)
    check, f2, refused = BlockCheck(), 0.0, False
    for b in blocks:
        a, found, f = transformed_rows(store, b, eps=eps, clamp=clamp, first=first, norm=True,
                                       region=tile.region)
        check = check.merge(found)
        refused = refused or a is None
        if not refused:  # data to refuse: the rest is only checked (the caller raises)
            f2 += f
            part.add(b.row0, a)
        del a
    if refused:
        return PassPart(part.sums(), {}, check, 0.0)
    target = zarr.open_array(storage.store(scratch), mode="r+")
    target[(slice(None), *tile.region)] = part.w.reshape(sketch.s, tile.y1 - tile.y0,
                                                         tile.x1 - tile.x0)
    return PassPart(part.sums(), {}, check, f2)


def _sketch_vectors_task(scratch: str, tile: TexelTile, to_v: np.ndarray, out: str
                         ) -> PassPart:
    """Write the tile's eigentextures ``V_t = W_t^T M`` (float64 products) from the scratch."""
    import zarr

    w = zarr.open_array(storage.store(scratch), mode="r")[(slice(None), *tile.region)]
    v = (w.reshape(-1, tile.texels).T.astype(np.float64) @ to_v).astype(np.float32)
    target = zarr.open_array(storage.store(out), path="V", mode="r+")
    target[tile.region] = v.reshape(tile.y1 - tile.y0, tile.x1 - tile.x0, -1)
    return PassPart({}, {}, BlockCheck(), 0.0)


def sketch_pass_graph(store: str, tiles: list[TexelTile], blocks: list[RowBlock], *,
                      sketch: Sketch, seed: int, scratch: str, eps: float, clamp: bool,
                      first: bool, kept: PassCheckpoint | None = None):
    """A delayed :class:`tasks.svd.PassPart` of the one-view sketch over the texel tiles.

    ``kept``: see :func:`~pipeline.graphs.row_passes.running_sum`.
    """
    import dask

    return running_sum([dask.delayed(_sketch_task, pure=True)(
        store, tile, blocks, sketch, seed, scratch, eps=eps, clamp=clamp, first=first)
        for tile in tiles], fan_in=SKETCH_FAN_IN, kept=kept)


def sketch_vectors_graph(scratch: str, tiles: list[TexelTile], to_v, out: str, *,
                         kept: PassCheckpoint | None = None):
    """A delayed (empty) :class:`tasks.svd.PassPart` writing ``V`` from the scratch sketch."""
    import dask

    return running_sum([dask.delayed(_sketch_vectors_task, pure=True)(scratch, tile, to_v, out)
                        for tile in tiles], kept=kept)


def _verify_task(store: str, tile: TexelTile, blocks: list[RowBlock], u: np.ndarray,
                 s: np.ndarray, out: str, *, eps: float, clamp: bool, first: bool) -> PassPart:
    """The tile's sum of per-texel ABRDF RMSEs (eq. 11) and squared log residual.

    ``V`` is read back from the output being written (``out``), so the figures are those of
    the stored, float32 factors.
    """
    import zarr

    v = as_float32(zarr.open_array(storage.store(out), path="V", mode="r")[tile.region])
    v = v.reshape(tile.texels, v.shape[-1])
    sse = np.zeros(tile.texels)
    residual, rows = 0.0, 0
    for b in blocks:
        raw, _ = read_rows(store, b, check=False, region=tile.region)
        if clamp:
            np.maximum(raw, 0.0, out=raw)
        log_a = log_transform(raw, eps=eps)  # a copy: raw stays linear for eq. (11)
        linear, log_residual = verification(raw, log_a, u[b.row0 : b.row0 + b.rows], s, v,
                                            eps=eps)
        sse += linear
        residual += log_residual
        rows += b.rows
    return PassPart({"rmse": np.array([np.sum(np.sqrt(sse / rows))])}, {}, BlockCheck(),
                    residual)


# pass kind: (task, arguments every task reads whole, whether it takes the output's path)
_TASKS = {"row-power": (_row_power_task, ("q",), False),
          "row-gram": (_row_power_task, ("q",), False),
          "row-vectors": (_row_vectors_task, ("q", "m"), True),
          "verify": (_verify_task, ("u", "s"), True)}


def tile_pass_graph(kind: str, store: str, tiles: list[TexelTile], blocks: list[RowBlock], *,
                    shared: dict, out: str | None, eps: float, clamp: bool, first: bool,
                    cache: int = TILE_CACHE_BYTES, kept: PassCheckpoint | None = None):
    """A delayed :class:`tasks.svd.PassPart` of one pass of ``kind`` over the texel tiles.

    ``blocks`` are the row blocks of a full tile (:func:`plan_tile_rows`); ``shared`` are
    handles of the arrays every task reads whole; ``out`` the compressed store being written
    (its ``V`` for ``row-vectors`` and ``verify``); ``cache`` the bytes of a tile's column
    a row-side power pass keeps between its two products; ``kept``: see
    :func:`~pipeline.graphs.row_passes.running_sum`.
    """
    import dask

    task, whole, writes = _TASKS[kind]
    extra = {"exact": kind == "row-gram", "cache": cache} \
        if kind.startswith("row-") and kind != "row-vectors" else {}
    parts = [dask.delayed(task, pure=True)(
                 store, tile, blocks, *(shared[name] for name in whole),
                 *((out,) if writes else ()), eps=eps, clamp=clamp, first=first, **extra)
             for tile in tiles]
    return running_sum(parts, kept=kept)


def sketch_memory(rows: int, tile_texels: int, sketch: Sketch, blocks: list[RowBlock], *,
                  workers: int) -> dict[str, int]:
    """Bytes a one-view sketch holds at its peak: client, one task, and all of them.

    A task holds a row block being read and range-reduced, its tile's test matrices, its
    co-range sketch and its encoded copy for the scratch array, a float64 run of it, and its
    sums (``y``, float32, and ``z``: rows x (k + t)); a step of the running sum holds
    :data:`SKETCH_FAN_IN` - 1 such sums, the float64 total so far and the new one. The client
    holds ``Y``, its QR and ``U`` (rows x k, float64). Nothing grows with the texels.
    """
    from tasks.svd import PSI_GROUP, TILE

    block = max(b.rows for b in blocks) * tile_texels * 4
    w = 4 * sketch.s * tile_texels
    small = 8 * (rows * sketch.t + sketch.s * (sketch.s + sketch.t))
    sums = 4 * rows * sketch.k + small
    total = 8 * rows * sketch.k + small  # the float64 sum of the shares
    task = (block + 2 * w + 4 * tile_texels * (2 * SPARSITY + sketch.t) + 8 * sketch.s * TILE
            + sums)
    client = 8 * 3 * rows * sketch.k + total + 4 * sketch.s * PSI_GROUP
    return {"client": client, "task": task,
            "total": client + workers * task + (SKETCH_FAN_IN - 1) * sums
            + 2 * total}


def tile_memory(rows: int, tile_texels: int, width: int, blocks: list[RowBlock], *,
                cache: int = TILE_CACHE_BYTES) -> int:
    """Bytes one row-side task holds at most.

    The cached column (or a row block), a block being read, the float64 copy of a block in the
    last pass, and its sums (also the verification's raw and range-reduced copies of a block).
    """
    column = rows * tile_texels * 4
    block = max(b.rows for b in blocks) * tile_texels * 4
    held = column if column <= cache else block
    return held + 3 * block + 8 * (2 * tile_texels * width + rows * width)

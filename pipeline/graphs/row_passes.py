"""Passes over a radiance store's BTF matrix in row blocks (compression, paper 000, 2.1).

A row block is a few (view, block of lights) units of whole stored light chunks, all texels,
sized so that a block stays within :data:`ROW_BLOCK_BYTES` (and there are enough blocks to keep
the workers busy). One task per row block reads its radiance, checks it, range-reduces it and
returns its share of the pass (:class:`tasks.svd.PassPart`); the shares are summed in a fixed
order (:func:`running_sum`), so the result does not depend on scheduling. Memory is a few row
blocks plus a few sketches, whatever the size of the store.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from pipeline import checksums, chunk_io, storage
from pipeline.errors import BTFError
from pipeline.resume import PassCheckpoint
from pipeline.stores.base import RADIANCE
from pipeline.stores.radiance import as_float32
from tasks.svd import (
    BlockCheck,
    PassPart,
    check_block,
    combine_parts,
    frobenius2,
    log_rows,
    matrix_rows,
    power_step,
    project,
)

ROW_BLOCK_BYTES = 128 << 20  # float32 radiance one task reads at most (a single unit may exceed)
MIN_ROW_BLOCKS = 8  # split smaller matrices further, so that workers share the work
FAN_IN = 4  # terms of a step of the running sum: its total so far and FAN_IN - 1 shares
SPAN_BYTES = 8 << 20  # float32 radiance one zarr read of a block gathers at most (or one unit)


@dataclasses.dataclass(frozen=True)
class RowBlock:
    """Consecutive (view, first light, end light) units and their first matrix row."""

    units: tuple[tuple[int, int, int], ...]
    row0: int
    rows: int


def plan_row_blocks(shape: tuple[int, ...], dir_chunk: int, *, budget: int | None = None,
                    minimum: int | None = None) -> list[RowBlock]:
    """Row blocks of whole stored light chunks, within ``budget`` bytes where possible.

    Defaults: :data:`ROW_BLOCK_BYTES` and at least :data:`MIN_ROW_BLOCKS` blocks.
    """
    budget = ROW_BLOCK_BYTES if budget is None else budget
    minimum = MIN_ROW_BLOCKS if minimum is None else minimum
    nv, nl, ny, nx, nc = shape
    units = [(v, l0, min(l0 + dir_chunk, nl)) for v in range(nv) for l0 in range(0, nl, dir_chunk)]
    unit_bytes = dir_chunk * nc * ny * nx * 4
    per_block = max(1, min(budget // max(unit_bytes, 1), math.ceil(len(units) / minimum)))
    blocks, row = [], 0
    for k in range(0, len(units), per_block):
        group = tuple(units[k : k + per_block])
        rows = sum((l1 - l0) * nc for _, l0, l1 in group)
        blocks.append(RowBlock(group, row, rows))
        row += rows
    return blocks


def memory_estimate(shape: tuple[int, ...], blocks: list[RowBlock], *, rank: int, extra: int,
                    workers: int) -> dict[str, int]:
    """Bytes a texel-side compression holds at its peak, roughly: client sketches, tasks' blocks.

    The sketches grow with the texels (texels x (rank + oversampling), float64, a few copies
    between passes); the tasks hold a row block, its range reduction in place, and a share of
    the sketch each; a step of the running sum holds :data:`FAN_IN` - 1 shares and two float64
    totals. (The one-view sketch runs by texel tiles:
    :func:`pipeline.graphs.tile_passes.sketch_memory`.)
    """
    n, width = shape[2] * shape[3], rank + extra
    rows = max(b.rows for b in blocks)
    client = 8 * 6 * n * width  # x, the previous iterate, their Krylov basis, QR copies
    share = 4 * n * width
    task = 4 * rows * n + share
    return {"client": client, "task": task, "total": client + workers * task
            + (FAN_IN - 1 + 2 * 2) * share}


def read_rows(store: str, block: RowBlock, *, check: bool, eps: float | None = None,
              clamp: bool = False, region: tuple[slice, slice] | None = None
              ) -> tuple[np.ndarray, BlockCheck]:
    """The block's BTF matrix rows (float32), range-reduced if ``eps`` is given.

    ``region`` restricts the columns to a (y, x) window of texels (default: all). With
    ``check``, also what the radiance holds besides good values (first pass only).
    """
    import zarr

    array = zarr.open_array(storage.store(store), path=RADIANCE, mode="r")
    nc = array.shape[-1]
    ys, xs = region or (slice(0, array.shape[2]), slice(0, array.shape[3]))
    texels = (ys.stop - ys.start) * (xs.stop - xs.start)
    rows = np.empty((block.rows, texels), np.float32)
    found, r = BlockCheck(), 0
    for v0, v1, l0, l1 in spans(block.units, SPAN_BYTES // (4 * nc * texels)):
        try:
            layers = as_float32(chunk_io.read(array, (slice(v0, v1), slice(l0, l1), ys, xs)))
        except Exception:  # named by its unit below, whatever the codec raised
            _raise_unreadable(array, store, block, ys, xs)
            raise
        if check:
            found = found.merge(check_block(layers, (v0, l0, ys.start, xs.start, 0)))
        n = (v1 - v0) * (l1 - l0) * nc
        if eps is None:
            rows[r : r + n] = matrix_rows(layers)
        elif not (found.nonfinite or (found.negative and not clamp)):
            log_rows(layers, rows[r : r + n], eps=eps, clamp=clamp)
        r += n
    return rows, found


def spans(units, layers: int) -> list[tuple[int, int, int, int]]:
    """Consecutive (view, first light, end light) units as rectangles ``(v0, v1, l0, l1)``.

    Lights that follow each other in one view join, then views with the same lights, in the
    units' (row) order, while a rectangle holds at most ``layers`` layers (one unit at least):
    a zarr read per rectangle fetches its chunks concurrently, where a read per unit pays a
    round trip each (1 ms a read on a local disk, more from object storage).
    """
    runs: list[list[int]] = []
    for v, l0, l1 in units:
        last = runs[-1] if runs else None
        if last and last[0] == v and last[3] == l0 and l1 - last[2] <= layers:
            last[3] = l1
        else:
            runs.append([v, v + 1, l0, l1])
    out: list[list[int]] = []
    for run in runs:
        last = out[-1] if out else None
        if last and last[1] == run[0] and last[2:] == run[2:] \
                and (last[1] + 1 - last[0]) * (run[3] - run[2]) <= layers:
            last[1] = run[1]
        else:
            out.append(run)
    return [tuple(span) for span in out]


def _raise_unreadable(array, store: str, block: RowBlock, ys: slice, xs: slice) -> None:
    """Read the block unit by unit and raise the first unit's error, named by its key."""
    for v, l0, l1 in block.units:
        try:
            array[v : v + 1, l0:l1, ys, xs]
        except Exception as exc:
            region = (slice(v, v + 1), slice(l0, l1), ys, xs, slice(None))
            if (error := checksums.named(store, RADIANCE, array, region, exc)) is not None:
                raise error from None
            raise BTFError(f"{store}: variable 'radiance', block [view {v}, lights {l0}:{l1}, "
                           f"y {ys.start}:{ys.stop}, x {xs.start}:{xs.stop}] is unreadable: "
                           f"{type(exc).__name__}: {exc}") from None


def transformed_rows(store: str, block: RowBlock, *, eps: float, clamp: bool, first: bool,
                     norm: bool, region: tuple[slice, slice] | None = None
                     ) -> tuple[np.ndarray | None, BlockCheck, float]:
    """Range-reduced rows of a block; None if the first pass finds data that must be refused.

    Data is checked in the first pass only (the caller stops after it if anything is wrong).
    """
    a, check = read_rows(store, block, check=first, eps=eps, clamp=clamp, region=region)
    if check.nonfinite or (check.negative and not clamp):
        return None, check, 0.0
    return a, check, (frobenius2(a) if norm else 0.0)


def _power_task(store: str, block: RowBlock, x: np.ndarray, *, eps: float, clamp: bool,
                first: bool) -> PassPart:
    a, check, f2 = transformed_rows(store, block, eps=eps, clamp=clamp, first=first, norm=False)
    w = power_step(a, x) if a is not None else np.zeros_like(x)
    return PassPart({"w": w}, {}, check, f2)


def _project_task(store: str, block: RowBlock, x: np.ndarray, *, eps: float, clamp: bool,
                  first: bool) -> PassPart:
    a, check, f2 = transformed_rows(store, block, eps=eps, clamp=clamp, first=first, norm=True)
    z = project(a, x) if a is not None else np.zeros((block.rows, x.shape[1]))
    return PassPart({}, {"z": [(block.row0, z)]}, check, f2)


def running_sum(parts: list, *, fan_in: int = FAN_IN, kept: PassCheckpoint | None = None
                ) -> Any:
    """Delayed sum of pass parts into one running total, ``fan_in`` - 1 parts a step.

    The order is fixed, so the sums are reproducible, and one float64 total is alive at a
    time (two while a step adds to it). A tree of :data:`FAN_IN` held every total of a level
    until the level above summed them: a one-pass compression over 16 texel tiles of 30603
    rows peaked at 1.06 GiB against 0.94 GiB over 4 tiles of the same rows (BENCHMARKS.md,
    "A store larger than memory"). Up to :data:`FAN_IN` parts, the same sum as that tree.
    Every ``fan_in`` gives the same bits (each step adds its parts to the total in order); a
    smaller one leaves fewer finished parts waiting for their step, and copies the total more
    often.

    With ``kept``, steps keep the total so far every few steps, and the sum starts from the
    one a killed run kept: the parts it holds are not computed again (their tasks are not in
    the graph), and the result is the same, bit for bit.
    """
    import dask

    starts = range(1, len(parts), fan_in - 1)
    total, first = parts[0], 0
    found = _kept_total(kept, len(parts), fan_in)
    if found is not None:
        first, total = found
    for step, i in enumerate(starts):
        if step < first:
            continue
        terms = parts[i : i + fan_in - 1]
        total = dask.delayed(combine_parts, pure=True)(total, *terms) if kept is None else \
            dask.delayed(_kept_step, pure=True)(kept, step, len(starts), total, *terms)
    return total


def parts_kept(kept: PassCheckpoint, parts: int, *, fan_in: int = FAN_IN) -> int:
    """How many of a pass's ``parts`` the total that ``kept`` holds already sums (0: none)."""
    found = _kept_total(kept, parts, fan_in)
    return 0 if found is None else 1 + found[0] * (fan_in - 1)


def _kept_total(kept: PassCheckpoint | None, parts: int, fan_in: int) -> tuple[int, Any] | None:
    """``(steps summed, total)`` a killed run kept of a sum of ``parts``, or None.

    None too where it holds no step or every one (the last step's total is never kept).
    """
    found = kept.latest() if kept is not None else None
    steps = len(range(1, parts, fan_in - 1))
    return found if found is not None and 0 < found[0] < steps else None


def _kept_step(kept: PassCheckpoint, step: int, steps: int, total: PassPart, *parts: PassPart
               ) -> PassPart:
    """A step of :func:`running_sum` that keeps its total when it is due (``kept.keep``)."""
    total = combine_parts(total, *parts)
    kept.keep(step, steps, total)
    return total


# the texel-side pass kinds of tasks.rsvd: (task, arguments read whole)
_TASKS = {"power": (_power_task, ("x",)), "project": (_project_task, ("x",))}


def pass_graph(kind: str, store: str, blocks: list[RowBlock], *, shared: dict[str, Any],
               eps: float, clamp: bool, first: bool, kept: PassCheckpoint | None = None):
    """A delayed :class:`tasks.svd.PassPart` of one pass of ``kind`` over the row blocks.

    ``shared`` are handles of arrays every task reads whole (sketches, factors); ``kept``:
    see :func:`running_sum`.
    """
    import dask

    task, whole = _TASKS[kind]
    parts = [dask.delayed(task, pure=True)(store, b, *(shared[name] for name in whole),
                                           eps=eps, clamp=clamp, first=first)
             for b in blocks]
    return running_sum(parts, kept=kept)


def raise_on_bad_data(check: BlockCheck, store: str, clamp: bool) -> None:
    """Raise :class:`BTFError` for NaN/Inf radiance, or negative radiance unless clamped."""
    dims = ("view", "light", "y", "x", "channel")

    def where(index):
        return ", ".join(f"{d}={i}" for d, i in zip(dims, index, strict=True))

    if check.nonfinite:
        raise BTFError(f"{store}: variable 'radiance' has {check.nonfinite} NaN or Inf "
                       f"value(s), the first at {where(check.first_nonfinite)}")
    if check.negative and not clamp:
        raise BTFError(f"{store}: variable 'radiance' has {check.negative} negative value(s), "
                       f"the first at {where(check.first_negative)}; log(radiance + eps) needs "
                       "radiance >= 0 (pass --clamp to clamp them to 0)")

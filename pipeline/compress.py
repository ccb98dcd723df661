"""``btf compress``: out-of-core randomized SVD of a radiance store (paper 000, section 2.1).

The store is streamed in row blocks of the BTF matrix: a few (view, block of lights) units,
all texels, sized so that a block stays within :data:`ROW_BLOCK_BYTES` (and there are enough
blocks to keep the workers busy). One task per row block reads its radiance, checks it,
range-reduces it and returns its share of the pass (:class:`tasks.svd.PassPart`); the shares
are summed by a fixed tree, so the result does not depend on scheduling. Between passes only the
sketch (texels x (rank + oversampling)) lives on the client, where it is re-orthonormalised.
Memory is therefore a few row blocks plus a few sketches, whatever the size of the store.

Passes over the data: ``power_iters + 1`` (fused ``A^T A`` passes, then the projection), or 1
with ``--passes 1`` (a one-view sketch), plus one with ``--verify``.
"""

from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.atomic import atomic_output
from pipeline.compressed import create_compressed_store
from pipeline.errors import BTFError
from pipeline.params import ParamError, check_seed, option
from pipeline.provenance import provenance
from pipeline.runtime import Session
from pipeline.store import RADIANCE, check_radiance, location, open_group, read_directions
from tasks.svd import (
    IDENTITY_RESOLUTION,
    BlockCheck,
    PassPart,
    Sketch,
    average_abrdf_rmse,
    check_block,
    combine_parts,
    error_from_identity,
    estimated_error,
    factors_from_projection,
    factors_from_sketch,
    frobenius2,
    gaussian,
    log_rows,
    log_transform,
    matrix_rows,
    orthonormalize,
    power_step,
    project,
    sketch_rows,
    stacked_rows,
    verification,
)

ROW_BLOCK_BYTES = 128 << 20  # float32 radiance one task reads at most (a single unit may exceed)
MIN_ROW_BLOCKS = 8  # split smaller matrices further, so that workers share the work
FAN_IN = 4  # row-block shares added per reduction task


@dataclasses.dataclass(frozen=True)
class CompressParams:
    """Parameters of ``btf compress``."""

    store: str = option(help="radiance store to compress", positional=True, path="in",
                        metavar="IN")
    out: str = option(help="output compressed store (a .zarr directory)", positional=True,
                      path="out")
    rank: int = option(help="components to keep (K)", metavar="K")
    oversample: int | None = option(
        None, metavar="P", help="extra sketch columns (default: 10; with --passes 1: K + 1, "
                                "so that the one-view sketch holds 2K + 1 columns)")
    power_iters: int | None = option(
        None, metavar="Q", help="power iterations, each one fused pass over the data "
                                "(default: 2, i.e. 3 passes)")
    passes: str = option("auto", metavar="auto|N", numbers_as_text=True,
                         help="passes over the data: auto (power iterations + 1), 1 (a one-view "
                              "sketch, for stores too large to read twice) or N >= 2")
    eps: float = option(1e-3, help="range reduction log(radiance + eps)")
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
        if self.passes != "auto":
            if not self.passes.isdigit() or int(self.passes) < 1:
                raise ParamError("passes", f"must be auto or a positive integer, got "
                                           f"{self.passes!r}")
            if int(self.passes) == 1 and self.power_iters:
                raise ParamError("power_iters", "cannot be combined with --passes 1")
            if (int(self.passes) > 1 and self.power_iters is not None
                    and self.power_iters != int(self.passes) - 1):
                raise ParamError("power_iters", f"{self.power_iters} power iterations take "
                                                f"{self.power_iters + 1} passes, not "
                                                f"{self.passes}")

    @property
    def one_pass(self) -> bool:
        """Whether to use the one-view sketch."""
        return self.passes == "1"

    @property
    def iterations(self) -> int:
        """Power iterations (fused passes before the projection pass)."""
        if self.passes != "auto":
            return max(int(self.passes) - 1, 0)
        return 2 if self.power_iters is None else self.power_iters

    @property
    def extra(self) -> int:
        """Oversampling actually used."""
        if self.oversample is not None:
            return self.oversample
        return self.rank + 1 if self.one_pass else 10


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
                    one_pass: bool, workers: int) -> dict[str, int]:
    """Bytes the stage will hold at its peak, roughly: sketches on the client, blocks in tasks.

    The sketches grow with the texels (texels x (rank + oversampling), float64, a few copies
    between passes); the tasks hold a row block, its range reduction in place, and a share of
    the sketch each; a reduction task holds :data:`FAN_IN` shares.
    """
    nv, nl, ny, nx, nc = shape
    m, n, width = nv * nl * nc, ny * nx, rank + extra
    rows = max(b.rows for b in blocks)
    if one_pass:
        s = 2 * width + 1
        client = 8 * (2 * s * n + m * width + n * width)
        share = 4 * s * n
    else:
        client = 8 * 6 * n * width  # x, the previous iterate, their Krylov basis, QR copies
        share = 4 * n * width
    task = 4 * rows * n + share
    return {"client": client, "task": task, "total": client + workers * task
            + FAN_IN * 2 * share}


def _read_rows(store: str, block: RowBlock, *, check: bool, eps: float | None = None,
               clamp: bool = False) -> tuple[np.ndarray, BlockCheck]:
    """The block's BTF matrix rows (float32), range-reduced if ``eps`` is given.

    With ``check``, also what the radiance holds besides good values (first pass only).
    """
    import zarr

    array = zarr.open_array(store, path=RADIANCE, mode="r")
    nc = array.shape[-1]
    rows = np.empty((block.rows, array.shape[2] * array.shape[3]), np.float32)
    found, r = BlockCheck(), 0
    for v, l0, l1 in block.units:
        try:
            layers = array[v : v + 1, l0:l1]
        except Exception as exc:  # re-raised with the unit's key, whatever the codec raised
            raise BTFError(f"{store}: variable 'radiance', block [view {v}, lights {l0}:{l1}] "
                           f"is unreadable: {type(exc).__name__}: {exc}") from None
        if check:
            found = found.merge(check_block(layers, (v, l0, 0, 0, 0)))
        n = (l1 - l0) * nc
        if eps is None:
            rows[r : r + n] = matrix_rows(layers)
        elif not (found.nonfinite or (found.negative and not clamp)):
            log_rows(layers, rows[r : r + n], eps=eps, clamp=clamp)
        r += n
    return rows, found


def _transformed(store: str, block: RowBlock, *, eps: float, clamp: bool, first: bool,
                 norm: bool) -> tuple[np.ndarray | None, BlockCheck, float]:
    """Range-reduced rows of a block; None if the first pass finds data that must be refused.

    Data is checked in the first pass only (the caller stops after it if anything is wrong).
    """
    a, check = _read_rows(store, block, check=first, eps=eps, clamp=clamp)
    if check.nonfinite or (check.negative and not clamp):
        return None, check, 0.0
    return a, check, (frobenius2(a) if norm else 0.0)


def _power_task(store: str, block: RowBlock, x: np.ndarray, *, eps: float, clamp: bool,
                first: bool) -> PassPart:
    a, check, f2 = _transformed(store, block, eps=eps, clamp=clamp, first=first, norm=False)
    w = power_step(a, x) if a is not None else np.zeros_like(x)
    return PassPart({"w": w}, {}, check, f2)


def _project_task(store: str, block: RowBlock, x: np.ndarray, *, eps: float, clamp: bool,
                  first: bool) -> PassPart:
    a, check, f2 = _transformed(store, block, eps=eps, clamp=clamp, first=first, norm=True)
    z = project(a, x) if a is not None else np.zeros((block.rows, x.shape[1]))
    return PassPart({}, {"z": [(block.row0, z)]}, check, f2)


def _sketch_task(store: str, block: RowBlock, omega, phi, psi_rows, *, eps: float,
                 clamp: bool, first: bool) -> PassPart:
    a, check, f2 = _transformed(store, block, eps=eps, clamp=clamp, first=first, norm=True)
    if a is None:
        y = np.zeros((block.rows, omega.shape[1]))
        z = np.zeros((block.rows, phi.shape[1]))
        w = np.zeros((psi_rows.shape[0], omega.shape[0]), np.float32)
    else:
        y, z, w = sketch_rows(a, omega, phi, psi_rows)
    return PassPart({"w": w}, {"y": [(block.row0, y)], "z": [(block.row0, z)]}, check, f2)


def _verify_task(store: str, block: RowBlock, u, s, v, *, eps: float, clamp: bool,
                 first: bool) -> PassPart:
    raw, check = _read_rows(store, block, check=first)
    if clamp:
        np.maximum(raw, 0.0, out=raw)
    log_a = log_transform(raw, eps=eps)  # a copy: raw stays linear for eq. (11)
    linear, log_residual = verification(raw, log_a, u[block.row0 : block.row0 + block.rows], s,
                                        v, eps=eps)
    return PassPart({"sse": linear}, {}, check, log_residual)


def tree_sum(parts: list) -> Any:
    """Delayed sum of pass parts by a fixed tree of :data:`FAN_IN` (reproducible order)."""
    import dask

    level = list(parts)
    while len(level) > 1:
        level = [dask.delayed(combine_parts, pure=True)(*level[i : i + FAN_IN])
                 for i in range(0, len(level), FAN_IN)]
    return level[0]


def _raise_on_bad_data(check: BlockCheck, store: str, clamp: bool) -> None:
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


class _Passes:
    """Runs passes over the row blocks and counts them."""

    def __init__(self, store: str, blocks: list[RowBlock], params: CompressParams,
                 session: Session):
        self.store, self.blocks, self.params, self.session = store, blocks, params, session
        self.count = 0
        self.planned = 1 if params.one_pass else params.iterations + 1

    def run(self, task, what: str, *shared, **kwargs) -> PassPart:
        import dask

        self.count += 1
        total = self.planned + self.params.verify
        self.session.log(f"compress: pass {self.count}/{total} ({what}, "
                         f"{len(self.blocks)} row blocks)")
        handles = [self.session.share(a) for a in shared]
        per_block = kwargs.pop("per_block", None)  # arguments that differ between blocks
        parts = [dask.delayed(task, pure=True)(
                     self.store, b, *handles, *(per_block(b) if per_block else ()),
                     first=self.count == 1, **kwargs)
                 for b in self.blocks]
        (result,) = self.session.compute(tree_sum(parts), reads=True)
        if self.count == 1:
            _raise_on_bad_data(result.check, self.params.store, self.params.clamp)
        return result


def _multi_pass(passes: _Passes, n: int, m: int, params: CompressParams, extra: int):
    p = params
    rank, width = p.rank, p.rank + extra
    x = gaussian(n, width, seed=p.seed, stream=0)
    previous = None
    for q in range(p.iterations):
        w = passes.run(_power_task, f"power iteration {q + 1}", x.astype(np.float32),
                       eps=p.eps, clamp=p.clamp).sums["w"]
        previous, x = x, orthonormalize(w)
        del w  # sketches are large: keep no more of them than needed
    # the block Krylov space of the last two iterates (see tasks.svd)
    x = orthonormalize(x if previous is None else np.hstack([previous, x]))
    del previous
    last = passes.run(_project_task, "projection", x.astype(np.float32), eps=p.eps,
                      clamp=p.clamp)
    u, s, v = factors_from_projection(stacked_rows(last.rows["z"]), x, rank)
    relative = error_from_identity(last.frobenius2, s)
    error = {"log_relative_frobenius": max(relative, 0.0),
             "method": "identity ||A - U S V^T||_F^2 = ||A||_F^2 - sum(S^2), exact in exact "
                       "arithmetic for the projection A X X^T computed in the last pass",
             "resolution": IDENTITY_RESOLUTION,
             "frobenius_norm": math.sqrt(last.frobenius2)}
    if relative < IDENTITY_RESOLUTION:
        error["note"] = (f"below the identity's resolution ({IDENTITY_RESOLUTION:g}) in floating "
                         "point: an upper bound; --verify measures it directly")
    widths = {"sketch_columns": width, "projection_columns": x.shape[1]}
    return u, s, v, error, widths


def _one_pass(passes: _Passes, n: int, m: int, params: CompressParams, extra: int):
    p = params
    sketch = Sketch.for_rank(p.rank, extra)
    # The test matrices are rounded to float32 once; the same values serve the tasks and the
    # client's algebra (float64 copies of float32 numbers).
    omega = gaussian(n, sketch.k, seed=p.seed, stream=1).astype(np.float32)
    phi = gaussian(n, sketch.t, seed=p.seed, stream=2).astype(np.float32)
    psi = gaussian(sketch.s, m, seed=p.seed, stream=3).astype(np.float32)
    part = passes.run(_sketch_task, "one-view sketch", omega, phi, eps=p.eps, clamp=p.clamp,
                      per_block=lambda b: (psi[:, b.row0 : b.row0 + b.rows],))
    psi = psi.astype(np.float64)
    phi = phi.astype(np.float64)
    u, s, v = factors_from_sketch(stacked_rows(part.rows["y"]), part.sums["w"], psi, p.rank)
    estimate = estimated_error(stacked_rows(part.rows["z"]), phi, u, s, v, part.frobenius2)
    error = {"log_relative_frobenius": estimate,
             "method": f"estimate from a Gaussian error sketch of {sketch.t} columns (Tropp "
                       "et al. 2017): E ||(A - U S V^T) Phi||_F^2 / t = ||A - U S V^T||_F^2",
             "frobenius_norm": math.sqrt(part.frobenius2)}
    return u, s, v, error, {f"sketch_{k}": v for k, v in dataclasses.asdict(sketch).items()}


def compress(params: CompressParams, session: Session) -> Path:
    """Compress the store of ``params`` into U, S, V; returns the output path."""
    group = open_group(params.store)  # zarr metadata only: no xarray needed here
    check_radiance(group, params.store)
    shape = tuple(group[RADIANCE].shape)
    nv, nl, ny, nx, nc = shape
    m, n = nv * nl * nc, ny * nx
    if params.rank > min(m, n):
        raise BTFError(f"{params.store}: --rank {params.rank} is larger than the BTF matrix "
                       f"allows: min(rows, columns) = min({m}, {n}) = {min(m, n)}")
    extra = min(params.extra, min(m, n) - params.rank)  # the sketch cannot outgrow the matrix
    dir_chunk = group[RADIANCE].chunks[1]
    blocks = plan_row_blocks(shape, dir_chunk)
    passes = _Passes(location(params.store), blocks, params, session)
    source_attrs = dict(group.attrs)
    attrs = {
        "source": "compress",
        "source_btf_kind": source_attrs.get("btf_kind"),
        "source_shape": list(shape),
        "transform": {"name": "log", "formula": "log(radiance + eps)", "eps": params.eps,
                      "clamp": params.clamp},
        "provenance": provenance("compress", params),
    }
    for key in ("sampling", "material"):
        if key in source_attrs:
            attrs[f"source_{key}"] = source_attrs[key]
    session.log(f"compress: {m} x {n} BTF matrix ({m * n * 4 / 2**30:.2f} GiB float32) to "
                f"rank {params.rank} -> {params.out}")
    memory = memory_estimate(shape, blocks, rank=params.rank, extra=extra,
                             one_pass=params.one_pass, workers=(os.cpu_count() or 1) + 1)
    session.log(f"compress: expected peak memory ~{memory['total'] / 2**30:.2f} GiB "
                f"(sketches {memory['client'] / 2**30:.2f} GiB, each task "
                f"{memory['task'] / 2**30:.2f} GiB)")
    with atomic_output(params.out, directory=True, overwrite=params.overwrite) as tmp, \
            session.blas_pinned_in_tasks():
        run = _one_pass if params.one_pass else _multi_pass
        u, s, v, error, widths = run(passes, n, m, params, extra)
        attrs["svd"] = {"rank": params.rank, "oversample": extra, **widths,
                        "power_iterations": 0 if params.one_pass else params.iterations,
                        "passes": passes.count, "seed": params.seed,
                        "method": "one-view sketch" if params.one_pass else
                                  "randomized SVD with fused power iterations, projected on "
                                  "the block Krylov space of the last two iterates"}
        attrs["error"] = error
        if params.verify:
            part = passes.run(_verify_task, "verification", u.astype(np.float32),
                              s.astype(np.float32), v.astype(np.float32), eps=params.eps,
                              clamp=params.clamp)
            attrs["error"]["abrdf_rmse"] = average_abrdf_rmse(part.sums["sse"], m)
            norm = attrs["error"]["frobenius_norm"]
            attrs["error"]["log_relative_frobenius_measured"] = (
                math.sqrt(part.frobenius2) / norm if norm else 0.0)
            attrs["error"]["abrdf_rmse_definition"] = (
                "paper 000 eq. 11: mean over texels of the RMS difference of the texel's "
                "ABRDF (all view x light x channel values), linear radiance")
            attrs["svd"]["passes"] = passes.count
        attrs["singular_values_energy"] = float(np.sum(s**2))
        out = create_compressed_store(
            tmp, directions=read_directions(group),
            channels=tuple(str(c) for c in group["channel"][:]),
            ny=ny, nx=nx, rank=params.rank, chunk=group[RADIANCE].chunks[2],
            dir_chunk=dir_chunk, attrs=attrs)
        out["U"][...] = u.reshape(nv, nl, nc, params.rank).astype(np.float32)
        out["S"][...] = s.astype(np.float32)
        out["V"][...] = v.reshape(ny, nx, params.rank).astype(np.float32)
        session.log(f"compress: relative error in the log domain "
                    f"{error['log_relative_frobenius']:.4g}"
                    + (f", average ABRDF RMSE {attrs['error']['abrdf_rmse']:.4g}"
                       if params.verify else ""))
    return Path(params.out)

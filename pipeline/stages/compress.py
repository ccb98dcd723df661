"""``btf compress``: out-of-core randomized SVD of a radiance store (paper 000, section 2.1).

The store is streamed in row blocks of the BTF matrix (:mod:`pipeline.graphs.row_passes`), one
pass at a time as the driver :func:`tasks.rsvd.randomized_svd` asks for them. Between passes
only the sketch (texels x (rank + oversampling)) lives on the client, where it is
re-orthonormalised. Memory is therefore a few row blocks plus a few sketches, whatever the size
of the store.

Passes over the data: ``power_iters + 1`` (fused ``A^T A`` passes, then the projection), or 1
with ``--passes 1`` (a one-view sketch), plus one with ``--verify``.
"""

from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path

import numpy as np

from pipeline.atomic import atomic_output
from pipeline.errors import BTFError
from pipeline.graphs.row_passes import (
    RowBlock,
    memory_estimate,
    pass_graph,
    plan_row_blocks,
    raise_on_bad_data,
)
from pipeline.params import ParamError, check_seed, option
from pipeline.provenance import provenance
from pipeline.session import Session
from pipeline.stores.base import RADIANCE, location, open_group, read_channels, read_directions
from pipeline.stores.compressed import create_compressed_store
from pipeline.stores.radiance import check_radiance
from tasks.rsvd import randomized_svd
from tasks.svd import PassPart, average_abrdf_rmse


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


class _Passes:
    """The ``run_pass`` of :func:`tasks.rsvd.randomized_svd`: one pass over the store each call.

    Counts the passes, logs them, and stops after the first if the data must be refused.
    """

    def __init__(self, store: str, blocks: list[RowBlock], params: CompressParams,
                 session: Session):
        self.store, self.blocks, self.params, self.session = store, blocks, params, session
        self.count = 0
        self.planned = (1 if params.one_pass else params.iterations + 1) + params.verify

    def __call__(self, kind: str, **arrays: np.ndarray) -> PassPart:
        self.count += 1
        what = {"power": f"power iteration {self.count}", "project": "projection",
                "sketch": "one-view sketch", "verify": "verification"}[kind]
        self.session.log(f"compress: pass {self.count}/{self.planned} ({what}, "
                         f"{len(self.blocks)} row blocks)")
        by_rows = {k: v for k, v in arrays.items() if k == "psi"}
        shared = {k: self.session.share(v) for k, v in arrays.items() if k not in by_rows}
        graph = pass_graph(kind, self.store, self.blocks, shared=shared, by_rows=by_rows,
                           eps=self.params.eps, clamp=self.params.clamp, first=self.count == 1)
        (result,) = self.session.compute(graph, reads=True)
        if self.count == 1:
            raise_on_bad_data(result.check, self.params.store, self.params.clamp)
        return result


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
        f = randomized_svd(passes, rows=m, texels=n, rank=params.rank, extra=extra,
                           iterations=params.iterations, seed=params.seed,
                           one_pass=params.one_pass)
        u, s, v, error = f.u, f.s, f.v, f.error
        attrs["svd"] = {"rank": params.rank, "oversample": extra, **f.widths,
                        "power_iterations": 0 if params.one_pass else params.iterations,
                        "passes": passes.count, "seed": params.seed,
                        "method": "one-view sketch" if params.one_pass else
                                  "randomized SVD with fused power iterations, projected on "
                                  "the block Krylov space of the last two iterates"}
        attrs["error"] = error
        if params.verify:
            part = passes("verify", u=u.astype(np.float32), s=s.astype(np.float32),
                          v=v.astype(np.float32))
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
            channels=read_channels(group),
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

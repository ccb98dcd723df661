"""The randomized SVD driver: which passes to run and what to do between them (paper 000, 2.1).

The driver never sees the data. It asks a ``run_pass`` callable for one pass over the BTF
matrix at a time and does the small algebra between passes on the client (orthonormalising
sketches, the final small SVD, the error bookkeeping; see :mod:`tasks.svd` for the maths).
``run_pass(kind, **arrays)`` returns the pass's :class:`tasks.svd.PassPart`, summed over the
matrix's row blocks, for one of three kinds:

- ``"power"``: ``sums["w"] = A^T (A x)`` for the texels x columns sketch ``x``;
- ``"project"``: ``rows["z"] = A x`` and ``frobenius2 = ||A||_F^2``;
- ``"sketch"``: the one-view sketch of ``omega``, ``phi`` and ``psi`` (whose columns follow the
  matrix rows): ``rows["y"] = A omega``, ``rows["z"] = A phi``, ``sums["w"] = psi A``.

The pipeline streams a store in its ``run_pass``; a test can pass one over a numpy matrix.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from tasks.svd import (
    IDENTITY_RESOLUTION,
    PassPart,
    Sketch,
    error_from_identity,
    estimated_error,
    factors_from_projection,
    factors_from_sketch,
    gaussian,
    orthonormalize,
    stacked_rows,
)

RunPass = Callable[..., PassPart]


@dataclass(frozen=True)
class Factorization:
    """``A ~ U diag(S) V^T`` (float64), how good it is, and how it was made."""

    u: np.ndarray
    s: np.ndarray
    v: np.ndarray
    error: dict[str, Any]
    widths: dict[str, int]


def randomized_svd(run_pass: RunPass, *, rows: int, texels: int, rank: int, extra: int,
                   iterations: int, seed: int, one_pass: bool = False) -> Factorization:
    """Rank-``rank`` factors of the ``rows x texels`` matrix that ``run_pass`` streams.

    ``extra`` is the oversampling; ``iterations`` the fused power passes before the projection
    pass (``iterations + 1`` passes), or, with ``one_pass``, a single one-view sketch pass.
    """
    run = _one_pass if one_pass else _multi_pass
    return run(run_pass, rows=rows, texels=texels, rank=rank, extra=extra,
               iterations=iterations, seed=seed)


def _multi_pass(run_pass: RunPass, *, rows, texels, rank, extra, iterations, seed
                ) -> Factorization:
    width = rank + extra
    x = gaussian(texels, width, seed=seed, stream=0)
    previous = None
    for _ in range(iterations):
        w = run_pass("power", x=x.astype(np.float32)).sums["w"]
        previous, x = x, orthonormalize(w)
        del w  # sketches are large: keep no more of them than needed
    # the block Krylov space of the last two iterates (see tasks.svd)
    x = orthonormalize(x if previous is None else np.hstack([previous, x]))
    del previous
    last = run_pass("project", x=x.astype(np.float32))
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
    return Factorization(u, s, v, error, {"sketch_columns": width,
                                          "projection_columns": x.shape[1]})


def _one_pass(run_pass: RunPass, *, rows, texels, rank, extra, iterations, seed
              ) -> Factorization:
    sketch = Sketch.for_rank(rank, extra)
    # The test matrices are rounded to float32 once; the same values serve the tasks and the
    # client's algebra (float64 copies of float32 numbers).
    omega = gaussian(texels, sketch.k, seed=seed, stream=1).astype(np.float32)
    phi = gaussian(texels, sketch.t, seed=seed, stream=2).astype(np.float32)
    psi = gaussian(sketch.s, rows, seed=seed, stream=3).astype(np.float32)
    part = run_pass("sketch", omega=omega, phi=phi, psi=psi)
    u, s, v = factors_from_sketch(stacked_rows(part.rows["y"]), part.sums["w"],
                                  psi.astype(np.float64), rank)
    estimate = estimated_error(stacked_rows(part.rows["z"]), phi.astype(np.float64), u, s, v,
                               part.frobenius2)
    error = {"log_relative_frobenius": estimate,
             "method": f"estimate from a Gaussian error sketch of {sketch.t} columns (Tropp "
                       "et al. 2017): E ||(A - U S V^T) Phi||_F^2 / t = ||A - U S V^T||_F^2",
             "frobenius_norm": math.sqrt(part.frobenius2)}
    return Factorization(u, s, v, error,
                         {f"sketch_{k}": v for k, v in dataclasses.asdict(sketch).items()})

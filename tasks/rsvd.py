"""The randomized SVD driver: which passes to run and what to do between them (paper 000, 2.1).

The driver never sees the data. It asks a ``run_pass`` callable for one pass over the BTF
matrix at a time and does the small algebra between passes on the client (orthonormalising
sketches, the final small SVD, the error bookkeeping; see :mod:`tasks.svd` for the maths).
``run_pass(kind, **arrays)`` returns the pass's :class:`tasks.svd.PassPart`, summed over the
matrix's row blocks (or texel tiles), for one of these kinds:

- ``"power"``: ``sums["w"] = A^T (A x)`` for the texels x columns sketch ``x``;
- ``"project"``: ``rows["z"] = A x`` and ``frobenius2 = ||A||_F^2``;
- ``"sketch"``: the one-view sketch of the sizes ``sketch`` (:class:`tasks.svd.Sketch`), its
  test matrices made from ``seed`` where they are used (:func:`tasks.svd.sign_map` and
  :func:`tasks.svd.tile_test_matrix` by texel tiles, :func:`tasks.svd.co_range_rows` by
  rows): ``sums["y"] = A Omega`` (absent
  for an exact range), ``sums["z"] = A Phi``, and of the co-range sketch ``W = Psi A``, kept
  tile by tile where the pass runs, ``sums["g"] = W W^T`` and ``sums["wphi"] = W Phi``;
- ``"sketch-vectors"``: ``V = W^T m`` for the small map ``m``, tile by tile from the kept
  ``W`` (not a pass over the matrix; the pipeline writes ``V``, a test returns
  ``sums["v"]``).

For a wide matrix (fewer rows than texels) :func:`randomized_svd_rows` keeps its sketches on
the row side instead, so that nothing on the client grows with the texels; its passes are

- ``"row-power"`` (float32) and ``"row-gram"`` (float64, the last): for the rows x columns
  basis ``q``, ``Z = A^T q`` by texel tiles and ``sums["y"] = A Z``; ``"row-gram"`` also gives
  ``sums["g"] = Z^T Z`` and ``frobenius2 = ||A||_F^2``;
- ``"row-vectors"``: ``V = A^T q M`` for the small map ``m``, formed tile by tile (the pipeline
  writes it to the store and returns no ``sums["v"]``; a test returns it).

The pipeline streams a store in its ``run_pass``; a test can pass one over a numpy matrix.
"""

from __future__ import annotations

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
    factors_from_co_range,
    factors_from_gram,
    factors_from_projection,
    gaussian,
    orthonormalize,
    psi_times,
    stacked_rows,
)

RunPass = Callable[..., PassPart]
SIDES = ("texels", "rows")


@dataclass(frozen=True)
class Factorization:
    """``A ~ U diag(S) V^T`` (float64), how good it is, and how it was made.

    ``v`` is None where the pipeline wrote ``V`` tile by tile instead.
    """

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
    error = _identity_error(last.frobenius2, s, "the projection A X X^T computed in the last "
                                                "pass")
    return Factorization(u, s, v, error, {"sketch_columns": width,
                                          "projection_columns": x.shape[1]})


def _one_pass(run_pass: RunPass, *, rows, texels, rank, extra, iterations, seed
              ) -> Factorization:
    sketch = Sketch.for_rank(rank, extra, rows)
    part = run_pass("sketch", sketch=sketch, seed=seed)
    y = None if sketch.exact_range else part.sums["y"]
    u, s, to_v = factors_from_co_range(
        y, part.sums["g"], (lambda q: q) if sketch.exact_co_range
        else (lambda q: psi_times(q, seed, sketch.s)), rank)
    estimate = estimated_error(part.sums["z"], to_v.T @ part.sums["wphi"], sketch.t, u, s,
                               part.frobenius2)
    v = run_pass("sketch-vectors", m=to_v).sums.get("v")
    error = {"log_relative_frobenius": estimate,
             "method": f"estimate from a Gaussian error sketch of {sketch.t} columns (Tropp "
                       "et al. 2017): E ||(A - U S V^T) Phi||_F^2 / t = ||A - U S V^T||_F^2",
             "frobenius_norm": math.sqrt(part.frobenius2)}
    widths = {"sketch_k": sketch.k, "sketch_s": sketch.s, "sketch_t": sketch.t}
    return Factorization(u, s, v, error, widths)


def randomized_svd_rows(run_pass: RunPass, *, rows: int, texels: int, rank: int, extra: int,
                        iterations: int, seed: int) -> Factorization:
    """:func:`randomized_svd` with row-side sketches: client memory ``O(rows x l)``.

    From an orthonormal Gaussian basis ``Q_0`` (rows x l), each pass computes ``A (A^T Q)`` in
    one read of the data (texel tile by texel tile: ``A_t (A_t^T Q)``; a tile's ``A_t^T Q``
    never leaves its task) and re-orthonormalises it. There are ``iterations + 1`` such passes,
    the last in float64 with the Gram matrix of ``Z = A^T Q``, from which ``U``, ``S`` and the
    map to ``V`` follow (:func:`tasks.svd.factors_from_gram`); a last pass forms ``V`` tile by
    tile. That is ``iterations + 2`` passes, one more than on the texel side, for a subspace of
    one degree more in ``A A^T`` (``(A A^T)^(q+1) Q_0`` against ``A (A^T A)^q X_0``).
    """
    width = rank + extra
    q = orthonormalize(gaussian(rows, width, seed=seed, stream=4))
    for _ in range(iterations):
        y = run_pass("row-power", q=q.astype(np.float32)).sums["y"]
        q = orthonormalize(y)
        del y
    last = run_pass("row-gram", q=q)
    u, s, to_v = factors_from_gram(last.sums["y"], last.sums["g"], rank)
    v = run_pass("row-vectors", q=q, m=to_v).sums.get("v")
    error = _identity_error(last.frobenius2, s, "the projection A X X^T onto the texel-side "
                            "basis X = A^T Q (Gram-orthonormalised) of the last row-side pass")
    return Factorization(u, s, v, error, {"sketch_columns": width})


def _identity_error(frobenius2: float, s: np.ndarray, projection: str) -> dict[str, Any]:
    """The error record of a projection: relative error from ``||A||_F^2 - sum(S^2)``."""
    relative = error_from_identity(frobenius2, s)
    error = {"log_relative_frobenius": max(relative, 0.0),
             "method": "identity ||A - U S V^T||_F^2 = ||A||_F^2 - sum(S^2), exact in exact "
                       f"arithmetic for {projection}",
             "resolution": IDENTITY_RESOLUTION,
             "frobenius_norm": math.sqrt(frobenius2)}
    if relative < IDENTITY_RESOLUTION:
        error["note"] = (f"below the identity's resolution ({IDENTITY_RESOLUTION:g}) in floating "
                         "point: an upper bound; --verify measures it directly")
    return error

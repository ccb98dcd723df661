"""Compiled loops (numba) of the one pass's sparse sign products (:mod:`tasks.svd`).

A sparse sign map holds :data:`tasks.svd.SPARSITY` entries +-1 per row, given as two arrays
(:func:`tasks.svd.sign_map`): ``cols`` (row x entry: the column) and ``signs`` (+-1,
float32). Two products use them on every value the one pass reads:

- :func:`add_sign_columns`, the range sketch ``y += a Omega`` (``Omega``: n x k, one row per
  texel). Rows of ``a`` are taken :data:`ROW_GROUP` at a time and their texels
  :data:`TEXEL_RUN` at a time, copied side by side, so that each texel's entries are read once
  per group and every entry adds a short contiguous vector to float64 sums of ``k`` columns
  (kept in cache);
- :func:`add_sign_rows`, the co-range sketch ``w += Psi a`` (``Psi^T``: one row per matrix
  row): every matrix row is added, with its signs, to its entries' rows of ``w``, a run of
  :data:`TEXEL_RUN` x 4 texels at a time so that those rows of ``w`` stay in cache.

Both are fixed-order loops (the same bits on every scheduler and thread count) that release
the GIL (``nogil``), so dask's threads run tiles in parallel; neither uses numba's own
threads. Compiled code is kept in numba's on-disk cache, as :mod:`tasks.csr_kernel`'s.
scipy's sparse products, which they replace, took about 3x as long on one thread
(BENCHMARKS.md, "The one pass's products compiled").
"""

from __future__ import annotations

import numba
import numpy as np

ROW_GROUP = 32  # rows of ``a`` whose range-sketch sums are formed at once (float64, k each)
TEXEL_RUN = 128  # texels of those rows copied side by side at once


@numba.njit(nogil=True, cache=True)
def _sign_columns(a, cols, signs, y, width, run_length):  # pragma: no cover - compiled
    # ``width`` and ``run_length`` are arguments, not constants: with a constant trip count
    # LLVM unrolled the innermost loop and left it scalar (3.5x slower)
    rows, n = a.shape
    z, k = cols.shape[1], y.shape[1]
    sums = np.zeros((k, width))
    group = np.zeros((run_length, width), np.float32)
    for r0 in range(0, rows, width):
        g = min(width, rows - r0)
        sums[:] = 0.0
        group[:] = 0.0
        for t0 in range(0, n, run_length):
            run = min(run_length, n - t0)
            for i in range(g):
                for t in range(run):
                    group[t, i] = a[r0 + i, t0 + t]
            for t in range(run):
                values = group[t]
                for j in range(z):
                    out, sign = sums[cols[t0 + t, j]], signs[t0 + t, j]
                    for i in range(width):
                        out[i] += sign * values[i]
        for i in range(g):
            for c in range(k):
                y[r0 + i, c] += sums[c, i]


@numba.njit(nogil=True, cache=True)
def _sign_rows(a, cols, signs, w, run_length):  # pragma: no cover - compiled
    rows, n = a.shape
    z = cols.shape[1]
    for t0 in range(0, n, run_length):
        t1 = min(t0 + run_length, n)
        for r in range(rows):
            values = a[r, t0:t1]
            for j in range(z):
                out, sign = w[cols[r, j], t0:t1], signs[r, j]
                for t in range(t1 - t0):
                    out[t] += sign * values[t]


def _sign_arrays(cols: np.ndarray, signs: np.ndarray, rows: int, width: int
                 ) -> tuple[np.ndarray, np.ndarray]:
    """``cols`` and ``signs`` as the loops take them, checked against the map's size."""
    cols = np.ascontiguousarray(cols, np.int64)
    signs = np.ascontiguousarray(signs, np.float32)
    if cols.ndim != 2 or cols.shape != signs.shape or cols.shape[0] != rows:
        raise ValueError(f"a sign map of {rows} rows was given entries of shape {cols.shape} "
                         f"and signs of shape {signs.shape}")
    if cols.size and (cols.min() < 0 or cols.max() >= width):
        raise ValueError(f"a sign map's column lies outside its {width} columns")
    return cols, signs


def _float32(x: np.ndarray, name: str) -> None:
    if x.dtype != np.float32 or x.ndim != 2 or not x.flags.c_contiguous:
        raise TypeError(f"{name} must be a C-contiguous float32 matrix, not {x.dtype} "
                        f"{x.shape}")


def add_sign_columns(a: np.ndarray, cols: np.ndarray, signs: np.ndarray, y: np.ndarray
                     ) -> None:
    """``y += a Omega`` in place.

    ``a`` is ``rows x n`` (float32), ``Omega`` ``n x k`` with row ``t`` holding ``signs[t]`` at
    ``cols[t]``, ``y`` ``rows x k`` (C-contiguous float32); each row's sum is formed in
    float64, texel by texel in order.
    """
    a = np.ascontiguousarray(a, np.float32)
    _float32(y, "y")
    if y.shape[0] != a.shape[0]:
        raise ValueError(f"a has {a.shape[0]} rows and y {y.shape[0]}")
    _sign_columns(a, *_sign_arrays(cols, signs, a.shape[1], y.shape[1]), y, ROW_GROUP,
                  TEXEL_RUN)


def add_sign_rows(a: np.ndarray, cols: np.ndarray, signs: np.ndarray, w: np.ndarray) -> None:
    """``w += Psi a`` in place.

    ``a`` is ``rows x n`` (float32), ``Psi^T`` ``rows x s`` with row ``r`` holding
    ``signs[r]`` at ``cols[r]``, ``w`` ``s x n`` (C-contiguous float32), summed in float32,
    row by row in order.
    """
    a = np.ascontiguousarray(a, np.float32)
    _float32(w, "w")
    if w.shape[1] != a.shape[1]:
        raise ValueError(f"a has {a.shape[1]} columns and w {w.shape[1]}")
    _sign_rows(a, *_sign_arrays(cols, signs, a.shape[0], w.shape[0]), w, 4 * TEXEL_RUN)

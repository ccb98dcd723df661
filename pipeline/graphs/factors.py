"""Stored factors as a new exact SVD: ``btf compress`` and ``btf crop`` of a compressed store.

A compressed store's values are ``U diag(S) V^T``. A part of it (some rows of ``U``, a region
of ``V``), or the whole of a store whose ``U`` or ``V`` is not orthonormal (an enlarged store,
a crop), is re-expressed exactly, up to float rounding, as an SVD ``U' diag(S') V'^T`` by
:func:`tasks.dfmf.svd_map`: a QR of the rows of ``U`` (small: rows x K, on the client) and
the Gram matrix of ``V diag(S)`` (one read of ``V``, by chunks); ``V'`` is then written chunk
by chunk from ``V``. Memory holds ``U`` and one chunk of ``V`` per task, whatever the texels.
"""

from __future__ import annotations

import numpy as np

ORTHONORMAL = 1e-5  # |U^T U - I| and |V^T V - I| within this: the factors are an SVD already


def _gram(block: np.ndarray, s: np.ndarray) -> np.ndarray:
    c = np.asarray(block, np.float64).reshape(-1, block.shape[-1]) * s
    return c.T @ c


def pairwise_sum(parts: list):
    """Delayed sum of delayed arrays in a fixed binary tree (the same bits on any scheduler)."""
    import dask

    while len(parts) > 1:
        parts = [dask.delayed(np.add, pure=True)(*parts[i : i + 2]) if i + 1 < len(parts)
                 else parts[i] for i in range(0, len(parts), 2)]
    return parts[0]


def gram(v, s: np.ndarray, session) -> np.ndarray:
    """``(V diag(s))^T (V diag(s))`` (float64) of a dask ``V`` ``(y, x, K)``: one read.

    The chunks' products are summed in a fixed tree, so every scheduler gives the same bits.
    """
    import dask

    blocks = v.to_delayed().ravel()
    parts = [dask.delayed(_gram, pure=True)(b, np.asarray(s, np.float64)) for b in blocks]
    (g,) = session.compute(pairwise_sum(parts))
    return g


def is_svd(u: np.ndarray, s: np.ndarray, g_v: np.ndarray) -> bool:
    """Whether ``u`` and ``V`` (its Gram matrix ``g_v = V^T V``) are orthonormal, ``s`` sorted.

    Then ``u diag(s) V^T`` is an SVD already, and its first ``r`` components are the best
    rank-``r`` approximation of it (Eckart-Young): truncation needs no new factors.
    """
    k = len(s)
    eye = np.eye(k)
    return (bool(np.all(np.diff(s) <= 0)) and float(np.abs(u.T @ u - eye).max()) < ORTHONORMAL
            and float(np.abs(g_v - eye).max()) < ORTHONORMAL)


def _new_v(block: np.ndarray, vmap: np.ndarray) -> np.ndarray:
    ny, nx, k = block.shape
    return (np.asarray(block, np.float64).reshape(-1, k) @ vmap).astype(np.float32).reshape(
        ny, nx, vmap.shape[1])


def mapped_v(v, vmap: np.ndarray):
    """Dask ``V @ vmap`` ``(y, x, K')`` chunk by chunk (float64 products, float32 result)."""
    import dask.array as da

    return da.map_blocks(_new_v, v, vmap, dtype=np.float32,
                         chunks=(*v.chunks[:2], (vmap.shape[1],)),
                         meta=np.empty((0, 0, 0), np.float32))


def dropped(s_all: np.ndarray, rank: int) -> float:
    """Relative Frobenius norm of the components past ``rank`` (of all of ``s_all``)."""
    total = float(np.sum(np.asarray(s_all, np.float64) ** 2))
    return float(np.sqrt(np.sum(np.asarray(s_all[rank:], np.float64) ** 2) / total)) \
        if total > 0 else 0.0

"""Prescriptions: sparse linear operators that transfer sample pixels to output pixels.

A plan made on the reference image (quilting, the roller) compiles to ``P``, a
``(output pixels) x (sample pixels)`` matrix whose rows are blend weights summing to 1
(docs/README.md, "Design in brief"). Applying it is ``layer_out = P @ layer_in`` for every
layer, which is what makes the transfer identical for all light and view directions; being
linear, it applies just as well to the eigentextures of a compressed store. Stored as padded
rows (an ELL matrix: ``index`` and ``weight`` of shape ``(output pixels, terms)``, index -1
for unused terms) and applied as a scipy CSR matrix, by a compiled row loop over whole layers
(:func:`apply`, the loop in :mod:`tasks.csr_kernel`, imported on first use: numba takes a
quarter of a second and ~100 MB to load).
"""

from __future__ import annotations

import numpy as np
import scipy  # submodules load on first use, not at every btf command (test_layout: HEAVY)


def to_csr(index: np.ndarray, weight: np.ndarray, samples: int) -> scipy.sparse.csr_matrix:
    """The CSR matrix of padded rows ``index``/``weight`` (``-1`` marks unused terms)."""
    index = np.asarray(index).reshape(index.shape[0], -1)
    weight = np.asarray(weight, np.float32).reshape(index.shape)
    used = index >= 0
    rows = np.broadcast_to(np.arange(index.shape[0])[:, None], index.shape)[used]
    matrix = scipy.sparse.csr_matrix((weight[used], (rows, index[used])),
                                     shape=(index.shape[0], samples), dtype=np.float32)
    matrix.sum_duplicates()
    return matrix


def check(index: np.ndarray, weight: np.ndarray, samples: int) -> list[str]:
    """What is wrong with padded prescription rows (empty list: nothing)."""
    problems = []
    used = index >= 0
    if np.any(index >= samples) or np.any(index < -1):
        problems.append(f"indices outside 0..{samples - 1}")
    if np.any(weight[used] < 0) or np.any(weight[~used] != 0):
        problems.append("negative weights, or weights on unused terms")
    total = weight.sum(axis=-1, dtype=np.float64)
    if not np.allclose(total, 1.0, atol=1e-5):
        problems.append(f"rows do not sum to 1 (from {total.min():.6f} to {total.max():.6f})")
    return problems


def apply(matrix: scipy.sparse.csr_matrix, layers: np.ndarray, *, output: tuple[int, int],
          out: np.ndarray | None = None) -> np.ndarray:
    """``P @ layer`` for each layer of ``(..., y, x, channel)`` float32 layers.

    ``output`` is the ``(y, x)`` shape of a result layer; ``out``, if given, a C-contiguous
    float32 array of the result's shape to write into (reusing one saves the page faults of a
    fresh allocation, which cost as much as the product here). A compiled loop over the output
    texels of each layer (:func:`tasks.csr_kernel.csr_product`), which releases the GIL: the
    pipeline's threads apply prescriptions in parallel. The weights are taken as float32 (as
    stored); the result equals scipy's ``P @ layer`` for that float32 CSR matrix bit for bit.
    """
    from tasks.csr_kernel import csr_product

    matrix = scipy.sparse.csr_matrix(matrix, dtype=np.float32)
    layers = np.ascontiguousarray(layers, np.float32)
    *lead, ny, nx, nc = layers.shape
    if matrix.shape != (output[0] * output[1], ny * nx):
        raise ValueError(f"a {matrix.shape[0]} x {matrix.shape[1]} prescription cannot take "
                         f"{ny} x {nx} layers to {output[0]} x {output[1]}")
    shape = (*lead, *output, nc)
    if out is None:
        out = np.empty(shape, np.float32)
    elif out.shape != shape or out.dtype != np.float32 or not out.flags.c_contiguous:
        raise ValueError(f"out must be a C-contiguous float32 array of shape {shape}, "
                         f"not {out.dtype} {out.shape}")
    elif np.shares_memory(out, layers):
        raise ValueError("out must not overlap the layers it is computed from")
    csr_product(matrix.indptr, matrix.indices, matrix.data, layers.reshape(-1, ny * nx, nc),
             out.reshape(-1, output[0] * output[1], nc))
    return out

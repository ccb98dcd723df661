"""Prescriptions: sparse linear operators that transfer sample pixels to output pixels.

A plan made on the reference image (quilting, the roller) compiles to ``P``, a
``(output pixels) x (sample pixels)`` matrix whose rows are blend weights summing to 1
(docs/README.md, "Design in brief"). Applying it is ``layer_out = P @ layer_in`` for every
layer, which is what makes the transfer identical for all light and view directions; being
linear, it applies just as well to the eigentextures of a compressed store. Stored as padded
rows (an ELL matrix: ``index`` and ``weight`` of shape ``(output pixels, terms)``, index -1
for unused terms) and applied as a CSR matrix (:func:`rows`) to whole layers (:func:`apply`): by a
compiled row loop (:mod:`tasks.csr_kernel`, imported on first use) where there is enough work
to pay for loading numba, 0.6-1.2 s of a process's time and ~100 MB, else by scipy's own row
loop; both give the same bits (:func:`compiled_pays`).
"""

from __future__ import annotations

import platform
import sys
from typing import NamedTuple

import numpy as np
import scipy  # submodules load on first use, not at every btf command (test_layout: HEAVY)


class Csr(NamedTuple):
    """A CSR matrix as scipy lays one out (float32 ``data``), held and applied without scipy."""

    indptr: np.ndarray
    indices: np.ndarray
    data: np.ndarray
    shape: tuple[int, int]

    def to_scipy(self) -> scipy.sparse.csr_matrix:
        """The same matrix for scipy: the same terms in the same order."""
        import scipy.sparse

        return scipy.sparse.csr_matrix((self.data, self.indices, self.indptr),
                                       shape=self.shape)


def rows(index: np.ndarray, weight: np.ndarray, samples: int) -> Csr:
    """The CSR matrix of padded rows ``index``/``weight`` (``-1`` marks unused terms).

    Each row keeps its used terms in their stored order, a sample texel named twice as two
    terms: the product adds them one after the other, in that order. Made with numpy alone:
    importing ``scipy.sparse`` is 0.25-0.35 s of a process (scipy's array-API layer imports
    parts of numpy no stage uses), more than applying a 960^2 tile to ten layers, and its
    conversion to scipy's canonical form (columns sorted, duplicates summed) 0.1 s more.
    """
    index = np.asarray(index).reshape(index.shape[0], -1)
    weight = np.asarray(weight, np.float32).reshape(index.shape)
    used = index >= 0
    # scipy's index type: int32 where it holds every index and term (numba's cached loops)
    kind = np.int32 if max(samples, index.size) <= np.iinfo(np.int32).max else np.int64
    indptr = np.zeros(index.shape[0] + 1, kind)
    np.cumsum(used.sum(axis=1), out=indptr[1:])
    return Csr(indptr, index[used].astype(kind, copy=False), weight[used],
               (index.shape[0], samples))


def to_csr(index: np.ndarray, weight: np.ndarray, samples: int) -> scipy.sparse.csr_matrix:
    """:func:`rows` as a scipy CSR matrix: the same terms in the same order.

    So ``to_csr(...) @ layer`` is :func:`apply`'s product, bit for bit; call
    ``sum_duplicates`` on it for the canonical form.
    """
    return rows(index, weight, samples).to_scipy()


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


COMPILED_VALUES = 2_000_000_000  # output values from which the compiled loop pays for numba
SAME_BITS = ("x86_64", "AMD64")  # where scipy's loop is known to give numba's bits (no FMA)


def compiled_pays(values: int) -> bool:
    """Whether to apply prescriptions making ``values`` output values with the compiled loop.

    It takes 5.2 ms a 960^2 RGB layer where scipy's loop takes 8.0 ms (1 ns less a value of
    a core), and loading numba and the loop takes a process 0.6-1.2 s, during which it holds
    the GIL (BENCHMARKS.md, "Prescriptions without numba on small work"). In one process on
    two threads the load is paid back from about :data:`COMPILED_VALUES` values (720 such
    layers; each worker process of a cluster pays its own load), so the compiled loop is used
    from there, or where numba is loaded already: it is imported only by the kernel modules,
    as they are first used (a quilting plan's), and after that the loop loads in 30 ms. The
    two loops give the same bits on x86-64, whose scipy wheels do not fuse multiply-adds (the
    tests check it); elsewhere scipy's C++ may, so the compiled loop is always used there and
    the bits never depend on the work or on what a process has loaded.
    """
    if platform.machine() not in SAME_BITS:
        return True
    return values >= COMPILED_VALUES or "numba" in sys.modules


def apply(matrix: Csr | scipy.sparse.spmatrix, layers: np.ndarray, *,
          output: tuple[int, int], out: np.ndarray | None = None,
          compiled: bool | None = None) -> np.ndarray:
    """``P @ layer`` for each layer of ``(..., y, x, channel)`` float32 layers.

    ``matrix`` is ``P``: a :class:`Csr` (:func:`rows`), or any scipy sparse matrix.
    ``output`` is the ``(y, x)`` shape of a result layer; ``out``, if given, a C-contiguous
    float32 array of the result's shape to write into (reusing one saves the page faults of a
    fresh allocation, which cost as much as the product here). ``compiled``: a compiled loop
    over the output texels of each layer (:func:`tasks.csr_kernel.csr_product`), or scipy's
    own (``csr_matvecs``, 1.5x slower, and nothing to load); by default as
    :func:`compiled_pays` says for this call's values. Both release the GIL, so the
    pipeline's threads apply prescriptions in parallel. The weights are taken as float32 (as
    stored); the result equals scipy's ``P @ layer`` for that float32 CSR matrix bit for bit.
    """
    if not isinstance(matrix, Csr):
        matrix = scipy.sparse.csr_matrix(matrix, dtype=np.float32)
        matrix = Csr(matrix.indptr, matrix.indices, matrix.data, matrix.shape)
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
    source, target = layers.reshape(-1, ny * nx, nc), out.reshape(-1, output[0] * output[1], nc)
    if compiled is None:
        compiled = compiled_pays(out.size)
    if compiled:
        from tasks.csr_kernel import csr_product

        csr_product(matrix.indptr, matrix.indices, matrix.data, source, target)
    else:
        _scipy_product(matrix, source, target)
    return out


def _scipy_product(matrix: Csr, source: np.ndarray, target: np.ndarray) -> None:
    """``target[l] = P @ source[l]`` by scipy's row loop, into ``target`` (no copy).

    ``csr_matvecs`` is what ``P @ x`` runs for a dense ``x`` of several columns (one column:
    ``csr_matvec``, the same sums in the same order), after allocating its result: called on
    ``target`` itself it saves that allocation's page faults and a copy (11.3 -> 8.0 ms a
    960^2 RGB layer). Where a scipy lacks it, ``P @ x``.
    """
    try:
        from scipy.sparse._sparsetools import csr_matvecs
    except ImportError:  # pragma: no cover - a scipy that moved it
        product = matrix.to_scipy()
        for layer in range(source.shape[0]):
            target[layer] = product @ source[layer]
        return
    # flat views of each layer: the loop writes into them, so they must not be copies
    sources = source.reshape(len(source), source.shape[1] * source.shape[2])
    targets = target.reshape(len(target), target.shape[1] * target.shape[2])
    if targets.size and not np.shares_memory(targets, target):
        raise ValueError("the output must be C-contiguous")
    height, width = matrix.shape
    for layer in range(len(source)):
        targets[layer] = 0  # the loop adds every term into its output value
        csr_matvecs(height, width, source.shape[2], matrix.indptr, matrix.indices, matrix.data,
                    sources[layer], targets[layer])

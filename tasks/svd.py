"""Randomized SVD of a BTF matrix streamed in row blocks (paper 000, section 2.1, Fig. 2).

The BTF matrix ``A`` has one row per (view, light, channel) texture and one column per (y, x)
texel; its entries are range-reduced radiance ``log(radiance + eps)``. ``A = U S V^T`` gives the
eigen-ABRDFs ``U``, singular values ``S`` and eigentextures ``V``.

Multi-pass (Halko, Martinsson and Tropp 2011, with fused power steps): starting from a Gaussian
test matrix ``X_0`` (texels x ``l``, ``l = rank + oversampling``), every power pass computes
``sum_i A_i^T (A_i X)`` over row blocks ``A_i`` (one read of the data per ``A^T A``) and
re-orthonormalises the result by QR. The last pass projects onto ``X``, an orthonormal basis of
the block Krylov space of the last two iterates ``[X_{q-1}, X_q]`` (Musco and Musco 2015): for
the same passes it is markedly more accurate than the last iterate alone (measured on a
generated BTF at rank 64 with two power passes: 1.002x instead of 1.016x the optimal error).
It computes ``Z = A X`` and ``||A||_F^2``; with ``Z = P diag(s) R^T`` (a small SVD),
``A ~ A X X^T = P diag(s) (X R)^T``, truncated to the rank. Because ``X`` is orthonormal, the
rows of ``A - A X X^T`` are orthogonal to those of ``(Z - Z_K) X^T``, so the error needs no
extra pass::

    ||A - U S V^T||_F^2 = ||A||_F^2 - ||Z||_F^2 + sum_{i>K} s_i^2 = ||A||_F^2 - sum_{i<=K} s_i^2

This holds in exact arithmetic. In floating point both terms carry the rounding of float32
products (relative ~1e-7), so the difference resolves relative errors down to about
:data:`IDENTITY_RESOLUTION` only; below that the stored value is an upper bound of that size,
and ``--verify`` measures the error directly.

Single pass (Tropp, Yurtsever, Udell and Cevher 2017, one-view sketch): one read gives the
range sketch ``Y = A Omega`` (rows x k), the co-range sketch ``W = Psi A`` (s x texels) and an
error sketch ``A Phi``; ``A ~ Q (Psi Q)^+ W`` with ``Q = orth(Y)``. ``Omega`` and ``Psi`` are
sparse sign maps, ``Phi`` Gaussian. The texel-side test matrices are made tile by tile from
seeds and ``W`` is kept tile by tile
(the pipeline writes it to a scratch array), so only ``Y``, ``A Phi``, ``W W^T`` and
``W Phi`` are summed: the factors come from the Gram matrix of the small core
(:func:`factors_from_co_range`) and ``V`` is formed tile by tile from the stored ``W``. The
error is estimated from the error sketch: ``E ||(A - A_hat) Phi||_F^2 / t = ||A - A_hat||_F^2``
for Gaussian ``Phi`` with ``t`` columns.

Block products run in float32 (the data's precision); sums over column tiles and over row blocks
are accumulated in float64 (except the one-view co-range sketch, float32 as it is stored), and
every orthonormalisation and small factorisation is float64.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from tasks.transform import LOG_MAX, Transform

TILE = 16384  # columns per float32 product; longer sums are accumulated in float64
IDENTITY_RESOLUTION = 1e-3  # relative errors the identity resolves (measured floor ~2e-4)
GRAM_FLOOR = 1e-10  # Gram eigenvalues kept, relative to the largest (see factors_from_gram)


@dataclass(frozen=True)
class BlockCheck:
    """What a row block holds besides good radiance: counts and first offending positions.

    Positions are index tuples in the caller's coordinates (see :func:`check_block`).
    """

    nonfinite: int = 0
    negative: int = 0
    first_nonfinite: tuple[int, ...] | None = None
    first_negative: tuple[int, ...] | None = None

    def merge(self, other: BlockCheck) -> BlockCheck:
        """Combine two checks; "first" means smallest index."""
        def first(a, b):
            return b if a is None else a if b is None else min(a, b)

        return BlockCheck(self.nonfinite + other.nonfinite, self.negative + other.negative,
                          first(self.first_nonfinite, other.first_nonfinite),
                          first(self.first_negative, other.first_negative))


def check_block(radiance: np.ndarray, origin: tuple[int, ...]) -> BlockCheck:
    """Count non-finite and negative values of a block whose first element is at ``origin``."""
    radiance = np.asarray(radiance)
    low, high = radiance.min(), radiance.max()  # NaN propagates: one cheap pass if all is well
    if np.isfinite(low) and np.isfinite(high) and low >= 0:
        return BlockCheck()
    nonfinite = ~np.isfinite(radiance)
    negative = radiance < 0
    n_bad, n_neg = int(nonfinite.sum()), int(negative.sum())

    def first(mask):
        return tuple(int(o + i) for o, i in zip(origin, np.argwhere(mask)[0], strict=True))

    return BlockCheck(n_bad, n_neg, first(nonfinite) if n_bad else None,
                      first(negative) if n_neg else None)


def log_transform(radiance: np.ndarray, *, eps: float, clamp: bool = False,
                  inplace: bool = False) -> np.ndarray:
    """Range reduction ``log(radiance + eps)`` (float32); negatives set to 0 first if ``clamp``.

    With ``inplace`` a float32 array is overwritten (no copy of a large block); otherwise the
    input is left alone.
    """
    x = radiance if inplace else np.array(radiance, dtype=np.float32)
    if clamp:
        np.maximum(x, 0.0, out=x)
    x += np.float32(eps)
    return np.log(x, out=x)


def frobenius2(a: np.ndarray, *, run: int = 4096) -> float:
    """``||a||_F^2`` of float32 rows: float32 sums over runs of ``run`` values, added in float64.

    Each partial sum carries a relative rounding error of about ``sqrt(run)`` float32 epsilons
    (~4e-6, random), and there are many of them, so the total is accurate to ~1e-7.
    """
    a = np.ascontiguousarray(a, np.float32)
    flat = a.reshape(-1)
    head = flat.size - flat.size % run
    body = flat[:head].reshape(-1, run)
    partial = np.einsum("ij,ij->i", body, body).astype(np.float64).sum()
    return float(partial + np.sum(flat[head:].astype(np.float64) ** 2))


def matrix_rows(layers: np.ndarray) -> np.ndarray:
    """BTF matrix rows of a block of layers ``(..., y, x, channel)``.

    Rows are ordered by the leading axes then channel, columns by ``y`` then ``x``: the row of
    (view, light, channel) holds one texture (paper 000, Fig. 2).
    """
    layers = np.asarray(layers)
    lead = int(np.prod(layers.shape[:-3]))
    ny, nx, nc = layers.shape[-3:]
    moved = np.moveaxis(layers.reshape(lead, ny, nx, nc), -1, 1)
    return np.ascontiguousarray(moved).reshape(lead * nc, ny * nx)


def log_rows(layers: np.ndarray, out: np.ndarray, *, eps: float, clamp: bool = False
             ) -> np.ndarray:
    """Range-reduced BTF matrix rows of a block of layers, written into ``out``.

    ``layers`` is ``(..., y, x, channel)`` float32; ``out`` receives one row per (leading
    index, channel), the same rows as ``log_transform(matrix_rows(layers))``, in one strided
    pass per channel and one in-place log (no intermediate copy of the block).
    """
    ny, nx, nc = layers.shape[-3:]
    src = np.asarray(layers, np.float32).reshape(-1, ny * nx, nc)
    dest = out.reshape(src.shape[0], nc, ny * nx)
    for c in range(nc):
        if clamp:
            np.maximum(src[:, :, c], 0.0, out=dest[:, c])
            dest[:, c] += np.float32(eps)
        else:
            np.add(src[:, :, c], np.float32(eps), out=dest[:, c])
    return np.log(out, out=out)


def blas_ready(x: np.ndarray) -> np.ndarray:
    """``x`` as an aligned, C-contiguous float32 array (copied only if it is not one).

    numpy hands only aligned arrays to BLAS and multiplies others with its own loops, which
    sum in another order: an array deserialized on a dask worker can sit at any address, and
    without this its products would differ in the last bits from the same products elsewhere.
    """
    return np.require(x, np.float32, ["C_CONTIGUOUS", "ALIGNED"])


def project(a: np.ndarray, x: np.ndarray, *, tile: int = TILE) -> np.ndarray:
    """``a @ x`` for float32 rows ``a`` (r x n) and a sketch ``x`` (n x l).

    Each tile of columns is a float32 product; the tiles are summed in float64.
    """
    a, x = blas_ready(a), blas_ready(x)
    out = np.zeros((a.shape[0], x.shape[1]), np.float64)
    for t in range(0, a.shape[1], tile):
        out += a[:, t : t + tile] @ x[t : t + tile]
    return out


def power_step(a: np.ndarray, x: np.ndarray) -> np.ndarray:
    """A row block's share ``a^T (a x)`` of one fused power pass (n x l).

    Float32, as computed (its sums over the block's rows are short); shares are added in
    float64 by :func:`combine_parts`, which halves what travels between tasks.
    """
    a = blas_ready(a)
    inner = project(a, x).astype(np.float32)
    return a.T @ inner


def co_project(a: np.ndarray, q: np.ndarray, *, exact: bool = False) -> np.ndarray:
    """A block's share ``a^T q`` (texels x l, float64) for its rows ``q`` of a row-side basis.

    Float32 products (the block's rows make short sums), or with ``exact`` float64 ones: the
    last pass of the row-side SVD forms a Gram matrix of these, which squares their rounding.
    """
    if exact:
        return np.asarray(a, np.float64).T @ np.asarray(q, np.float64)
    return (blas_ready(a).T @ blas_ready(q)).astype(np.float64)


def row_product(a: np.ndarray, z: np.ndarray, *, exact: bool = False) -> np.ndarray:
    """``a z`` (rows x l, float64) for a block and a texel-side share ``z`` of the same texels."""
    if exact:
        return np.asarray(a, np.float64) @ np.asarray(z, np.float64)
    return project(a, z.astype(np.float32))


def factors_from_gram(y: np.ndarray, gram: np.ndarray, rank: int
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``U``, ``S`` and the map to ``V`` from a row-side pass ``Z = A^T Q``, ``y = A Z``.

    ``gram = Z^T Z = W diag(lambda) W^T``, so ``X = Z W lambda^(-1/2)`` is an orthonormal
    texel-side basis and ``A X = y W lambda^(-1/2)``: with its small SVD ``P diag(s) R^T``,
    ``A ~ A X X^T = P diag(s) (X R)^T`` as in :func:`factors_from_projection`. Returns ``U``,
    ``S`` and ``M`` with ``V = Z M`` (the caller forms ``V`` tile by tile). Forming the Gram
    matrix squares the condition number: a direction with ``lambda`` below :data:`GRAM_FLOOR`
    of the largest (singular values below 1e-5 of the largest, under the float32 data's own
    resolution) would come out with orthogonality errors above ~1e-6, so such directions are
    left out: their singular values are 0 and their columns of ``V`` are 0.
    """
    evals, w, kept = gram_eigen(gram)
    scale = np.zeros_like(w)
    scale[:, kept] = w[:, kept] / np.sqrt(evals[kept])
    p, s, rt = np.linalg.svd(np.asarray(y, np.float64) @ scale, full_matrices=False)
    return p[:, :rank], s[:rank], scale @ rt[:rank].T


def gram_eigen(gram: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eigenvalues (decreasing) and eigenvectors of a Gram matrix, and which are kept.

    Kept: eigenvalues above :data:`GRAM_FLOOR` of the largest (none if it is not positive).
    """
    evals, w = np.linalg.eigh(np.asarray(gram, np.float64))
    order = np.argsort(evals)[::-1]
    evals, w = evals[order], w[:, order]
    kept = evals > (evals[0] * GRAM_FLOOR if evals.size and evals[0] > 0 else np.inf)
    return evals, w, kept


def orthonormalize(w: np.ndarray) -> np.ndarray:
    """Orthonormal basis of the columns of ``w`` (reduced Householder QR, float64).

    Householder QR stays orthonormal when ``w`` is rank-deficient or very ill-conditioned,
    which is what power iterations produce. ``w`` may be overwritten (the sketch is large and
    the caller does not need it again). A shifted CholeskyQR3 was measured as well: no faster
    here, and it needs a fallback for rank-deficient sketches.
    """
    from scipy.linalg import qr

    q, _ = qr(np.asarray(w, np.float64), mode="economic", overwrite_a=True,
              check_finite=False)
    return q


def gaussian(rows: int, cols: int, *, seed: int, stream: int) -> np.ndarray:
    """A Gaussian test matrix (float64) from an explicit seed and stream number."""
    return np.random.default_rng([seed, stream]).standard_normal((rows, cols))


def factors_from_projection(z: np.ndarray, x: np.ndarray, rank: int
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``U, S, V`` of rank ``rank`` from ``z = A x`` and the orthonormal ``x`` (see module)."""
    p, s, rt = np.linalg.svd(np.asarray(z, np.float64), full_matrices=False)
    return p[:, :rank], s[:rank], x @ rt[:rank].T


def error_from_identity(frobenius2: float, s: np.ndarray) -> float:
    """Relative Frobenius error ``sqrt(max(||A||^2 - sum s_i^2, 0)) / ||A||`` (float64)."""
    if frobenius2 <= 0:
        return 0.0
    residual = max(float(frobenius2) - float(np.sum(np.asarray(s, np.float64) ** 2)), 0.0)
    return float(np.sqrt(residual / frobenius2))


PSI_GROUP = 1024  # rows of Psi generated per seed stream (so a task makes only its rows')


@dataclass(frozen=True)
class Sketch:
    """One-view sketch sizes: ``k`` range columns, ``s`` co-range rows, ``t`` error columns.

    A side that would reach the matrix's ``rows`` is exact instead of random: ``k = rows``
    takes ``Q = I`` (no range sketch), ``s = rows`` takes ``Psi = I`` (the co-range sketch is
    the matrix itself, ``W = A``).
    """

    k: int
    s: int
    rows: int
    t: int = 10

    @staticmethod
    def for_rank(rank: int, oversample: int, rows: int) -> Sketch:
        """``k = rank + oversample`` and Tropp et al.'s ``s = 2k + 1``, at most ``rows`` each."""
        k = min(rank + oversample, rows)
        return Sketch(k, min(2 * k + 1, rows), rows)

    @property
    def exact_range(self) -> bool:
        """Whether ``Q = I``: the range sketch would span every row."""
        return self.k >= self.rows

    @property
    def exact_co_range(self) -> bool:
        """Whether ``Psi = I``: the co-range sketch is the matrix itself."""
        return self.s >= self.rows


SPARSITY = 8  # nonzeros per texel row of Omega and per matrix-row column of Psi


def sign_map(seed: int, stream: int, key: tuple[int, ...], n: int, width: int
             ) -> tuple[np.ndarray, np.ndarray]:
    """An ``n x width`` sparse sign matrix, made from a seed, as its entries row by row.

    In each row, :data:`SPARSITY` entries +-1 at distinct random columns (all ``width`` if
    fewer), the rest 0. Returns ``cols`` (``n x z`` int64, ascending in each row) and
    ``signs`` (``n x z`` float32, +-1): the form the compiled products of
    :mod:`tasks.sketch_kernel` take.

    Tropp et al. (2019, section 3.3) recommend such maps for streaming sketches: they work as
    well as Gaussian ones (measured here: the same errors to 1%, bench store and ranks 16-64)
    while a product with a block costs ``SPARSITY`` additions per value instead of ``width``
    multiply-adds. ``key`` names the block of rows (a tile's first texel, a group of matrix
    rows), so every task makes its rows alone and the same rows on every scheduler.
    """
    rng = np.random.default_rng([seed, stream, *key])
    z = min(SPARSITY, width)
    if width <= 4 * z:  # few columns: a random choice of z per row, by permutation
        cols = np.sort(rng.permuted(np.tile(np.arange(width), (n, 1)), axis=1)[:, :z], axis=1)
    else:  # draw, then redraw the rows with a repeated column (rare) until none is left
        cols = np.sort(rng.integers(0, width, (n, z)), axis=1)
        repeated = np.flatnonzero(np.any(cols[:, 1:] == cols[:, :-1], axis=1))
        while repeated.size:
            redrawn = np.sort(rng.integers(0, width, (repeated.size, z)), axis=1)
            cols[repeated] = redrawn
            repeated = repeated[np.any(redrawn[:, 1:] == redrawn[:, :-1], axis=1)]
    signs = rng.integers(0, 2, (n, z)).astype(np.float32) * 2 - 1
    return cols.astype(np.int64), signs


def tile_test_matrix(seed: int, stream: int, key: tuple[int, ...], texels: int, cols: int
                     ) -> np.ndarray:
    """A tile's rows of a texel-side Gaussian test matrix (float32), from its own seed.

    ``key`` names the tile (its first texel), so every task makes its rows alone and the same
    rows on every scheduler; the matrix as a whole depends on the tiling.
    """
    rng = np.random.default_rng([seed, stream, *key])
    return rng.standard_normal((texels, cols), dtype=np.float32)


def co_range_rows(seed: int, s: int, r0: int, r1: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows ``r0:r1`` of ``Psi^T``, the co-range test matrix transposed, as sign-map entries.

    ``Psi^T`` (``rows x s``, entries as :func:`sign_map` gives them) is made in groups of
    :data:`PSI_GROUP` rows, each from its own seed stream, so any range of rows is the same
    whichever task (or the client) makes it.
    """
    g0, g1 = r0 // PSI_GROUP, (r1 - 1) // PSI_GROUP + 1
    groups = [sign_map(seed, 3, (g,), PSI_GROUP, s) for g in range(g0, g1)]
    rows = slice(r0 - g0 * PSI_GROUP, r1 - g0 * PSI_GROUP)
    return (np.concatenate([c for c, _ in groups])[rows],
            np.concatenate([x for _, x in groups])[rows])


def co_range_test(seed: int, s: int, r0: int, r1: int):
    """Columns ``r0:r1`` of the ``s x rows`` co-range test matrix ``Psi`` (scipy CSR, float32).

    The same entries as :func:`co_range_rows`, for products on the client (:func:`psi_times`).
    """
    import scipy.sparse

    cols, signs = co_range_rows(seed, s, r0, r1)
    z = cols.shape[1]
    return scipy.sparse.csr_matrix((signs.ravel(), cols.ravel(),
                                    np.arange(0, cols.size + 1, z)),
                                   shape=(r1 - r0, s)).T.tocsr()


def psi_times(q: np.ndarray, seed: int, s: int) -> np.ndarray:
    """``Psi q`` (float64) for the co-range test matrix of :func:`co_range_test`, by groups."""
    out = np.zeros((s, q.shape[1]))
    for r0 in range(0, q.shape[0], PSI_GROUP):
        r1 = min(r0 + PSI_GROUP, q.shape[0])
        out += co_range_test(seed, s, r0, r1).astype(np.float64) @ q[r0:r1]
    return out


class TileSketch:
    """One texel tile's share of a one-view sketch, accumulated row block by row block.

    ``add(row0, a)`` takes the tile's range-reduced rows ``row0 : row0 + len(a)`` (float32);
    ``sums()`` gives the tile's ``y = A_t Omega_t`` (unless the range is exact),
    ``z = A_t Phi_t``, and ``g = W_t W_t^T`` and ``wphi = W_t Phi_t`` of its co-range sketch
    ``w = W_t = Psi A_t`` (float32, ``s x texels``), which the caller keeps (stores) as it is.
    ``Omega_t`` (sparse signs, :func:`sign_map`) and ``Phi_t`` (Gaussian, as the error
    estimate needs: :func:`tile_test_matrix`) come from ``seed`` and the tile's ``key``,
    ``Psi``'s columns from ``seed`` and the rows (:func:`co_range_rows`).
    """

    def __init__(self, sketch: Sketch, seed: int, key: tuple[int, ...], texels: int):
        self.sketch, self.seed = sketch, seed
        self.omega = None if sketch.exact_range else sign_map(seed, 1, key, texels, sketch.k)
        self.phi = tile_test_matrix(seed, 2, key, texels, sketch.t)
        # float32 (summed over tiles in float64): rows x k is the one sum that grows with rows
        self.y = None if self.omega is None else np.zeros((sketch.rows, sketch.k), np.float32)
        self.z = np.zeros((sketch.rows, sketch.t))
        self.w = np.zeros((sketch.s, texels), np.float32)

    def add(self, row0: int, a: np.ndarray) -> None:
        """Add the rows ``row0 : row0 + len(a)`` of the tile (each row once).

        The sparse products are :mod:`tasks.sketch_kernel`'s fixed-order loops (the same bits
        on every scheduler): ``y``'s rows summed in float64, ``w`` in float32 as it is stored.
        Exact sketches (few rows) need neither, nor numba (about 50 MB of memory).
        """
        a = blas_ready(a)
        rows = slice(row0, row0 + a.shape[0])
        if self.omega is not None:
            from tasks.sketch_kernel import add_sign_columns

            add_sign_columns(a, *self.omega, self.y[rows])
        self.z[rows] = project(a, self.phi)
        if self.sketch.exact_co_range:
            self.w[rows] = a
        else:
            from tasks.sketch_kernel import add_sign_rows

            add_sign_rows(a, *co_range_rows(self.seed, self.sketch.s, rows.start, rows.stop),
                          self.w)

    def sums(self) -> dict[str, np.ndarray]:
        """The tile's sums of the pass (see the class)."""
        gram, w_phi = co_range_sums(self.w, self.phi)
        return {"z": self.z, "g": gram, "wphi": w_phi} | ({} if self.y is None
                                                         else {"y": self.y})


GRAM_RUN = 2048  # texels of a co-range sketch converted to float64 at once (cache-sized)


def co_range_sums(w: np.ndarray, phi: np.ndarray, *, tile: int = GRAM_RUN
                  ) -> tuple[np.ndarray, np.ndarray]:
    """``w w^T`` and ``w phi`` (float64) of a tile's stored co-range sketch ``w`` (float32).

    ``w`` is ``s x texels``, ``phi`` the tile's rows of the error test matrix. The products are
    float64 (over runs of ``tile`` texels, to bound the copies), so the Gram matrix is that of
    the stored values to float64 precision, and the eigentextures made from the same values
    come out orthonormal. A run's float64 copy keeps ``w``'s row order and goes to BLAS's
    ``dsyrk`` as the transpose it is (a Fortran copy cost as much as the product, 0.19 s per
    16384 texels at s = 771).
    """
    from scipy.linalg.blas import dsyrk

    gram = np.zeros((w.shape[0],) * 2)
    w_phi = np.zeros((w.shape[0], phi.shape[1]))
    for t in range(0, w.shape[1], tile):
        part = np.array(w[:, t : t + tile], np.float64)  # s x run, C order
        gram = dsyrk(1.0, part.T, beta=1.0, c=gram, trans=1, overwrite_c=True)
        w_phi += part @ np.asarray(phi[t : t + tile], np.float64)
    return np.triu(gram) + np.triu(gram, 1).T, w_phi


def factors_from_co_range(y: np.ndarray | None, gram: np.ndarray, psi_q, rank: int
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``U``, ``S`` and the map ``N`` to ``V = W^T N`` of a one-view sketch (Tropp et al. 2017).

    ``y = A Omega`` (``m x k``; None: ``Q = I``), ``gram = W W^T`` of the co-range sketch
    ``W = Psi A`` (``s x n``), ``psi_q(q)`` gives ``Psi Q``. With ``Psi Q = Q_c R_c``, the core
    ``X = M W`` with ``M = R_c^-1 Q_c^T`` gives ``A ~ Q X``; the eigenvectors ``P`` of
    ``X X^T = M gram M^T`` give ``U = Q P``, ``S = sqrt(lambda)`` and ``V = X^T P / S`` (Alg. 7's
    SVD of ``X``, from its Gram matrix: ``W`` never leaves the tiles). Directions below
    :data:`GRAM_FLOOR` of the largest are left out as in :func:`factors_from_gram`.
    """
    if y is None:  # an exact range: Q = I, and then the co-range is exact too (Sketch)
        q = np.eye(gram.shape[0])
    else:
        q = orthonormalize(y)
    if q.shape[1] < rank:
        raise ValueError(f"a range sketch of {q.shape[1]} columns cannot give rank {rank}")
    qc, rc = np.linalg.qr(psi_q(q))
    m = np.linalg.solve(rc, qc.T)
    g = m @ np.asarray(gram, np.float64) @ m.T
    evals, p, kept = (x[..., :rank] for x in gram_eigen((g + g.T) / 2))
    s = np.where(kept, np.sqrt(np.maximum(evals, 0.0)), 0.0)
    to_v = np.zeros((m.shape[1], rank))
    to_v[:, kept] = m.T @ p[:, kept] / s[kept]
    return q @ p, s, to_v


def estimated_error(z_phi: np.ndarray, vt_phi: np.ndarray, t: int, u, s,
                    frobenius2: float) -> float:
    """Relative Frobenius error estimated from an error sketch ``z_phi = A phi`` (t columns).

    ``vt_phi = V^T phi``: ``E ||(A - U S V^T) Phi||_F^2 / t = ||A - U S V^T||_F^2`` for a
    Gaussian ``Phi`` (Tropp et al. 2017, section 6).
    """
    if frobenius2 <= 0:
        return 0.0
    residual = z_phi - u @ (s[:, None] * vt_phi)
    return float(np.sqrt(np.sum(residual**2) / t / frobenius2))




def reconstruct(u: np.ndarray, s: np.ndarray, v: np.ndarray, *, transform: Transform,
                scale: np.ndarray | None = None) -> np.ndarray:
    """Radiance (float32) of ``u`` rows and ``v`` texels: ``transform`` of ``u diag(s) v^T``.

    Rows run over (layer, channel) with the channel fastest (:func:`matrix_rows`); the log
    transform rebuilds ``max(exp(u diag(s) v^T) - eps, 0)``. Radiance was non-negative (or
    clamped to be) before compression, so the small negatives that approximation error would
    give are set to 0 (:meth:`tasks.transform.Transform.decode`). ``scale``, one number per
    row, multiplies the decoded rows (a cosine store's :meth:`~tasks.transform.Transform.
    layer_scale`, repeated over each layer's channels).
    """
    values = (blas_ready(u) * np.asarray(s, np.float32)) @ blas_ready(v).T
    radiance = transform.decode_rows(values)
    if scale is not None:
        radiance *= np.asarray(scale, np.float32).reshape(-1, 1)
    return radiance


FUSED_DECODE = 1 << 16  # values from which reconstruct_layers decodes in compiled code


def reconstruct_layers(u: np.ndarray, s: np.ndarray, v: np.ndarray, *, transform: Transform,
                       scale: np.ndarray | None = None) -> np.ndarray:
    """Radiance layers ``(..., y, x, channel)`` rebuilt from factors.

    ``u`` holds eigen-ABRDF rows ``(..., channel, k)``, ``v`` an eigentexture tile
    ``(y, x, k)``: the result is what the corresponding radiance block held. ``scale`` (shape
    ``u.shape[:-2]``, one number per layer) multiplies each layer (a cosine store's
    :meth:`~tasks.transform.Transform.layer_scale`).
    """
    u = np.asarray(u)
    lead, nc, k = u.shape[:-2], u.shape[-2], u.shape[-1]
    ny, nx = v.shape[:2]
    layers = int(np.prod(lead, dtype=np.int64))
    if layers * nc * ny * nx >= FUSED_DECODE and (transform.channels or nc) == nc:
        # the product, then the transform and the move of the channels last in one compiled
        # pass (:func:`tasks.dfmf_kernel.decode_layers`): numpy's steps took 2.4 of a
        # block's 3.3 ms (48 rows of 4,096 texels, a YUV model)
        from tasks.dfmf_kernel import CODES, decode_layers

        values = (blas_ready(u.reshape(-1, k)) * np.asarray(s, np.float32)) @ blas_ready(
            np.asarray(v).reshape(ny * nx, k)).T
        out = np.empty((layers, ny * nx, nc), np.float32)
        factor = (np.ones(layers, np.float32) if scale is None else
                  np.broadcast_to(np.asarray(scale, np.float32), lead).reshape(-1).copy())
        decode_layers(values.reshape(layers, nc, ny * nx), out, CODES[transform.name],
                      transform.eps, factor)
        return out.reshape(*lead, ny, nx, nc)
    rows = None if scale is None else np.repeat(
        np.broadcast_to(np.asarray(scale, np.float32), lead).reshape(-1), nc)
    flat = reconstruct(u.reshape(-1, k), s, np.asarray(v).reshape(ny * nx, k),
                       transform=transform, scale=rows)
    return np.moveaxis(flat.reshape(*lead, nc, ny, nx), -3, -1)


def reconstruct_pieces(u: np.ndarray, s: np.ndarray, v: np.ndarray, *, transform: Transform,
                       cuts: tuple[list[tuple[int, int]], ...],
                       scale: np.ndarray | None = None) -> np.ndarray:
    """A block of radiance ``(view, light, y, x, channel)`` rebuilt piece by piece.

    ``u`` ``(view, light, channel, k)`` and ``v`` ``(y, x, k)`` are the block's factors;
    ``cuts`` the pieces' ``(start, stop)`` along view, light, y and x. Each piece is
    :func:`reconstruct_layers` of its own rows of ``u`` and tile of ``v``, written into the
    block: the same bits as rebuilding each piece alone and concatenating them (a product's
    last bit depends on its shape), without the copy of the concatenation.
    """
    out = np.empty((u.shape[0], u.shape[1], v.shape[0], v.shape[1], u.shape[2]), np.float32)
    for (a0, a1), (b0, b1) in itertools.product(cuts[0], cuts[1]):
        rows = u[a0:a1, b0:b1]
        layer_scale = None if scale is None else scale[a0:a1, b0:b1]
        for (y0, y1), (x0, x1) in itertools.product(cuts[2], cuts[3]):
            out[a0:a1, b0:b1, y0:y1, x0:x1] = reconstruct_layers(
                rows, s, v[y0:y1, x0:x1], transform=transform, scale=layer_scale)
    return out


def squared_errors(original: np.ndarray, approx: np.ndarray, *, tile: int = TILE
                   ) -> np.ndarray:
    """Per-column sums of squared differences of two float32 row blocks (float64 result).

    Differences are taken in float32 tile by tile (no float64 copies of the blocks).
    """
    out = np.empty(original.shape[1], np.float64)
    for t in range(0, original.shape[1], tile):
        d = np.subtract(original[:, t : t + tile], approx[:, t : t + tile], dtype=np.float32)
        out[t : t + tile] = np.einsum("ij,ij->j", d, d, dtype=np.float64)
    return out


def verification(raw: np.ndarray, log_rows_: np.ndarray, u: np.ndarray, s: np.ndarray,
                 v: np.ndarray, *, eps: float, tile: int = TILE) -> tuple[np.ndarray, float]:
    """Errors of a factorization on one row block, measured directly, tile by tile.

    ``raw`` are the block's radiance rows (clamped if compression clamped them), ``log_rows_``
    their range reduction, ``u`` the block's rows of ``U``. Returns the per-texel sums of
    squared linear-radiance differences (for eq. 11) and the block's squared log-domain
    residual ``||A_i - U_i S V^T||_F^2`` (float64).
    """
    linear = np.empty(raw.shape[1], np.float64)
    log_residual = 0.0
    us = blas_ready(u) * np.asarray(s, np.float32)
    v = blas_ready(v)
    for t in range(0, raw.shape[1], tile):
        approx_log = us @ v[t : t + tile].T
        d = np.subtract(log_rows_[:, t : t + tile], approx_log, dtype=np.float32)
        log_residual += float(np.einsum("ij,ij->", d, d, dtype=np.float64))
        np.minimum(approx_log, np.float32(LOG_MAX), out=approx_log)
        approx = np.exp(approx_log, out=approx_log)
        approx -= np.float32(eps)
        np.maximum(approx, 0.0, out=approx)
        linear[t : t + tile] = squared_errors(raw[:, t : t + tile], approx)
    return linear, log_residual


@dataclass
class PassPart:
    """What one row block contributes to a pass, in the chunk / combine / aggregate shape.

    ``sums`` are added over row blocks (float64 sketches such as ``sum_i A_i^T A_i X``),
    ``rows`` are row-block pieces kept with their first matrix row (such as ``A_i X``),
    ``check`` and ``frobenius2`` describe the data read.
    """

    sums: dict[str, np.ndarray]
    rows: dict[str, list[tuple[int, np.ndarray]]]
    check: BlockCheck
    frobenius2: float

    @property
    def nbytes(self) -> int:
        """Bytes of its arrays."""
        return (sum(a.nbytes for a in self.sums.values())
                + sum(piece.nbytes for pieces in self.rows.values() for _, piece in pieces))


def combine_parts(*parts: PassPart) -> PassPart:
    """Merge pass parts (in the given order, so the float sums are reproducible).

    Sums are accumulated in float64 whatever the parts hold.
    """
    first = parts[0]
    sums = {name: first.sums[name].astype(np.float64) for name in first.sums}
    rows = {name: list(first.rows[name]) for name in first.rows}
    check, frobenius2 = first.check, first.frobenius2
    for part in parts[1:]:
        for name in sums:
            sums[name] += part.sums[name]
        for name in rows:
            rows[name] += part.rows[name]
        check = check.merge(part.check)
        frobenius2 += part.frobenius2
    return PassPart(sums, rows, check, frobenius2)


def stacked_rows(pieces: list[tuple[int, np.ndarray]]) -> np.ndarray:
    """Row-block pieces stacked in row order into one matrix."""
    return np.concatenate([p for _, p in sorted(pieces, key=lambda rp: rp[0])], axis=0)


def refactor(u: np.ndarray, coefficients: np.ndarray) -> tuple[np.ndarray, np.ndarray,
                                                              np.ndarray, np.ndarray]:
    """``U, S, V`` with orthonormal ``U``, ``V`` and decreasing ``S`` of ``u @ coefficients^T``.

    ``u`` is an orthonormal basis ``(rows, K)`` and ``coefficients`` ``(texels, K)`` the
    columns of ``S V^T`` in it (the output of BTF enlargement). With the thin SVD
    ``coefficients = V' diag(s) W^T``: ``U = u W``, ``S = s``, ``V = V'`` (float64). The
    product, hence every layer, is unchanged; only the factorisation is made canonical.
    Also returns ``W`` (``K x K``): other coefficients ``c`` in ``u``'s basis are ``c W`` in
    the new one.
    """
    c = np.asarray(coefficients, np.float64)
    new_u, s, w = refactor_gram(u, c.T @ c)
    v = c @ w
    kept = s > (s[0] * 1e-12 if s.size else 0.0)  # components the coefficients do not use: 0
    v[:, kept] /= s[kept]
    v[:, ~kept] = 0.0
    return new_u, s, v, w


def refactor_gram(u: np.ndarray, gram: np.ndarray) -> tuple[np.ndarray, np.ndarray,
                                                            np.ndarray]:
    """:func:`refactor` from the coefficients' Gram matrix ``C^T C`` (a sum over tiles).

    Returns ``U = u W``, ``S`` and ``W``; the caller computes ``V = C W / S`` tile by tile.
    """
    evals, w = np.linalg.eigh(np.asarray(gram, np.float64))
    order = np.argsort(evals)[::-1]
    s = np.sqrt(np.maximum(evals[order], 0.0))
    w = w[:, order]
    return np.asarray(u, np.float64) @ w, s, w


def projected_level(v: np.ndarray, *, u: np.ndarray, s: np.ndarray, factor: int,
                    transform: Transform, budget: int = 64 << 20) -> np.ndarray:
    """Eigentextures of a level of detail: block-mean radiance, back in the basis ``U``.

    ``v`` is a level-0 tile ``(y, x, k)`` whose sides are multiples of ``factor``. Its radiance
    (:func:`reconstruct`, as many rows of ``U`` at a time as fit ``budget`` bytes, whole
    layers of channels) is averaged over ``factor x factor`` blocks in linear radiance,
    range-reduced again (``transform.encode``) and projected on the orthonormal ``U``:
    ``V = encode(mean) U / S``, the level's best approximation with the same ``U`` and ``S``
    in the value domain. (For the log transform, the block mean of ``V`` itself would be the
    geometric mean of ``radiance + eps``.) Components with ``S = 0`` get 0.
    """
    ty, tx, k = v.shape
    oy, ox = ty // factor, tx // factor
    texels = np.ascontiguousarray(v, np.float32).reshape(ty * tx, k)
    c = np.zeros((oy * ox, k))
    group = transform.channels or 1
    rows = max(1, budget // (ty * tx * 4) // group) * group
    for r0 in range(0, u.shape[0], rows):
        ur = np.asarray(u[r0 : r0 + rows], np.float32)
        radiance = reconstruct(ur, s, texels, transform=transform)  # (rows, texels) float32
        means = radiance.reshape(-1, oy, factor, ox, factor).mean(axis=(2, 4),
                                                                  dtype=np.float64)
        c += transform.encode_rows(means.reshape(len(ur), -1)).T @ ur.astype(np.float64)
    s = np.asarray(s, np.float64)
    out = np.zeros_like(c)
    kept = s > 0
    out[:, kept] = c[:, kept] / s[kept]
    return out.reshape(oy, ox, k).astype(np.float32)

"""The per-texel quadratic programme of BTF enlargement (paper 000, eqs. 4-6).

For every texel ``p``, with ``b1`` its eigentexture coefficients before and ``b2`` after
statistical synthesis::

    minimise  alpha ||x - b1||^2 + beta ||x - b2||^2   subject to   A x = b

``A`` holds the rows of the sample's basis ``U_S`` that belong to the constraint images (``x``
is a column of ``Sigma V^T``), ``b`` the texel's constraint values in the log domain. The
objective is ``(alpha + beta) ||x - m||^2 + const`` with ``m = (alpha b1 + beta b2) /
(alpha + beta)``, so the solution is the orthogonal projection of ``m`` onto ``{x : A x = b}``::

    x = m + A^+ (b - A m)

``A`` is shared by all texels: one SVD ``A = P diag(s) Q^T`` serves them all, and the
correction of every texel is ``Q diag(1/s) P^T (b - A m)``. Singular values below ``rcond``
times the largest are dropped (a rank-deficient ``A``: two constraint images of the same
direction). With more rows than components, or inconsistent rows, ``A x = b`` has no exact
solution and the same formula gives the least-squares one closest to ``m``.

**Damping.** The constraint values are photos, the rows are the sample's compressed basis: even
the true texel misses ``A x = b`` by the compression error of those layers. Enforcing them
exactly divides that error by the smallest singular values of ``A``, which can be tiny (a
photo's colour direction that the sample's first components barely use), and moves ``x`` far
from ``m`` in every other direction. :meth:`ConstraintProjector.project` therefore takes a
damping ``delta`` (Tikhonov: the correction becomes ``Q diag(s / (s^2 + delta)) P^T``, the
minimiser of ``||x - m||^2 + ||A x - b||^2 / delta``), and :meth:`ConstraintProjector.damping`
picks the smallest ``delta`` that leaves an RMS residual equal to a given noise level (the
discrepancy principle): the constraints are met to within the sample's own compression error.
``delta = 0`` is the exact QP.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

RCOND = 1e-6  # relative singular value below which constraint directions are dropped


@dataclass(frozen=True)
class ConstraintProjector:
    """The projection onto ``{x : A x = b}`` for one constraint matrix ``A`` (rows x K)."""

    a: np.ndarray  # (rows, K) float64
    p: np.ndarray  # (rows, r): left singular vectors kept
    s: np.ndarray  # (r,): singular values kept
    qt: np.ndarray  # (r, K): right singular vectors kept

    @staticmethod
    def of(a: np.ndarray, *, rcond: float = RCOND) -> ConstraintProjector:
        """Factorise ``A`` once (SVD) for every texel's projection."""
        a = np.atleast_2d(np.asarray(a, np.float64))
        p, s, qt = np.linalg.svd(a, full_matrices=False)
        kept = s > rcond * s[0] if s.size and s[0] > 0 else np.zeros(s.shape, bool)
        return ConstraintProjector(a, p[:, kept], s[kept], qt[kept])

    @property
    def rank(self) -> int:
        """Constraint directions kept."""
        return int(self.s.size)

    def project(self, m: np.ndarray, b: np.ndarray, *, damping: float = 0.0) -> np.ndarray:
        """``m`` moved towards ``A x = b``, for texels on the leading axes (float64).

        ``m`` is ``(..., K)``, ``b`` ``(..., rows)``; ``damping = 0``: exactly onto it.
        """
        m = np.asarray(m, np.float64)
        residual = np.asarray(b, np.float64) - m @ self.a.T
        gain = self.s / (self.s**2 + damping)
        return m + ((residual @ self.p) * gain) @ self.qt

    def damping(self, m: np.ndarray, b: np.ndarray, noise: float) -> float:
        """The smallest damping whose projection leaves an RMS residual of ``noise``.

        0 if the exact projection already does (its residual is what ``A`` cannot reach).
        """
        residual = (np.asarray(b, np.float64) - np.asarray(m, np.float64) @ self.a.T)
        residual = residual.reshape(-1, self.a.shape[0])
        along = residual @ self.p  # components in the range of A, which the projection removes
        total = float(np.sum(residual**2))
        outside = max(total - float(np.sum(along**2)), 0.0)
        power = np.sum(along**2, axis=0)  # per singular direction
        values = residual.size

        def rms(delta: float) -> float:
            kept = (delta / (self.s**2 + delta)) ** 2
            return float(np.sqrt((np.sum(kept * power) + outside) / values))

        if noise <= rms(0.0) or self.rank == 0:
            return 0.0
        if noise >= np.sqrt(total / values):
            return float("inf")
        lo, hi = 1e-12 * self.s[0] ** 2, 1e12 * self.s[0] ** 2
        for _ in range(100):  # bisection on a log scale: rms grows with the damping
            mid = np.sqrt(lo * hi)
            lo, hi = (mid, hi) if rms(mid) < noise else (lo, mid)
        return float(np.sqrt(lo * hi))

    def residual(self, x: np.ndarray, b: np.ndarray) -> float:
        """Relative constraint residual ``||A x - b|| / ||b||`` over all texels."""
        x = np.asarray(x, np.float64)
        b = np.asarray(b, np.float64)
        norm = np.linalg.norm(b)
        return float(np.linalg.norm(x @ self.a.T - b) / norm) if norm else 0.0

    def rms_residual(self, x: np.ndarray, b: np.ndarray) -> float:
        """RMS of ``A x - b`` over all texels and constraint values."""
        d = np.asarray(x, np.float64) @ self.a.T - np.asarray(b, np.float64)
        return float(np.sqrt(np.mean(d**2)))


def blend(b1: np.ndarray, b2: np.ndarray, b: np.ndarray, projector: ConstraintProjector, *,
          alpha: float = 1.0, beta: float = 1.0, noise: float = 0.0) -> tuple[np.ndarray, float]:
    """Solve the per-texel QP for all texels at once; returns the result (float32) and damping.

    ``b1``, ``b2`` are ``(..., K)`` coefficients before and after statistical synthesis, ``b``
    the ``(..., rows)`` constraint values; ``noise``: the RMS constraint residual to leave
    (0: the exact QP; see the module).
    """
    if not (alpha >= 0 and beta >= 0 and alpha + beta > 0):
        raise ValueError(f"alpha and beta must be non-negative, not both 0: {alpha}, {beta}")
    m = (alpha * np.asarray(b1, np.float64) + beta * np.asarray(b2, np.float64)) / (alpha + beta)
    damping = projector.damping(m, b, noise) if noise > 0 else 0.0
    if not np.isfinite(damping):  # the noise level is above the whole residual: leave m
        return m.astype(np.float32), damping
    return projector.project(m, b, damping=damping).astype(np.float32), damping

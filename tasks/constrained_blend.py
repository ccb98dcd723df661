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

**Metric** (an extension of the paper's QP, issue 57). The paper measures ``||x - m||`` in
plain coefficients, so the correction that meets a photo is the shortest one: it changes the
ABRDF mostly in the photo's own layer. A texel that is brighter in a top-light photo than
``m`` is, on real surfaces, mostly a texel of higher albedo or a flatter slope, which changes
every layer alike; the sample shows which. :meth:`ConstraintProjector.of` with ``metric =
Sigma`` (:func:`sample_covariance`, the covariance of the sample's coefficients over its
texels) measures ``(x - m)^T Sigma^-1 (x - m)`` instead: the correction goes along the
directions in which the sample's texels vary together, the most likely explanation of the
photos under a Gaussian model of the sample's texels (the projection is then the
conditional mean given the photos, with the damping as the photos' noise). With ``Sigma = L
L^T`` this is the plain QP in ``y = L^-1 x`` with rows ``A L``, mapped back by ``L``. Its
damping is the conditional mean's (:meth:`ConstraintProjector.prior_damping`), the prior's
scale estimated from how far the photos are from ``m``. :func:`blend` takes that step within
a trust region and lets the plain QP (the discrepancy principle's damping) meet what the
photos still ask (:func:`_metric_blend`), so the result is the conditional mean only where
the step is short.
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
    qt: np.ndarray  # (r, K): the corrections' directions in x (right singular vectors kept,
    # mapped back by L^T under a metric)
    whiten: np.ndarray | None = None  # (K, K) L^-1 under a metric Sigma = L L^T, else None
    plain: ConstraintProjector | None = None  # the same rows without the metric (under one)

    @property
    def whitened(self) -> bool:
        """Whether ``x - m`` is measured in a covariance metric (see the module)."""
        return self.whiten is not None

    @staticmethod
    def of(a: np.ndarray, *, rcond: float = RCOND,
           metric: np.ndarray | None = None) -> ConstraintProjector:
        """Factorise ``A`` once (SVD) for every texel's projection.

        ``metric``: a ``(K, K)`` symmetric positive definite ``Sigma`` in which ``x - m`` is
        measured as ``(x - m)^T Sigma^-1 (x - m)`` (see the module); None: plain.
        """
        a = np.atleast_2d(np.asarray(a, np.float64))
        factor = None if metric is None else np.linalg.cholesky(np.asarray(metric, np.float64))
        p, s, qt = np.linalg.svd(a if factor is None else a @ factor, full_matrices=False)
        kept = s > rcond * s[0] if s.size and s[0] > 0 else np.zeros(s.shape, bool)
        if factor is None:
            return ConstraintProjector(a, p[:, kept], s[kept], qt[kept])
        return ConstraintProjector(a, p[:, kept], s[kept], qt[kept] @ factor.T,
                                   np.linalg.inv(factor), ConstraintProjector.of(a, rcond=rcond))

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

    def prior_damping(self, m: np.ndarray, b: np.ndarray, noise: float) -> float:
        """The damping of the conditional mean when ``x - m`` is drawn from ``c Sigma``.

        With ``x = m + e``, ``e ~ N(0, c Sigma)`` and photos ``b = A x + n``, ``n ~ N(0,
        noise^2)``, the residual ``r = b - A m`` has ``E |r|^2 = c tr(A Sigma A^T) + rows
        noise^2``; ``c`` is estimated from the texels' mean ``|r|^2`` (the method of moments),
        and the conditional mean of ``x`` is the projection damped by ``noise^2 / c``. Inf
        (no correction) when the residual is no larger than the noise alone. The metric's
        ``Sigma`` says in which directions ``m`` is wrong; ``c`` how far, from the photos.
        """
        residual = (np.asarray(b, np.float64) - np.asarray(m, np.float64) @ self.a.T)
        residual = residual.reshape(-1, self.a.shape[0])
        spread = float(np.sum(self.s**2))  # tr(A Sigma A^T) over the kept directions
        excess = float(np.mean(np.sum(residual**2, axis=1))) - residual.shape[1] * noise**2
        if excess <= 0 or spread <= 0:
            return float("inf")
        return noise**2 / (excess / spread)

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


METRIC_RIDGE = 1e-6  # of the mean variance, added to a sample's covariance (a constant channel)
# The metric step's trust region, in median step lengths (of one call's texels). Measured with
# `btf bench enlarge` (BENCHMARKS.md, issue 57): without it, texels far from the photos took
# values under grazing lights beyond any of the truth's (generated fabric, ten photos:
# realism 1.46 -> 6.34 while the error fell 0.0130 -> 0.0116); at 1.5 realism was 1.85 and
# the error 0.0108, at 1 realism 1.54 and the error 0.0110.
TRUST = 1.0


def sample_covariance(coefficients: np.ndarray) -> np.ndarray:
    """The ``(K, K)`` covariance of a sample's coefficients over its texels, for ``metric``.

    A ridge of :data:`METRIC_RIDGE` times the mean variance keeps it positive definite when a
    channel hardly varies.
    """
    coefficients = np.asarray(coefficients, np.float64)
    flat = coefficients.reshape(-1, coefficients.shape[-1])
    cov = np.atleast_2d(np.cov(flat, rowvar=False)) if len(flat) > 1 else np.zeros(
        (flat.shape[1],) * 2)
    ridge = METRIC_RIDGE * max(float(np.trace(cov)) / len(cov), 1e-30)
    return cov + ridge * np.eye(len(cov))


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
    if projector.whitened:
        return _metric_blend(m, b, projector, noise)
    damping = projector.damping(m, b, noise) if noise > 0 else 0.0
    if not np.isfinite(damping):  # the noise level is above the whole residual: leave m
        return m.astype(np.float32), damping
    return projector.project(m, b, damping=damping).astype(np.float32), damping


def _metric_blend(m: np.ndarray, b: np.ndarray, projector: ConstraintProjector,
                  noise: float) -> tuple[np.ndarray, float]:
    """The QP in the projector's metric, within a trust region, then the plain QP for the rest.

    The conditional mean is a linear model of how texels vary, fitted to the whole sample; far
    from ``m`` it is wrong (a texel whose synthesis disagrees with the photos by much more than
    most, e.g. a thread synthesized half a thread off, would take values under unseen lights
    that no texel of the sample has). Its step is therefore kept within :data:`TRUST` times
    the median step length (in the metric) of this call's texels, and what the photos still
    ask after that is met by the plain QP (the discrepancy principle's damping as without a
    metric; exactly for ``noise = 0``). Returns the result and the metric step's damping.
    """
    damping = projector.prior_damping(m, b, noise) if noise > 0 else 0.0
    if not np.isfinite(damping):  # the photos are within their noise of m: leave it
        return m.astype(np.float32), damping
    step = (projector.project(m, b, damping=damping) - m).reshape(-1, m.shape[-1])
    length = np.linalg.norm(step @ projector.whiten.T, axis=1)
    limit = TRUST * float(np.median(length))  # 0 when most texels need no step: none do
    step *= np.minimum(1.0, limit / np.maximum(length, 1e-300))[:, None]
    x = m + step.reshape(m.shape)
    rest = projector.plain
    rest_damping = rest.damping(x, b, noise) if noise > 0 else 0.0
    if np.isfinite(rest_damping):
        x = rest.project(x, b, damping=rest_damping)
    return x.astype(np.float32), damping

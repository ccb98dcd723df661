"""A texel's coefficients predicted from its photo values: local linear regression on the sample.

Texture Optimization (paper 000, section 3.1) composes the result from the sample's texels, so
at best each texel copies one the photos cannot tell from it, and the M-step averages the
copies that fit. Where several photos under different lights pin down what varies between
texels (slope, albedo, a shadow's depth), the expected value of a texel's coefficients given
its photo values, ``E[x | b]``, is a better estimate of its ABRDF than any one copy: under the
lights the photos did not see, a copy's errors are those of a draw from the texels that fit,
the expectation's are not.

:func:`local_regression` estimates ``E[x | b]`` from the sample alone, where both are known:
for each target texel, the ``neighbours`` sample texels nearest in photo values, and a linear
fit of their coefficients on their photo values (ridge-regularised relative to the
neighbourhood's spread), evaluated at the texel's own values. It extends the paper's QP, whose
sample metric (:func:`tasks.constrained_blend.sample_covariance`) is the same regression fitted
once to the whole sample and applied as a correction of Texture Optimization's result; here it
is local and gives the estimate itself. :func:`tasks.enlargement.enlarge` moves each texel of
the rounds' result a share of the way to it and applies the QP again; the share is
``--regress`` times how much of the neighbours' variation the fit explains (its adjusted
R^2): where the photos tell the texels apart (a stone's slopes under ten lights) the texel
goes most of the way, where they do not (a wood's grain, which its neighbourhood tells) it
stays with Texture Optimization's result.

A linear fit extrapolates: where a texel's neighbours differ little in photo values and much in
coefficients, its estimate can leave what the sample holds, and under a light the photos did
not see it decodes darker (or brighter) than any texel of the sample. A few such texels, a
thousandth of a fabric's, are black specks in the result that no texture statistics allow (its
minimum). :class:`ValueRange` bounds the move: it stops, texel by texel, where any of the
sample's layers (rows of ``U_S``; :func:`range_rows`) would leave the range the sample's own
texels span in it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

NEIGHBOURS = 64  # sample texels each fit uses (at least 2 per photo value)
RIDGE = 0.03  # ridge, relative to the mean variance of the neighbours' photo values
TRUST = 2.0  # the most a fit's step may be, in multiples of its neighbours' spread
SEARCH_ENERGY = 0.999  # share of the sample's photo-value variance the neighbour search keeps
CHUNK = 512  # target texels per batch: their neighbours' values, a few MB for ten photos
RANGE_ROWS = 1536  # most rows of U_S whose values bound the move (512 directions of RGB)
RANGE_CHUNK = 1024  # texels per product when a move is checked: ~40 MB at 1536 rows


def local_regression(sample: np.ndarray, sample_values: np.ndarray, target_values: np.ndarray,
                     *, neighbours: int = NEIGHBOURS, ridge: float = RIDGE
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Each target texel's coefficients from a linear fit of its photo-value neighbours.

    Parameters
    ----------
    sample, sample_values
        ``(h, w, K)`` coefficients of the sample and ``(h, w, G)`` its photo values (log
        domain, as :func:`tasks.enlargement.enlarge` takes them).
    target_values
        ``(H, W, G)`` photo values of the target.
    neighbours
        Sample texels per fit (at least ``2 G``, at most the sample's texel count; found a
        chunk of target texels at a time, so memory is bounded by :data:`CHUNK`), the
        nearest in the leading principal components of the sample's photo values (those
        holding :data:`SEARCH_ENERGY` of their variance).
    ridge
        Weight of the ridge term, relative to the mean variance of the neighbours' values.

    Returns the estimate ``(H, W, K)`` float32 and how much of its neighbours' variation each
    fit explains, ``(H, W)`` float32 in [0, 1]: the adjusted R^2, ``1 - (RSS / (n - G - 1)) /
    (TSS / (n - 1))`` over its ``n`` neighbours' coefficients, clipped (0 where ``n <= G + 1``,
    too few neighbours to tell, and where the neighbours' coefficients are all the same).
    Deterministic: the same inputs give the same bits.
    """
    from scipy.spatial import cKDTree

    k = sample.shape[-1]
    g = sample_values.shape[-1]
    coefficients = np.asarray(sample, np.float32).reshape(-1, k)
    keys = np.asarray(sample_values, np.float32).reshape(-1, g)
    wanted = np.asarray(target_values, np.float32).reshape(-1, g)
    count = int(min(max(neighbours, 2 * g), len(keys)))
    # neighbours found among the leading principal components of the sample's values
    # (photos of one texture under several lights vary together): the k-d tree's search
    # in 30 dimensions was most of the time
    mean = keys.mean(axis=0)
    _, singular, axes = np.linalg.svd(keys - mean, full_matrices=False)
    energy = np.cumsum(singular.astype(np.float64) ** 2)
    kept = int(np.searchsorted(energy, SEARCH_ENERGY * energy[-1]) + 1) if energy[-1] > 0 else 1
    basis = axes[: min(kept, g)].T
    tree = cKDTree((keys - mean) @ basis)
    out = np.empty((len(wanted), k), np.float32)
    explained = np.zeros(len(wanted), np.float32)
    eye = np.eye(g)
    floor = np.finfo(np.float64).tiny / np.finfo(np.float64).eps
    for start in range(0, len(wanted), CHUNK):
        _, index = tree.query((wanted[start : start + CHUNK] - mean) @ basis, k=count)
        index = index.reshape(-1, count)
        a, y = keys[index], coefficients[index]  # (n, count, G), (n, count, K)
        a_mean, y_mean = a.mean(axis=1), y.mean(axis=1)
        a -= a_mean[:, None]
        y -= y_mean[:, None]
        at = a.transpose(0, 2, 1)
        gram = (at @ a).astype(np.float64)
        scale = np.trace(gram, axis1=1, axis2=2) / g
        # the ridge relative to the spread, with a floor for neighbours all of one value
        gram += (ridge * np.maximum(scale, floor))[:, None, None] * eye
        slope = np.linalg.solve(gram, (at @ y).astype(np.float64))
        step = ((wanted[start : start + CHUNK] - a_mean)[:, None] @ slope)[:, 0]
        # a texel whose values lie far outside its neighbours' would be extrapolated
        # without bound (a wood's one photo: coefficients of 1e9): its step is kept within
        # TRUST times the neighbours' own spread
        spread = np.sqrt(np.mean(np.sum(y.astype(np.float64) ** 2, axis=2), axis=1))
        length = np.linalg.norm(step, axis=1)
        step *= np.minimum(1.0, TRUST * spread / np.maximum(length, floor))[:, None]
        out[start : start + CHUNK] = y_mean + step
        if count > g + 1:
            rss = np.sum((y - a @ slope) ** 2, axis=(1, 2))
            tss = np.sum(y.astype(np.float64) ** 2, axis=(1, 2))
            share = 1 - (rss / (count - g - 1)) / np.maximum(tss / (count - 1), floor)
            # neighbours of one and the same coefficients: nothing to explain (0), whatever
            # their float32 mean's rounding left in the residual
            explained[start : start + CHUNK] = np.where(tss > floor, np.clip(share, 0, 1), 0)
    shape = np.shape(target_values)[:-1]
    return out.reshape(*shape, k), explained.reshape(shape)


def range_rows(basis: np.ndarray, channels: int, most: int = RANGE_ROWS) -> np.ndarray:
    """The rows of ``basis`` (``U_S`` as ``(directions x channels, K)``) that bound the move.

    All of them up to ``most``; beyond, every channel of ``most // channels`` directions evenly
    spaced over the store's order (a dome of 22,801 directions: every 45th), so that checking a
    move costs at most ``most`` values per texel whatever the sampling.
    """
    basis = np.asarray(basis)
    if len(basis) <= most:
        return basis
    directions = len(basis) // channels
    picked = np.unique(np.linspace(0, directions - 1, max(1, most // channels)).astype(int))
    return basis.reshape(directions, channels, -1)[picked].reshape(-1, basis.shape[-1])


@dataclass(frozen=True)
class ValueRange:
    """Per row of ``U_S`` (log domain), the least and greatest value of the sample's texels."""

    rows: np.ndarray  # (R, K) float32
    low: np.ndarray  # (R,) float32
    high: np.ndarray  # (R,) float32

    @classmethod
    def of(cls, sample: np.ndarray, rows: np.ndarray) -> ValueRange:
        """The range of ``sample``'s coefficients ``(h, w, K)`` in ``rows`` ``(R, K)``."""
        rows = np.asarray(rows, np.float32)
        flat = np.asarray(sample, np.float32).reshape(-1, rows.shape[-1])
        low = np.full(len(rows), np.inf, np.float32)
        high = np.full(len(rows), -np.inf, np.float32)
        for start in range(0, len(flat), RANGE_CHUNK):
            values = flat[start : start + RANGE_CHUNK] @ rows.T
            np.minimum(low, values.min(axis=0), out=low)
            np.maximum(high, values.max(axis=0), out=high)
        return cls(rows, low, high)

    def share(self, x: np.ndarray, move: np.ndarray) -> np.ndarray:
        """Per texel, the largest ``t`` in [0, 1] with ``x + t move`` in the range in every row.

        ``x`` and ``move`` are ``(..., K)``; returns ``(...)`` float32. A row where ``x`` itself
        is outside the range bounds the move by ``x``'s value instead (``t = 0`` always fits:
        the move never takes a texel further out than it was).
        """
        k = self.rows.shape[-1]
        flat_x = np.asarray(x, np.float32).reshape(-1, k)
        flat_move = np.asarray(move, np.float32).reshape(-1, k)
        out = np.ones(len(flat_x), np.float32)
        for start in range(0, len(flat_x), RANGE_CHUNK):
            here = flat_x[start : start + RANGE_CHUNK] @ self.rows.T
            step = flat_move[start : start + RANGE_CHUNK] @ self.rows.T
            # room to the edge the step goes toward: negative where the texel is already
            # past it (t < 0, clipped to 0), so it may move back in but not further out
            room = np.where(step < 0, self.low - here, self.high - here)
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                limit = np.where(step != 0, room / step, np.inf)
            out[start : start + RANGE_CHUNK] = np.clip(limit.min(axis=1), 0, 1)
        return out.reshape(np.shape(x)[:-1])

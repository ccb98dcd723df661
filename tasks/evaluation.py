"""Enlargement against ground truth: the error of paper 000's eq. (11) and two baselines.

Pure numpy: the caller reads the stores. Coefficients are per texel, ``S V^T`` in a
compressed store's basis ``U`` (rows in BTF-matrix order: view, light, channel). ``scale``,
where given, is one number per row multiplying the decoded radiance (a cosine store's
:meth:`~tasks.transform.Transform.layer_scale`, repeated over the channels).
"""

from __future__ import annotations

import numpy as np

from tasks.transform import Transform


def abrdf_error(u: np.ndarray, coefficients: np.ndarray, transform: Transform, truth: np.ndarray,
                mask: np.ndarray, scale: np.ndarray | None = None) -> float:
    """Eq. (11) over the masked texels: mean of each texel's RMS radiance error (linear).

    ``u`` ``(rows, K)``; ``coefficients`` ``(H, W, K)``; ``truth`` ``(H, W, rows)`` linear
    radiance in the rows' order; ``mask`` ``(H, W)``: the texels that count.
    """
    return float(np.mean(abrdf_errors(u, coefficients, transform, truth, mask, scale)))


def abrdf_errors(u: np.ndarray, coefficients: np.ndarray, transform: Transform, truth: np.ndarray,
                 mask: np.ndarray, scale: np.ndarray | None = None) -> np.ndarray:
    """Each masked texel's RMS radiance error (see :func:`abrdf_error`), 16384 at a time."""
    from tasks.svd import reconstruct

    texels = coefficients.reshape(-1, coefficients.shape[-1])[mask.ravel()]
    rows = truth.reshape(-1, truth.shape[-1])[mask.ravel()]
    errors = [np.zeros(0)]
    for k in range(0, len(texels), 16384):
        approx = reconstruct(u, np.ones(u.shape[1]), texels[k : k + 16384], transform=transform,
                             scale=scale).T
        errors.append(np.sqrt(np.mean((approx - rows[k : k + 16384]) ** 2, axis=1)))
    return np.concatenate(errors)


def lookup_baseline(sample_coef: np.ndarray, sample_keys: np.ndarray, keys: np.ndarray
                    ) -> np.ndarray:
    """Per-texel lookup: each texel takes the coefficients of the nearest sample texel.

    Nearest by ``keys`` (e.g. log constraint values), with no neighbourhoods:
    ``(h, w, K)``, ``(h, w, C)``, ``(H, W, C)`` -> ``(H, W, K)``.
    """
    from scipy.spatial import cKDTree

    _, index = cKDTree(sample_keys.reshape(-1, sample_keys.shape[-1])).query(
        keys.reshape(-1, keys.shape[-1]))
    flat = sample_coef.reshape(-1, sample_coef.shape[-1])
    return flat[index].reshape(*keys.shape[:2], -1)


def tiling_baseline(sample_coef: np.ndarray, shape: tuple[int, int],
                    origin: tuple[int, int], start: tuple[int, int] = (0, 0)) -> np.ndarray:
    """The sample repeated periodically, aligned with its place ``origin``.

    Returns the ``shape`` window of that tiling whose first texel is ``start``.
    """
    h, w = sample_coef.shape[:2]
    ys = (start[0] + np.arange(shape[0]) - origin[0]) % h
    xs = (start[1] + np.arange(shape[1]) - origin[1]) % w
    return sample_coef[np.ix_(ys, xs)]


def abrdf_index(u: np.ndarray, sample_coef: np.ndarray, transform: Transform,
                scale: np.ndarray | None = None):
    """The exact search index over the sample's ABRDFs in linear radiance (faiss, flat L2).

    It holds ``texels x rows`` float32 values: build it once for many searches.
    """
    import faiss

    from tasks.svd import reconstruct

    flat = sample_coef.reshape(-1, sample_coef.shape[-1])
    sample = np.ascontiguousarray(reconstruct(u, np.ones(u.shape[1]), flat, transform=transform,
                                              scale=scale).T, np.float32)
    index = faiss.IndexFlatL2(sample.shape[1])
    index.add(sample)
    return index


def nearest_abrdfs(u: np.ndarray, sample_coef: np.ndarray, transform: Transform, truth: np.ndarray,
                   index=None, scale: np.ndarray | None = None) -> np.ndarray:
    """For every truth texel, the sample texel whose ABRDF is nearest to it (exact search).

    Nearest in eq. (11)'s measure: the RMS over the rows of linear radiance, the sample's
    ABRDFs as its compression reconstructs them (``u`` ``(rows, K)``, ``sample_coef``
    ``(h, w, K)``) against the truth's ``(H, W, rows)``. Returns flat sample indices
    ``(H, W)``. Exact brute force (faiss, flat L2), so the oracle is the best any copy can do.
    ``index``: :func:`abrdf_index` of the same sample, if already built.
    """
    index = abrdf_index(u, sample_coef, transform, scale) if index is None else index
    rows = truth.reshape(-1, truth.shape[-1])
    found = np.empty(len(rows), np.int64)
    for k in range(0, len(rows), 16384):
        _, hit = index.search(np.ascontiguousarray(rows[k : k + 16384], np.float32), 1)
        found[k : k + 16384] = hit[:, 0]
    return found.reshape(truth.shape[:2])


def oracle(u: np.ndarray, sample_coef: np.ndarray, transform: Transform, truth: np.ndarray, *,
           rows: np.ndarray | None = None, values: np.ndarray | None = None,
           noise: float = 0.0, metric: np.ndarray | None = None
           ) -> tuple[np.ndarray, np.ndarray]:
    """The best a method composing the sample's ABRDFs can reach, given the ground truth.

    Every texel copies the sample ABRDF nearest to the truth's (:func:`nearest_abrdfs`);
    with constraint ``rows`` ``(G, K)`` and the target's constraint ``values`` ``(H, W, G)``
    (log domain) the copy then goes through the same QP as the enlargement's result
    (:func:`tasks.constrained_blend.blend`, left to a residual of ``noise``, in ``metric``:
    :meth:`tasks.constrained_blend.ConstraintProjector.of`). Returns the
    copy and the constrained copy (the same array without constraints), ``(H, W, K)``.
    """
    from tasks.constrained_blend import ConstraintProjector, blend

    copy = sample_coef.reshape(-1, sample_coef.shape[-1])[
        nearest_abrdfs(u, sample_coef, transform, truth)]
    copy = copy.reshape(*truth.shape[:2], -1)
    if rows is None:
        return copy, copy
    constrained, _ = blend(copy, copy, values, ConstraintProjector.of(rows, metric=metric),
                           noise=noise)
    return copy, constrained


def gap_share(error: float, lookup: float, best: float) -> float:
    """The share of the gap from the best achievable to the lookup baseline left by ``error``.

    ``(error - best) / (lookup - best)``: 0 is the oracle, 1 the per-texel lookup, negative
    below the oracle (possible: a blend is not a copy).
    """
    return (error - best) / (lookup - best) if lookup != best else float("nan")

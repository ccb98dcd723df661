"""Enlargement against ground truth: the error of paper 000's eq. (11) and two baselines.

Pure numpy: the caller reads the stores. Coefficients are per texel, ``S V^T`` in a
compressed store's basis ``U`` (rows in BTF-matrix order: view, light, channel).
"""

from __future__ import annotations

import numpy as np


def abrdf_error(u: np.ndarray, coefficients: np.ndarray, eps: float, truth: np.ndarray,
                mask: np.ndarray) -> float:
    """Eq. (11) over the masked texels: mean of each texel's RMS radiance error (linear).

    ``u`` ``(rows, K)``; ``coefficients`` ``(H, W, K)``; ``truth`` ``(H, W, rows)`` linear
    radiance in the rows' order; ``mask`` ``(H, W)``: the texels that count.
    """
    return float(np.mean(abrdf_errors(u, coefficients, eps, truth, mask)))


def abrdf_errors(u: np.ndarray, coefficients: np.ndarray, eps: float, truth: np.ndarray,
                 mask: np.ndarray) -> np.ndarray:
    """Each masked texel's RMS radiance error (see :func:`abrdf_error`), 16384 at a time."""
    from tasks.svd import reconstruct

    texels = coefficients.reshape(-1, coefficients.shape[-1])[mask.ravel()]
    rows = truth.reshape(-1, truth.shape[-1])[mask.ravel()]
    errors = [np.zeros(0)]
    for k in range(0, len(texels), 16384):
        approx = reconstruct(u, np.ones(u.shape[1]), texels[k : k + 16384], eps=eps).T
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

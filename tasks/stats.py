"""Summary statistics of large arrays in dask's chunk / combine / aggregate shape.

``chunk_stats`` summarises one block as a small float64 vector, ``combine_stats`` merges any
number of such vectors, and ``finalize_stats`` turns the merged vector into a report. Only the
blocks' summaries travel, so an array of any size is scanned in memory bounded by one block.
"""

from __future__ import annotations

import numpy as np

STATS = ("count", "nan", "inf", "negative", "min", "max", "sum")
_COUNT, _NAN, _INF, _NEG, _MIN, _MAX, _SUM = range(len(STATS))


def chunk_stats(block: np.ndarray) -> np.ndarray:
    """Summary of one block: counts of values, NaN, +-Inf and negatives; finite min/max/sum."""
    block = np.asarray(block)
    out = np.zeros(len(STATS), np.float64)
    out[_COUNT] = block.size
    out[_MIN], out[_MAX] = np.inf, -np.inf
    if block.dtype.kind not in "fc":
        finite = block.reshape(-1)
    else:
        nan = np.isnan(block)
        inf = np.isinf(block)
        out[_NAN], out[_INF] = np.count_nonzero(nan), np.count_nonzero(inf)
        finite = block[~(nan | inf)]
    if block.dtype.kind in "fiu" and finite.size:
        out[_NEG] = np.count_nonzero(block < 0)
        out[_MIN], out[_MAX] = finite.min(), finite.max()
        out[_SUM] = finite.sum(dtype=np.float64)  # float64 accumulation: blocks can be large
    return out


def combine_stats(parts: np.ndarray) -> np.ndarray:
    """Merge summaries stacked along the first axis (any leading shape is flattened)."""
    parts = np.asarray(parts, np.float64).reshape(-1, len(STATS))
    out = parts.sum(axis=0)
    out[_MIN] = parts[:, _MIN].min(initial=np.inf)
    out[_MAX] = parts[:, _MAX].max(initial=-np.inf)
    return out


def finalize_stats(summary: np.ndarray) -> dict[str, float | int | None]:
    """Report of a merged summary: counts, and min/max/mean of the finite values (or None)."""
    s = np.asarray(summary, np.float64)
    finite = s[_COUNT] - s[_NAN] - s[_INF]
    has = finite > 0
    return {
        "count": int(s[_COUNT]),
        "nan": int(s[_NAN]),
        "inf": int(s[_INF]),
        "negative": int(s[_NEG]),
        "min": float(s[_MIN]) if has else None,
        "max": float(s[_MAX]) if has else None,
        "mean": float(s[_SUM] / finite) if has else None,
    }

"""Random numbers as pure functions of integer coordinates.

Procedural materials must give the same value for a texel however the image is cut into tiles
and whichever worker renders it, so randomness never comes from a generator's state: it is a hash
of the integer lattice coordinates and the seed (a SplitMix64 finaliser, which passes the usual
avalanche tests and costs a handful of integer operations per value).
"""

from __future__ import annotations

import numpy as np

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)


def _mix(z: np.ndarray) -> np.ndarray:
    z = (z ^ (z >> np.uint64(30))) * _MIX1
    z = (z ^ (z >> np.uint64(27))) * _MIX2
    return z ^ (z >> np.uint64(31))


def hash_coords(*coords: np.ndarray | int, seed: int) -> np.ndarray:
    """Hash integer coordinates (broadcast together) and a seed to uniform 64-bit integers.

    Parameters
    ----------
    *coords
        Integer arrays (or ints), broadcast against each other. Negative values are allowed.
    seed
        Non-negative integer; different seeds give independent streams.

    Returns
    -------
    numpy.ndarray
        ``uint64`` array of the broadcast shape.
    """
    # uint64 arithmetic is meant to wrap around; numpy only warns about it for scalars.
    with np.errstate(over="ignore"):
        h = _mix(np.asarray(seed, dtype=np.uint64) + _GOLDEN)
        for c in coords:
            c = np.asarray(c, dtype=np.int64).astype(np.uint64)
            h = _mix(h ^ (c * _GOLDEN + _MIX1))
    return np.asarray(h)


def hash_uniform(*coords: np.ndarray | int, seed: int) -> np.ndarray:
    """Uniform float64 numbers in ``[0, 1)`` from :func:`hash_coords` (53 significant bits)."""
    return (hash_coords(*coords, seed=seed) >> np.uint64(11)).astype(np.float64) * 2.0**-53

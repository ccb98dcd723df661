"""Kernels of ``btf scene``: one output block of the requested directions, region and level.

A scene's output block holds ``(direction, y, x, channel)``: for each requested direction the
weighted sum of the measured layers its interpolation terms name (:mod:`tasks.directions`), at
level of detail ``n`` the mean of ``2^n x 2^n`` texel blocks in linear radiance. The weights
are a dense ``(direction, layer)`` matrix over the distinct layers the block needs.
"""

from __future__ import annotations

import numpy as np

from tasks.svd import reconstruct
from tasks.transform import Transform

BUDGET = 64 << 20  # bytes of level-0 radiance one kernel holds at a time


def block_mean(a: np.ndarray, factor: int) -> np.ndarray:
    """Means of ``factor x factor`` texel blocks of ``(..., y, x, channel)`` (float64 sums).

    The sides must be multiples of ``factor``.
    """
    if factor == 1:
        return np.asarray(a, np.float32)
    *lead, ny, nx, nc = a.shape
    blocks = a.reshape(*lead, ny // factor, factor, nx // factor, factor, nc)
    return blocks.mean(axis=(-4, -2), dtype=np.float64).astype(np.float32)


def mix(layers: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """``(direction, ...)`` sums of ``(layer, ...)`` arrays with ``(direction, layer)`` weights."""
    w = np.asarray(weights, np.float32)
    flat = np.asarray(layers, np.float32).reshape(len(layers), -1)
    return (w @ flat).reshape(len(w), *layers.shape[1:])


def compressed_block(v: np.ndarray, *, u: np.ndarray, s: np.ndarray, transform: Transform,
                     weights: np.ndarray, factor: int = 1, scale: np.ndarray | None = None
                     ) -> np.ndarray:
    """Requested directions of an eigentexture block, ``(direction, y, x, channel)``.

    ``v`` is ``(y, x, k)`` at level 0 (sides multiples of ``factor``), ``u`` the eigen-ABRDF
    rows ``(layer, channel, k)`` of the layers ``weights`` ``(direction, layer)`` combine.
    Radiance (``transform`` of ``U S V^T``, each layer times its ``scale``: a cosine store's)
    is rebuilt as many layers at a time as fit :data:`BUDGET`, averaged over
    ``factor x factor`` blocks, and mixed.
    """
    ty, tx, k = v.shape
    nl, nc = u.shape[:2]
    texels = np.ascontiguousarray(v, np.float32).reshape(ty * tx, k)
    out = np.zeros((len(weights), ty // factor, tx // factor, nc), np.float32)
    step = max(1, BUDGET // (ty * tx * nc * 4))
    for l0 in range(0, nl, step):
        rows = np.asarray(u[l0 : l0 + step], np.float32)
        n = len(rows)
        radiance = reconstruct(rows.reshape(n * nc, k), s, texels, transform=transform,
                               scale=None if scale is None
                               else np.repeat(np.asarray(scale[l0 : l0 + n]), nc))
        layers = np.moveaxis(radiance.reshape(n, nc, ty, tx), 1, -1)
        out += mix(block_mean(layers, factor), weights[:, l0 : l0 + n])
    return out


def surface_block(values: np.ndarray, *, weights: np.ndarray, factor: int = 1,
                  u: np.ndarray | None = None, s: np.ndarray | None = None,
                  transform: Transform | None = None, scale: np.ndarray | None = None
                  ) -> np.ndarray:
    """Requested directions of a gathered surface block, ``(direction, y, x, channel)``.

    ``values`` is the level-0 block gathered from a tile set: ``(y, x, layer, channel)``
    radiance, or with ``u`` (a compressed tile set) ``(y, x, k)`` eigentextures.
    """
    if u is not None:
        return compressed_block(values, u=u, s=s, transform=transform, weights=weights,
                                factor=factor, scale=scale)
    layers = np.moveaxis(values, 2, 0)
    return mix(block_mean(layers, factor), weights)

"""What the relighting viewer (``btf view``) computes before the page is written.

The page renders a layer of a compressed store as the viewer's shader does (one dot product of
length ``k`` per texel and channel, then the store's transform and the report's tone mapping).
Between measured directions it blends the measured (view, light) pairs with barycentric
weights over a Delaunay triangulation of the directions projected onto the unit disk
(``(sin theta cos phi, sin theta sin phi)``): C0-continuous, exactly one pair at a measured
pair, and on the edge between two measured directions a blend of those two only. This module
holds the parts the page's script mirrors, so that tests can compute what the page must show.
"""

from __future__ import annotations

import numpy as np

SNAP = 1e-9  # barycentric weights below this are rounding noise: dropped


def disk(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Directions (degrees) projected onto the unit disk, ``(n, 2)`` float64."""
    t, p = np.radians(np.asarray(theta, np.float64)), np.radians(np.asarray(phi, np.float64))
    return np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p)], -1)


def triangulate(theta: np.ndarray, phi: np.ndarray, what: str) -> np.ndarray:
    """Triangles ``(m, 3)`` (int32 indices) of a Delaunay triangulation of the directions.

    One direction needs none (an empty array); two, or directions on one line, cannot be
    blended over a surface and raise ``ValueError`` naming ``what``.
    """
    from scipy.spatial import Delaunay, QhullError

    points = disk(theta, phi)
    if len(points) == 1:
        return np.zeros((0, 3), np.int32)
    if len(np.unique(np.round(points, 9), axis=0)) < 3:
        raise ValueError(f"{len(points)} {what} direction(s) cannot be triangulated: the "
                         "viewer blends between at least three directions not on one line")
    try:
        return Delaunay(points).simplices.astype(np.int32)
    except QhullError:
        raise ValueError(f"the {len(points)} {what} directions lie on one line and cannot be "
                         "triangulated") from None


def blend_weights(points: np.ndarray, triangles: np.ndarray, at: np.ndarray
                  ) -> list[tuple[int, float]]:
    """Barycentric weights of the point ``at`` (disk coordinates) over ``triangles``.

    The containing triangle's three corners; outside the triangulation, the triangle whose
    smallest weight is the largest, with negative weights set to 0 and the rest renormalised.
    Weights below :data:`SNAP` are dropped. One direction alone has weight 1. The page's
    script computes the same.
    """
    if len(triangles) == 0:
        return [(0, 1.0)]
    best, best_low = None, -np.inf
    for tri in triangles:
        a, b, c = points[tri]
        m = np.array([[b[0] - a[0], c[0] - a[0]], [b[1] - a[1], c[1] - a[1]]])
        det = np.linalg.det(m)
        if abs(det) < 1e-15:
            continue
        wb, wc = np.linalg.solve(m, np.asarray(at) - a)
        w = np.array([1.0 - wb - wc, wb, wc])
        if w.min() > best_low:
            best, best_low = (tri, w), w.min()
    tri, w = best
    w = np.where(w > SNAP, w, 0.0)  # rounding leaves 1e-17 of the other corners at a corner
    w /= w.sum()
    return [(int(i), float(x)) for i, x in zip(tri, w, strict=True) if x > 0]


def coefficients(us: np.ndarray, view_weights, light_weights) -> np.ndarray:
    """The blended rows of ``U diag(S)`` ``(channel, k)`` for the given pair weights.

    ``us`` is ``(view, light, channel, k)``; each weight list is ``[(index, weight), ...]``.
    """
    out = np.zeros(us.shape[2:], np.float64)
    for v, wv in view_weights:
        for li, wl in light_weights:
            out += wv * wl * us[v, li]
    return out.astype(np.float32)


def half_bits(values: np.ndarray) -> np.ndarray:
    """IEEE half-float bit patterns (uint16) of ``values``, rounded to nearest.

    Raises ``ValueError`` if a value is beyond half's range (65504).
    """
    a = np.asarray(values, np.float32)
    if a.size and float(np.abs(a).max()) > 65504.0:
        raise ValueError(f"values up to {float(np.abs(a).max()):.3g} exceed half floats' range")
    return a.astype(np.float16).view(np.uint16)


def pack_eigentextures(v: np.ndarray) -> np.ndarray:
    """Eigentextures ``(y, x, k)`` as half-float layers of four components ``(k/4, y, x, 4)``.

    Components past ``k`` (to a multiple of four) are zero. Half floats keep 11 significant
    bits: about 5e-4 of each value, below an 8-bit display step after the transform (the
    viewer's tests bound the displayed error).
    """
    ny, nx, k = v.shape
    layers = -(-k // 4)
    padded = np.zeros((ny, nx, layers * 4), np.float32)
    padded[..., :k] = v
    return np.ascontiguousarray(half_bits(padded).reshape(ny, nx, layers, 4).transpose(2, 0, 1, 3))


def triangle_grid(points: np.ndarray, triangles: np.ndarray, size: int) -> np.ndarray:
    """Per cell of a ``size`` x ``size`` grid over ``[-1, 1]^2``, the triangle a shader blends in.

    The triangle :func:`blend_weights` picks for the cell's centre (int32, row ``y`` from -1
    up); -1 where there are no triangles. The surface mode looks up each pixel's light and view
    direction here, then weighs the triangle's corners by their barycentric coordinates of the
    exact direction, so only points within a cell of an edge can blend in a neighbouring
    triangle, with weights clipped at 0 (continuous, 2 / ``size`` wide at most).
    """
    if len(triangles) == 0:
        return np.full((size, size), -1, np.int32)
    centres = (np.arange(size) + 0.5) / size * 2 - 1
    gx, gy = np.meshgrid(centres, centres)
    at = np.stack([gx.ravel(), gy.ravel()], -1)
    a, b, c = (points[triangles[:, i]] for i in range(3))
    m00, m01 = b[:, 0] - a[:, 0], c[:, 0] - a[:, 0]
    m10, m11 = b[:, 1] - a[:, 1], c[:, 1] - a[:, 1]
    det = m00 * m11 - m01 * m10
    ok = np.abs(det) >= 1e-15
    out = np.empty(len(at), np.int32)
    for s in range(0, len(at), 1024):
        px = at[s:s + 1024, None, 0] - a[None, :, 0]
        py = at[s:s + 1024, None, 1] - a[None, :, 1]
        with np.errstate(divide="ignore", invalid="ignore"):
            wb = (px * m11 - m01 * py) / det
            wc = (m00 * py - px * m10) / det
        low = np.minimum(np.minimum(1 - wb - wc, wb), wc)
        low[:, ~ok] = -np.inf
        out[s:s + 1024] = np.argmax(low, axis=1)  # the first of equals, as blend_weights
    return out.reshape(size, size)

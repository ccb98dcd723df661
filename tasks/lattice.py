"""Lattice geometry shared by the roller's planner and the renderer (paper 004).

A tile lattice is spanned by two integer vectors ``U``, ``V`` (``(dy, dx)`` in texels). Its
Hermite normal form ``(h, w, s)`` is the equivalent basis ``(h, s)``, ``(0, w)``: tiles stored
as ``h x w`` rectangles tile the plane by row bands shifted by ``s``, so rendering is slice
copies. Everything here is exact integer arithmetic.
"""

from __future__ import annotations

import numpy as np


def hermite(U, V) -> tuple[int, int, int]:
    """``(h, w, s)``: the lattice spanned by ``U``, ``V`` has the basis ``(h, s)``, ``(0, w)``."""
    uy, ux = (int(c) for c in U)
    vy, vx = (int(c) for c in V)
    det = uy * vx - ux * vy
    if det == 0:
        raise ValueError(f"U = {U} and V = {V} are parallel")
    g, p, q = _egcd(uy, vy)
    if g == 0:  # both horizontal: impossible with det != 0
        raise ValueError(f"U = {U} and V = {V} do not span the plane")
    h = abs(g)
    sx = p * ux + q * vx
    if g < 0:
        sx = -sx
    w = abs(det) // h
    return h, w, sx % w


def _egcd(a: int, b: int) -> tuple[int, int, int]:
    """``(g, p, q)`` with ``p a + q b = g = gcd(a, b)``."""
    if b == 0:
        return (a, 1, 0)
    g, p, q = _egcd(b, a % b)
    return g, q, p - (a // b) * q


def lattice_coordinates(points: np.ndarray, U, V) -> tuple[np.ndarray, np.ndarray]:
    """Integer part and fraction of ``points`` (``(..., 2)`` int) in the basis ``U``, ``V``.

    Exact integer arithmetic: ``points = floor_a U + floor_b V + (frac_a U + frac_b V)``.
    """
    uy, ux = U
    vy, vx = V
    det = uy * vx - ux * vy
    y, x = points[..., 0].astype(np.int64), points[..., 1].astype(np.int64)
    num_a = vx * y - vy * x
    num_b = -ux * y + uy * x
    if det < 0:
        num_a, num_b, det = -num_a, -num_b, -det
    ia, ib = np.floor_divide(num_a, det), np.floor_divide(num_b, det)
    return np.stack([ia, ib], -1), np.stack([(num_a - ia * det) / det,
                                             (num_b - ib * det) / det], -1)


def hermite_bands(y0: int, x0: int, ny: int, nx: int, hnf):
    """The stored-tile slices of a region: ``(out_rows, out_cols, rows, cols)`` per piece."""
    h, w, s = hnf
    for k in range(y0 // h, (y0 + ny - 1) // h + 1):
        ya, yb = max(y0, k * h), min(y0 + ny, (k + 1) * h)
        shifted = x0 - k * s
        for j in range(shifted // w, (shifted + nx - 1) // w + 1):
            xa, xb = max(shifted, j * w), min(shifted + nx, (j + 1) * w)
            yield (slice(ya - y0, yb - y0), slice(xa - shifted, xb - shifted),
                   slice(ya - k * h, yb - k * h), slice(xa - j * w, xb - j * w))


def lattice_cells(y0: int, x0: int, ny: int, nx: int, *, hnf, basis, representative
                  ) -> np.ndarray:
    """Lattice cell ``(i, j)`` of every texel of a region tiled by cut tiles ``(ny, nx, 2)``.

    Texel ``p`` is stored texel ``q`` (Hermite layout, see :func:`hermite_bands`) and lies in
    the cell ``(i, j)`` with ``p = i U + j V + representative[q]``.
    """
    out = np.empty((ny, nx, 2), np.int64)
    for orows, ocols, rows, cols in hermite_bands(y0, x0, ny, nx, hnf):
        yy, xx = np.mgrid[y0 + orows.start : y0 + orows.stop, x0 + ocols.start : x0 + ocols.stop]
        cell, _ = lattice_coordinates(np.stack([yy, xx], -1) - representative[rows, cols],
                                      *basis)
        out[orows, ocols] = cell
    return out

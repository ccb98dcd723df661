"""Rays over a height field: cast shadows towards a light and parallax towards a camera.

A ray's horizontal direction is marched like a line-drawing DDA: one pixel per step along the
dominant axis, a fraction of a pixel along the other. The height at every step is then a blend of
two shifted slices of the height array with weights that are the same for all texels, so a whole
tile advances one step with a few vector operations, and a texel's result depends only on the
heights within a fixed distance: tiles rendered separately with a large enough halo agree bit for
bit with one large render.

Heights and horizontal distances are both in pixels. The frame is the store's (docs/formats.md,
"The frame"): x along increasing columns, y towards the top of the picture, so +y is *decreasing*
row index; the azimuth ``phi`` runs from +x towards +y (see :mod:`tasks.sampling`). Offsets
below are in rows and columns.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tasks.noise import smoothstep

_TOP = 1e-6  # degrees: a direction this close to the normal casts no shadow and no parallax


@dataclass(frozen=True)
class Step:
    """One DDA step along azimuth ``phi``: row and column offsets and horizontal length.

    ``dy`` is in rows, which run against the frame's +y.
    """

    dy: float
    dx: float
    length: float


def dda_step(phi_deg: float) -> Step:
    """The step along azimuth ``phi_deg`` that moves exactly one pixel along the dominant axis."""
    # cy: the step's row component; +y (phi = 90) is towards row 0
    cx, cy = math.cos(math.radians(phi_deg)), -math.sin(math.radians(phi_deg))
    major = max(abs(cx), abs(cy))
    if abs(cx) >= abs(cy):
        return Step(cy / major, math.copysign(1.0, cx), 1.0 / major)
    return Step(math.copysign(1.0, cy), cx / major, 1.0 / major)


def shifted(h: np.ndarray, r0: int, c0: int, ny: int, nx: int, oy: float, ox: float) -> np.ndarray:
    """``h`` sampled bilinearly at ``(r0 + i + oy, c0 + j + ox)`` for an ``ny x nx`` region."""
    iy, ix = math.floor(oy), math.floor(ox)
    fy, fx = oy - iy, ox - ix
    r, c = r0 + iy, c0 + ix
    out = h[r : r + ny, c : c + nx]
    if fy > 1e-9:
        out = out + np.float32(fy) * (h[r + 1 : r + 1 + ny, c : c + nx] - out)
    if fx > 1e-9:
        right = h[r : r + ny, c + 1 : c + 1 + nx]
        if fy > 1e-9:
            below = h[r + 1 : r + 1 + ny, c + 1 : c + 1 + nx]
            right = right + np.float32(fy) * (below - right)
        out = out + np.float32(fx) * (right - out)
    return out


def _check_reach(h: np.ndarray, r0: int, c0: int, ny: int, nx: int, reach: int) -> None:
    if min(r0, c0, h.shape[0] - r0 - ny, h.shape[1] - c0 - nx) < reach:
        raise ValueError(
            f"height window {h.shape} leaves less than {reach} texels around the region "
            f"({r0}:{r0 + ny}, {c0}:{c0 + nx}) that the rays need"
        )


def _rise(theta_deg: float) -> float:
    """Height gained per unit of horizontal distance along a ray at ``theta`` from the normal."""
    return math.cos(math.radians(theta_deg)) / math.sin(math.radians(theta_deg))


def shadow_length(theta_deg: float, *, relief: float, penumbra: float, max_length: float) -> float:
    """Horizontal distance (px) a shadow ray must travel to rise above every height.

    Beyond it the ray is higher than the relief, so nothing farther can shadow the texel. Very
    grazing lights are cut at ``max_length`` (a deterministic truncation, not a tiling artefact).
    """
    if theta_deg < _TOP:
        return 0.0
    return min((relief + penumbra) / _rise(theta_deg), max_length)


def visibility(
    h: np.ndarray, r0: int, c0: int, ny: int, nx: int, *, theta: float, phi: float,
    relief: float, penumbra: float, max_length: float,
) -> np.ndarray:
    """Fraction of the light at ``(theta, phi)`` reaching each texel of a region (cast shadows).

    A texel is lit when the ray towards the light stays above the height field; the margin by
    which it clears (or misses) is smoothed over ``penumbra`` pixels of height, a stand-in for
    the light source's finite size.

    Parameters
    ----------
    h
        Height window (float32), including a halo of at least :func:`shadow_length` + 1.
    r0, c0, ny, nx
        The region of ``h`` to shade.
    theta, phi
        Light direction in degrees.
    relief, penumbra, max_length
        Height range of ``h``, shadow softness and the longest ray traced (pixels).
    """
    h0 = h[r0 : r0 + ny, c0 : c0 + nx]
    length = shadow_length(theta, relief=relief, penumbra=penumbra, max_length=max_length)
    if length == 0.0:
        return np.ones_like(h0)
    step, rise = dda_step(phi), _rise(theta)
    steps = math.ceil(length / step.length)
    _check_reach(h, r0, c0, ny, nx, steps + 1)
    top = shadow_tops(h, r0, c0, ny, nx, step, steps, rise)
    return smoothstep(-0.5 * penumbra, 0.5 * penumbra, h0 - top).astype(np.float32)


def shadow_tops(h: np.ndarray, r0: int, c0: int, ny: int, nx: int, step: Step, steps: int,
                rise: float) -> np.ndarray:
    """How far the heights along each texel's ray to the light rise above it, at most.

    The maximum over steps ``t = 1 .. steps`` of ``shifted(h, .., t * step.dy, t * step.dx)``
    minus the ray's height there, ``t * step.length * rise``, in one compiled loop
    (:func:`tasks.render_kernels.shadow_tops`): the same bits as those array operations.
    """
    from tasks.render_kernels import shadow_tops as loop

    t = np.arange(1, steps + 1)
    oy, ox = t * step.dy, t * step.dx
    iy, ix = np.floor(oy), np.floor(ox)
    fy, fx = oy - iy, ox - ix
    # shifted() skips a blend whose fraction is under 1e-9, and rounds the others to float32.
    fy = np.where(fy > 1e-9, fy, 0.0).astype(np.float32)
    fx = np.where(fx > 1e-9, fx, 0.0).astype(np.float32)
    ray = (t * step.length * rise).astype(np.float32)
    return loop(np.ascontiguousarray(h, np.float32), r0, c0, ny, nx, iy.astype(np.intp),
                ix.astype(np.intp), fy, fx, ray, np.empty((ny, nx), np.float32))


def parallax_length(theta_deg: float, *, relief: float, reference: float) -> float:
    """Largest horizontal distance (px) between a texel and the point its view ray meets.

    Heights lie in ``[0, relief]`` and views are registered on the plane ``z = reference``.
    """
    if theta_deg < _TOP:
        return 0.0
    return max(relief - reference, reference) / _rise(theta_deg)


def parallax_hits(
    h: np.ndarray, r0: int, c0: int, ny: int, nx: int, *, theta: float, phi: float,
    relief: float, reference: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Where the view ray through each texel of a region first meets the height field.

    Layers are registered on the reference plane ``z = reference`` (rectified, as measured BTFs
    are): the camera ray of a texel crosses that plane straight above the texel. Followed from
    the camera, the ray enters the relief at ``z = relief`` on the camera's side and descends
    until it meets the surface (linear refinement between the last step above and the first
    below). A texel therefore shows a point displaced towards the camera if the surface there
    is above the plane (so raised structure appears displaced away from the camera), and away
    from the camera if it is below: parallax and occlusion, as a camera sees them.

    Returns
    -------
    oy, ox : numpy.ndarray
        Float32 offsets (rows, columns) from each texel of the region to the visible surface
        point. Offsets, not absolute positions, so that rounding does not depend on where the
        region lies in its window.
    """
    hit = np.zeros((ny, nx), np.float32)
    if theta < _TOP:
        return hit, hit.copy()
    step = dda_step(phi)  # towards the camera
    climb = step.length * _rise(theta)  # height of the ray gained per step towards the camera
    first = math.ceil((relief - reference) / climb)  # here the ray is above the whole relief
    last = math.floor(-reference / climb) - 1  # here it is below the floor: it has hit
    _check_reach(h, r0, c0, ny, nx, max(first, -last) + 1)
    found = np.zeros((ny, nx), bool)
    prev = None
    for u in range(first, last - 1, -1):
        ray = np.float32(reference + u * climb)
        cur = shifted(h, r0, c0, ny, nx, u * step.dy, u * step.dx) - ray
        new = ~found & (cur >= 0)
        if new.any():
            if prev is None:
                hit[new] = u
            else:
                hit[new] = (u + 1) - prev[new] / (prev[new] - cur[new])
            found |= new
        prev = cur
    return hit * np.float32(step.dy), hit * np.float32(step.dx)


def bilinear(a: np.ndarray, r0: int, c0: int, oy: np.ndarray, ox: np.ndarray) -> np.ndarray:
    """Sample ``a`` (2-D, or 3-D with trailing channels) at ``(r0 + i + oy, c0 + j + ox)``.

    ``oy`` and ``ox`` are per-texel offsets of an ``ny x nx`` region whose first texel is
    ``(r0, c0)``; interpolation is bilinear. The renderer runs :func:`bilinear_layers`, which
    gives these bits for a stack of layers at once; this is its reference.
    """
    ny, nx = oy.shape
    iy, ix = np.floor(oy), np.floor(ox)
    fy, fx = oy - iy, ox - ix
    rows = (r0 + np.arange(ny))[:, None] + iy.astype(np.intp)
    cols = (c0 + np.arange(nx))[None, :] + ix.astype(np.intp)
    if a.ndim == 3:
        fy, fx = fy[..., None], fx[..., None]
    top = a[rows, cols] + fx * (a[rows, cols + 1] - a[rows, cols])
    bottom = a[rows + 1, cols] + fx * (a[rows + 1, cols + 1] - a[rows + 1, cols])
    return top + fy * (bottom - top)


def bilinear_layers(a: np.ndarray, r0: int, c0: int, oy: np.ndarray, ox: np.ndarray
                    ) -> np.ndarray:
    """:func:`bilinear` of every layer of ``a`` ``(layers, h, w)`` at the same offsets.

    In one compiled loop (:func:`tasks.render_kernels.bilinear_layers`) that finds each
    texel's position and weights once for all layers: the same bits as ``np.stack([bilinear(
    layer, ..) for layer in a])``.
    """
    from tasks.render_kernels import bilinear_layers as loop

    out = np.empty((a.shape[0], *oy.shape), np.result_type(a, oy))
    return loop(a, r0, c0, oy, ox, out)

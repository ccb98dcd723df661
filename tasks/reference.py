"""The reference image that guides quilting (paper 003, section 2.2).

Quilting plans patch transfers on one image that stands for the whole (A)BTF, so that the same
transfers can be applied to every layer. Its components, all computed per texel from the layers
of one view (the one closest to the normal):

- **diffuse map**: the mean over light directions of the radiance ("normalized sum");
- **normal map**: the direction of the strongest response, estimated as the average of the
  light directions weighted by ``(I / max I)^k`` (paper: "the averaged direction to the
  strongest incoming light contribution"). The map uses the low exponent ``k = 1``: on glossy
  texels a high exponent follows the specular highlight rather than the normal;
- **height map**: the normal map integrated in the Fourier domain (Frankot and Chellappa 1988);
- **reflectance map**: how far two such normal estimates, weighted with a low and a high
  exponent, disagree. On a diffuse texel both point along the normal; on a glossy one the
  high exponent follows the specular highlight, which for a camera above the sample sits at
  twice the normal's tilt (paper: "comparing two normal maps weighted with different
  exponents to find strongly reflective areas").

The per-texel sums over lights are the chunk step (:func:`light_sums`, one spatial tile at a
time, summable over light blocks); :func:`reference_maps` finishes on whole-image arrays.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

LOW_EXPONENT = 1.0
HIGH_EXPONENT = 16.0
SUMS = ("diffuse_r", "diffuse_g", "diffuse_b", "count",
        "low_x", "low_y", "low_z", "low_w", "high_x", "high_y", "high_z", "high_w", "peak")
_PEAK = SUMS.index("peak")


def luminance(rgb: np.ndarray) -> np.ndarray:
    """Rec. 709 luminance of linear RGB ``(..., 3)`` (the mean of the channels otherwise)."""
    rgb = np.asarray(rgb, np.float32)
    if rgb.shape[-1] != 3:
        return rgb.mean(axis=-1)
    return rgb @ np.array([0.2126, 0.7152, 0.0722], np.float32)


def light_sums(layers: np.ndarray, lights: np.ndarray) -> np.ndarray:
    """Per-texel sums over a block of light directions (the chunk step).

    Parameters
    ----------
    layers
        Radiance ``(lights, y, x, channel)`` of one view, float32.
    lights
        Unit light vectors ``(lights, 3)``.

    Returns
    -------
    numpy.ndarray
        ``(y, x, len(SUMS))`` float64: radiance sums (RGB), the layer count, for each exponent
        the weighted sums of light vectors and of weights, and the per-texel maximum luminance
        ``peak``. Weights are ``(I / peak)^k`` with the maximum taken over *this block's*
        lights; blocks are combined by :func:`combine_light_sums`, which rescales them to a
        common maximum.
    """
    layers = np.asarray(layers, np.float32)
    nl, ny, nx, nc = layers.shape
    rgb = layers if nc == 3 else np.repeat(layers.mean(axis=-1, keepdims=True), 3, axis=-1)
    out = np.zeros((ny, nx, len(SUMS)), np.float64)
    out[..., 0:3] = rgb.sum(axis=0, dtype=np.float64)
    out[..., 3] = nl
    intensity = np.maximum(luminance(rgb), 0.0)
    peak = intensity.max(axis=0)
    rel = intensity / np.where(peak > 0, peak, 1.0)
    for k, base in ((LOW_EXPONENT, 4), (HIGH_EXPONENT, 8)):
        w = rel.astype(np.float64) ** k
        out[..., base : base + 3] = np.einsum("lyx,lc->yxc", w, lights)
        out[..., base + 3] = w.sum(axis=0)
    out[..., _PEAK] = peak
    return out


def combine_light_sums(parts: np.ndarray) -> np.ndarray:
    """Combine :func:`light_sums` of light blocks stacked on the first axis ``(k, y, x, n)``.

    Each block's weights were relative to its own per-texel maximum; they are rescaled to the
    maximum over all blocks (``w * (m_block / m_all)^k``) before adding, so the result equals
    the sums computed over all lights at once. The result is itself such a sum (with the common
    maximum as ``peak``), so combining is associative: partial combines may be combined again.
    """
    parts = np.asarray(parts, np.float64)
    peaks = parts[..., _PEAK]
    top = peaks.max(axis=0)
    ratio = np.where(top > 0, peaks / np.where(top > 0, top, 1.0), 0.0)
    scaled = parts.copy()
    scaled[..., 4:8] *= (ratio**LOW_EXPONENT)[..., None]
    scaled[..., 8:12] *= (ratio**HIGH_EXPONENT)[..., None]
    total = scaled.sum(axis=0)
    total[..., _PEAK] = top
    return total


def _normals(sums: np.ndarray, base: int) -> np.ndarray:
    v = sums[..., base : base + 3]
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    n = np.where(norm > 0, v / np.where(norm > 0, norm, 1.0), np.array([0.0, 0.0, 1.0]))
    n[..., 2] = np.maximum(n[..., 2], 0.05)  # a normal never points below the sample plane
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def frankot_chellappa(nx: np.ndarray, ny: np.ndarray, nz: np.ndarray) -> np.ndarray:
    """Height (pixels) whose gradient best fits a normal field, in the Fourier domain.

    Frankot and Chellappa (1988): with ``p = dz/dx = -nx/nz`` and ``q = dz/dy = -ny/nz``, the
    least-squares integrable surface is ``Z = (-i wx P - i wy Q) / (wx^2 + wy^2)`` (periodic
    boundary, mean height 0). The normals are in the store's frame, whose +y is towards row 0:
    along rows the slope is ``-q``, and ``wy`` is the rows' frequency.
    """
    p, q = -nx / nz, ny / nz  # q: dz per row
    h, w = p.shape
    wy = 2 * np.pi * np.fft.fftfreq(h)[:, None]
    wx = 2 * np.pi * np.fft.fftfreq(w)[None, :]
    denom = wx**2 + wy**2
    denom[0, 0] = 1.0
    z = (-1j * wx * np.fft.fft2(p) - 1j * wy * np.fft.fft2(q)) / denom
    z[0, 0] = 0.0
    return np.real(np.fft.ifft2(z))


def _unit(x: np.ndarray, percentile: float = 99.5) -> np.ndarray:
    """Scale to about ``[0, 1]`` (robust to a few extreme texels), clipped."""
    lo = np.percentile(x, 100 - percentile)
    hi = np.percentile(x, percentile)
    return np.clip((x - lo) / (hi - lo if hi > lo else 1.0), 0.0, 1.0).astype(np.float32)


@dataclass(frozen=True)
class ReferenceMaps:
    """The maps of a reference image (float32, ``(y, x)`` or ``(y, x, 3)``)."""

    diffuse: np.ndarray  # RGB, about [0, 1]
    normal: np.ndarray  # unit vectors (x, y, z)
    height: np.ndarray  # [0, 1]
    reflectance: np.ndarray  # [0, 1]
    reference: np.ndarray  # RGB: the weighted combination quilting compares


def reference_maps(sums: np.ndarray, *, weights: tuple[float, float, float] = (1.0, 0.5, 0.5)
                   ) -> ReferenceMaps:
    """The reference image and its components from the light sums of every texel.

    ``weights`` are those of the diffuse, height and reflectance maps in the combination
    ``R = w_D D + w_H H + w_R Rf`` (the scalar maps are added to every channel), each map
    scaled to about ``[0, 1]`` first; the result is divided by the sum of the weights.
    """
    wd, wh, wr = (float(w) for w in weights)
    if min(wd, wh, wr) < 0 or wd + wh + wr <= 0:
        raise ValueError(f"weights must be non-negative and not all 0, got {weights}")
    diffuse = sums[..., 0:3] / np.maximum(sums[..., 3:4], 1.0)
    low, high = _normals(sums, 4), _normals(sums, 8)
    height = frankot_chellappa(low[..., 0], low[..., 1], low[..., 2])
    disagreement = 1.0 - np.clip(np.sum(low * high, axis=-1), -1.0, 1.0)
    d, h, r = _unit(diffuse), _unit(height), _unit(disagreement)
    combined = (wd * d + (wh * h + wr * r)[..., None]) / (wd + wh + wr)
    return ReferenceMaps(d, low.astype(np.float32), h, r, combined.astype(np.float32))

"""HLS fitting of an ABTF (paper 003, section 2.5).

Per texel, hue and saturation are taken as constant over light directions and lightness is
fitted, for every light rotation, by six parameters over elevation. Choices where the paper is
not specific:

- **HLS for HDR radiance.** Lightness ``L = (max + min) / 2`` of the linear RGB values and hue
  as usual; saturation is ``(max - min) / (max + min)``, which equals HLS saturation for
  ``L <= 1/2`` and stays in ``[0, 1]`` for radiance above 1, so that
  ``max = L (1 + S)`` and ``min = L (1 - S)`` invert it for any ``L >= 0``.
- **Constant hue and saturation**: the chroma-weighted circular mean of the hue and the
  lightness-weighted mean of the saturation over all layers.
- **Six parameters**: a polynomial of degree 5 in the elevation scaled to ``[-1, 1]``, fitted by
  least squares (with fewer than six elevations, degree ``E - 1``: exact interpolation).
- **The error is the stored fit's**: parameters are rounded to float32 (as stored) before the
  fit's error against the input is measured, so the reported error is that of what a reader
  reconstructs.
"""

from __future__ import annotations

import numpy as np

PARAMETERS = 6


def rgb_to_hls(rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Hue in ``[0, 1)``, lightness and saturation (see module) of non-negative RGB."""
    rgb = np.maximum(np.asarray(rgb, np.float64), 0.0)
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    hi, lo = rgb.max(axis=-1), rgb.min(axis=-1)
    chroma = hi - lo
    light = 0.5 * (hi + lo)
    sat = np.where(hi + lo > 0, chroma / np.where(hi + lo > 0, hi + lo, 1.0), 0.0)
    safe = np.where(chroma > 0, chroma, 1.0)
    hue = np.where(hi == r, ((g - b) / safe) % 6.0,
                   np.where(hi == g, (b - r) / safe + 2.0, (r - g) / safe + 4.0)) / 6.0
    return np.where(chroma > 0, hue, 0.0) % 1.0, light, sat


def hls_to_rgb(hue: np.ndarray, light: np.ndarray, sat: np.ndarray) -> np.ndarray:
    """Inverse of :func:`rgb_to_hls` (broadcasting), float32."""
    light = np.asarray(light, np.float64)
    hi = light * (1.0 + sat)
    lo = light * (1.0 - sat)
    h6 = (np.asarray(hue, np.float64) % 1.0) * 6.0
    sector = np.floor(h6)
    f = h6 - sector
    rising = lo + f * (hi - lo)
    falling = hi - f * (hi - lo)
    k = sector.astype(np.int64) % 6
    r = np.choose(k, [hi, falling, lo, lo, rising, hi])
    g = np.choose(k, [rising, hi, hi, falling, lo, lo])
    b = np.choose(k, [lo, lo, rising, hi, hi, falling])
    return np.stack([r, g, b], axis=-1).astype(np.float32)


def constant_hue_saturation(hue: np.ndarray, light: np.ndarray, sat: np.ndarray
                            ) -> tuple[np.ndarray, np.ndarray]:
    """Per-texel hue and saturation over the leading (layer) axis, see the module."""
    chroma = 2.0 * light * sat
    angle = 2 * np.pi * hue
    x = np.sum(chroma * np.cos(angle), axis=0)
    y = np.sum(chroma * np.sin(angle), axis=0)
    mean_hue = (np.arctan2(y, x) / (2 * np.pi)) % 1.0
    weight = light.sum(axis=0)
    mean_sat = np.where(weight > 0, np.sum(light * sat, axis=0) / np.where(weight > 0, weight,
                                                                              1.0), 0.0)
    return mean_hue, mean_sat


def _design(elevation: np.ndarray) -> np.ndarray:
    e = np.asarray(elevation, np.float64)
    t = (e / 90.0) * 2.0 - 1.0
    degree = min(PARAMETERS, e.size) - 1
    return np.vander(t, degree + 1, increasing=True)


def fit_lightness(light: np.ndarray, elevation: np.ndarray) -> np.ndarray:
    """Coefficients ``(rotations, PARAMETERS, ...)`` of lightness.

    ``light`` is ``(rotations, elevations, ...)``; fitted by least squares per rotation.
    """
    light = np.asarray(light, np.float64)
    rotations, elevations = light.shape[:2]
    rest = light.shape[2:]
    basis = _design(elevation)
    coef, *_ = np.linalg.lstsq(basis, light.transpose(1, 0, *range(2, light.ndim)).reshape(
        elevations, -1), rcond=None)
    full = np.zeros((PARAMETERS, coef.shape[1]))
    full[: coef.shape[0]] = coef
    return full.reshape(PARAMETERS, rotations, *rest).swapaxes(0, 1)


def evaluate_lightness(coefficients: np.ndarray, elevation: np.ndarray) -> np.ndarray:
    """Lightness ``(rotations, elevations, ...)`` of fitted coefficients, never negative."""
    basis = _design(elevation)
    used = coefficients[:, : basis.shape[1]]
    return np.maximum(np.einsum("ep,rp...->re...", basis, used), 0.0)


def light_grid(phi_light: np.ndarray, theta_light: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rotation azimuths, elevations (degrees) and the light index of every (rotation, elevation).

    Raises ``ValueError`` when the lights are not a full grid of rotations x elevations.
    """
    phi = np.round(np.asarray(phi_light, np.float64) % 360.0, 6)
    elev = np.round(90.0 - np.asarray(theta_light, np.float64), 6)
    rotations, elevations = np.unique(phi), np.unique(elev)
    grid = np.full((rotations.size, elevations.size), -1, np.int64)
    for i, (p, e) in enumerate(zip(phi, elev, strict=True)):
        r, k = np.searchsorted(rotations, p), np.searchsorted(elevations, e)
        if grid[r, k] >= 0:
            raise ValueError(f"lights {grid[r, k]} and {i} have the same direction")
        grid[r, k] = i
    if np.any(grid < 0):
        raise ValueError(f"the lights are not a grid of {rotations.size} rotations x "
                         f"{elevations.size} elevations (HLS fitting needs an ABTF sampling "
                         "such as abtf:R,E)")
    return rotations, elevations, grid


def rebuild(hue, sat, coef, grid: np.ndarray, elevations: np.ndarray) -> np.ndarray:
    """Radiance ``(light, y, x, 3)`` of fitted parameters (lights in store order), float32."""
    light = evaluate_lightness(coef, elevations)  # (rotation, elevation, y, x)
    out = np.empty((grid.size, *np.shape(hue), 3), np.float32)
    out[grid.ravel()] = hls_to_rgb(hue, light.reshape(grid.size, *np.shape(hue)), sat)
    return out


def fit_block(layers: np.ndarray, grid: np.ndarray, elevations: np.ndarray):
    """Fit a block ``(light, y, x, 3)``.

    Returns hue, saturation, lightness coefficients ``(rotation, PARAMETERS, y, x)`` (float32,
    as stored) and the error of those parameters against ``layers``: (sum of squares, maximum
    absolute difference, number of values).
    """
    hue, light, sat = rgb_to_hls(layers)
    h, s = constant_hue_saturation(hue, light, sat)
    coef = fit_lightness(light[grid], elevations)
    h, s, coef = (np.asarray(a, np.float32) for a in (h, s, coef))
    d = rebuild(h, s, coef, grid, elevations).astype(np.float64) - layers
    return h, s, coef, (float(np.sum(d * d)), float(np.max(np.abs(d))), d.size)

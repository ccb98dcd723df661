"""Periodicity detection: the two periodicity vectors of a texture (paper 004, section 2).

Following the paper: the Fourier amplitude spectrum of the grey-scale image gives the two
largest coefficients at least 10 degrees apart; their directions bisect two sectors (here the
two halves of the half-plane of directions, split half-way between the bisectors); in each
sector the maximum of the spatial autocorrelation gives a periodicity vector, and among several
maxima of about the same correlation the smallest period is taken. Choices where the paper is not
specific:

- **Autocorrelation**: of the image minus a broad Gaussian blur (sigma = size / 8, removing
  shading gradients), zero-padded and normalised per lag by the overlap and the variance, so
  that a perfectly periodic image scores 1 at its lattice vectors; lags up to half the image.
- **"About the same correlation"**: at least 80% of the sector's maximum.
- **Minimal rhomboid**: the two vectors are Lagrange-Gauss reduced (the shortest basis of the
  lattice they span); a strong maximum that is not on that lattice (a finer lattice than the
  sectors suggested) is added and the basis reduced again.
- **Sub-pixel vectors**: the maxima near the lattice points ``i u + j v`` (``|i|, |j| <= 3``)
  are located to sub-pixel precision by quadratic fits and ``u``, ``v`` fitted to all of them by
  least squares, so rotated lattices are not limited to integer lags.
- **Confidence**: the smaller of the normalised autocorrelations at ``u`` and ``v`` (0 if no
  vector was found): about 1 for a strictly periodic texture, under 0.3 for a stochastic one.

Vectors are ``(dy, dx)`` in pixels; angles are degrees from the image's +x axis (columns)
towards +y (rows), in ``(-90, 90]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.fft import irfft2, next_fast_len, rfft2

MIN_SEPARATION_DEG = 10.0
SAME_CORRELATION = 0.8
PEAK_FLOOR = 0.15


@dataclass(frozen=True)
class Lattice:
    """Two periodicity vectors ``u``, ``v`` (``(dy, dx)`` pixels) and the confidence."""

    u: tuple[float, float]
    v: tuple[float, float]
    confidence: float
    sector_angles_deg: tuple[float, float] = (0.0, 90.0)

    @property
    def lengths_px(self) -> tuple[float, float]:
        """Lengths of ``u`` and ``v``."""
        return (float(np.hypot(*self.u)), float(np.hypot(*self.v)))

    @property
    def angles_deg(self) -> tuple[float, float]:
        """Directions of ``u`` and ``v``."""
        return (_angle(np.asarray(self.u)), _angle(np.asarray(self.v)))

    @property
    def area(self) -> float:
        """Area of the rhomboid spanned by ``u`` and ``v`` (pixels)."""
        return abs(self.u[0] * self.v[1] - self.u[1] * self.v[0])

    def as_dict(self) -> dict:
        """JSON-ready: ``u``, ``v``, ``angles_deg``, ``lengths_px``, ``confidence``."""
        return {"u": [round(float(c), 3) for c in self.u],
                "v": [round(float(c), 3) for c in self.v],
                "angles_deg": [round(a, 3) for a in self.angles_deg],
                "lengths_px": [round(n, 3) for n in self.lengths_px],
                "confidence": round(float(self.confidence), 4)}


def _angle(d: np.ndarray) -> float:
    """Direction of ``(dy, dx)`` in ``(-90, 90]`` degrees (a line, not an arrow)."""
    a = float(np.degrees(np.arctan2(d[0], d[1])))
    while a <= -90.0:
        a += 180.0
    while a > 90.0:
        a -= 180.0
    return a


def _line_difference(a: float | np.ndarray, b: float) -> np.ndarray:
    """Angle between lines of directions ``a`` and ``b`` (degrees, in ``[0, 90]``)."""
    d = np.abs((np.asarray(a) - b) % 180.0)
    return np.minimum(d, 180.0 - d)


def spectrum_directions(gray: np.ndarray) -> tuple[float, float]:
    """Directions (degrees) of the two largest Fourier coefficients >= 10 degrees apart."""
    h, w = gray.shape
    window = np.outer(np.hanning(h), np.hanning(w))
    amp = np.abs(np.fft.fftshift(np.fft.fft2((gray - gray.mean()) * window)))
    fy = np.fft.fftshift(np.fft.fftfreq(h))[:, None] * np.ones((1, w))
    fx = np.fft.fftshift(np.fft.fftfreq(w))[None, :] * np.ones((h, 1))
    near_dc = np.hypot(fy * h, fx * w) < 2.0
    amp[near_dc] = 0.0
    order = np.argsort(amp, axis=None)[::-1]
    angles = np.degrees(np.arctan2(fy.ravel()[order], fx.ravel()[order]))
    first = float(angles[0])
    apart = np.flatnonzero(_line_difference(angles, first) > MIN_SEPARATION_DEG)
    second = float(angles[apart[0]]) if apart.size else first + 90.0
    return _angle(np.array([np.sin(np.radians(first)), np.cos(np.radians(first))])), _angle(
        np.array([np.sin(np.radians(second)), np.cos(np.radians(second))]))


def autocorrelation(gray: np.ndarray) -> np.ndarray:
    """Normalised autocorrelation for lags ``(-h/2..h/2, -w/2..w/2)``, centred (see module)."""
    g = np.asarray(gray, np.float64)
    h, w = g.shape
    g = g - ndimage.gaussian_filter(g, sigma=max(h, w) / 8.0, mode="reflect")
    g = g - g.mean()
    shape = (next_fast_len(2 * h, real=True), next_fast_len(2 * w, real=True))
    spec = rfft2(g, shape)
    num = irfft2(np.abs(spec) ** 2, shape)
    ones = rfft2(np.ones_like(g), shape)
    count = np.maximum(np.rint(irfft2(np.abs(ones) ** 2, shape)), 1.0)
    var = float(np.mean(g**2)) or 1.0
    corr = num / count / var
    hy, hx = h // 2, w // 2
    rows = np.r_[-hy:hy + 1] % shape[0]
    cols = np.r_[-hx:hx + 1] % shape[1]
    return corr[np.ix_(rows, cols)]


def _subpixel(corr: np.ndarray, y: int, x: int) -> tuple[float, float, float]:
    """Quadratic-fit peak position and value around the integer maximum ``(y, x)``."""
    def offset(a, b, c):
        den = a - 2 * b + c
        return 0.0 if den >= 0 else float(np.clip(0.5 * (a - c) / den, -0.5, 0.5))

    h, w = corr.shape
    if not (0 < y < h - 1 and 0 < x < w - 1):
        return float(y), float(x), float(corr[y, x])
    dy = offset(corr[y - 1, x], corr[y, x], corr[y + 1, x])
    dx = offset(corr[y, x - 1], corr[y, x], corr[y, x + 1])
    return y + dy, x + dx, float(corr[y, x])


def _reduce(u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lagrange-Gauss reduction: the shortest basis of the lattice spanned by ``u``, ``v``."""
    u, v = u.astype(float), v.astype(float)
    for _ in range(64):
        if v @ v < u @ u:
            u, v = v, u
        k = round(float(v @ u) / float(u @ u))
        if k == 0:
            break
        v = v - k * u
    return u, v


def _canonical(d: np.ndarray) -> np.ndarray:
    """The sign of a lattice vector that points right (down when within 0.5 px of vertical)."""
    return -d if (d[1] < -0.5 or (abs(d[1]) <= 0.5 and d[0] < 0)) else d


def _on_lattice(p: np.ndarray, u: np.ndarray, v: np.ndarray, tol: float = 0.15) -> bool:
    coef = np.linalg.solve(np.stack([u, v], axis=1), p)
    return bool(np.all(np.abs(coef - np.rint(coef)) < tol))


def detect_lattice(gray: np.ndarray) -> Lattice:
    """The two periodicity vectors of a grey-scale image, and the confidence (see module)."""
    gray = np.asarray(gray, np.float64)
    if gray.ndim != 2 or min(gray.shape) < 16:
        raise ValueError(f"need a grey-scale image of at least 16 x 16, got {gray.shape}")
    sectors = spectrum_directions(gray)
    corr = autocorrelation(gray)
    cy, cx = corr.shape[0] // 2, corr.shape[1] // 2
    peaks = (ndimage.maximum_filter(corr, size=3, mode="constant", cval=-np.inf) == corr)
    peaks &= corr > PEAK_FLOOR
    ys, xs = np.nonzero(peaks)
    lags = np.stack([ys - cy, xs - cx], axis=1).astype(float)
    keep = np.hypot(lags[:, 0], lags[:, 1]) >= 2.0
    lags, values = lags[keep], corr[ys[keep], xs[keep]]
    if lags.shape[0] == 0:
        return Lattice((0.0, 0.0), (0.0, 0.0), 0.0, sectors)
    angles = np.array([_angle(d) for d in lags])
    sector = _line_difference(angles, sectors[0]) > _line_difference(angles, sectors[1])
    chosen = []
    for s in (False, True):
        inside = sector == s
        if not inside.any():
            continue
        strong = inside & (values >= SAME_CORRELATION * values[inside].max())
        lengths = np.where(strong, np.hypot(lags[:, 0], lags[:, 1]), np.inf)
        chosen.append(lags[int(np.argmin(lengths))])
    if len(chosen) < 2 or abs(chosen[0][0] * chosen[1][1] - chosen[0][1] * chosen[1][0]) < 1:
        return Lattice(tuple(chosen[0]), (0.0, 0.0), 0.0, sectors)
    u, v = _reduce(chosen[0], chosen[1])
    strong = values >= SAME_CORRELATION * min(_value(corr, u), _value(corr, v))
    for p in lags[strong][np.argsort(np.hypot(*lags[strong].T))]:
        if not _on_lattice(p, u, v):
            a, b = _reduce(u, p)
            if abs(a[0] * b[1] - a[1] * b[0]) >= 1:
                u, v = a, b
    u, v = _refine(corr, u, v)
    u, v = _reduce(u, v)
    u, v = _canonical(u), _canonical(v)
    if _angle(v) < _angle(u):
        u, v = v, u
    confidence = float(np.clip(min(_value(corr, u), _value(corr, v)), 0.0, 1.0))
    return Lattice((float(u[0]), float(u[1])), (float(v[0]), float(v[1])), confidence, sectors)


def _value(corr: np.ndarray, d: np.ndarray) -> float:
    """Autocorrelation at the lag nearest ``d`` (``-inf`` outside the computed lags)."""
    cy, cx = corr.shape[0] // 2, corr.shape[1] // 2
    y, x = round(cy + d[0]), round(cx + d[1])
    if not (0 <= y < corr.shape[0] and 0 <= x < corr.shape[1]):
        return -np.inf
    return float(corr[y, x])


def _refine(corr: np.ndarray, u: np.ndarray, v: np.ndarray, reach: int = 3
            ) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares ``u``, ``v`` from the sub-pixel maxima near ``i u + j v``."""
    cy, cx = corr.shape[0] // 2, corr.shape[1] // 2
    h, w = corr.shape
    for _ in range(2):
        coefs, points, weights = [], [], []
        for i in range(-reach, reach + 1):
            for j in range(-reach, reach + 1):
                if (i, j) == (0, 0):
                    continue
                p = i * u + j * v
                y, x = round(cy + p[0]), round(cx + p[1])
                if not (1 <= y < h - 1 and 1 <= x < w - 1):
                    continue
                win = corr[y - 1 : y + 2, x - 1 : x + 2]
                oy, ox = np.unravel_index(int(np.argmax(win)), win.shape)
                py, px, val = _subpixel(corr, y - 1 + oy, x - 1 + ox)
                if val < PEAK_FLOOR:
                    continue
                coefs.append((i, j))
                points.append((py - cy, px - cx))
                weights.append(val)
        if len(points) < 2:
            break
        a = np.asarray(coefs, float) * np.sqrt(weights)[:, None]
        b = np.asarray(points) * np.sqrt(weights)[:, None]
        sol, *_ = np.linalg.lstsq(a, b, rcond=None)
        if np.linalg.matrix_rank(a) < 2:
            break
        u, v = sol[0], sol[1]
    return u, v

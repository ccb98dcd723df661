"""Periodicity detection: the two periodicity vectors of a texture (paper 004, section 2).

The paper takes the directions of the two largest Fourier coefficients, splits the half-plane
of directions into two sectors around them and, in each sector, the autocorrelation maximum with
the smallest period. On rotated and oblique lattices the two largest coefficients often belong
to one lattice row (a harmonic, or a diagonal of the cell), so a sector holds no basis vector and
the detection fails. This module keeps the paper's ingredients (the autocorrelation, its maxima,
the smallest period among strong maxima) but picks the basis by a rule that does not depend on
directions:

- **Autocorrelation**: of the image with its illumination removed (minus a broad Gaussian blur,
  sigma = size / 8, divided by the local contrast at the same scale), zero-padded and normalised
  per lag by the overlap and the variance, so that a perfectly periodic image scores 1 at its
  lattice vectors; lags up to half the image.
- **Candidates**: the local maxima (3 x 3) above 0.15 with a prominence of at least 0.03
  (skimage's ``h_maxima``: the ridges of line textures carry maxima without prominence), at
  least 2 px from the origin, one of each +- pair; the 24 shortest.
- **Basis**: every pair of candidates spanning a cell of at least 4 px^2 is reduced
  (Lagrange-Gauss: the shortest basis of its lattice) and scored by the weakest autocorrelation
  maximum within a pixel of ``u``, ``v``, ``u + v`` and ``u - v``. A lattice finer than the
  texture's has a basis vector off the texture's lattice, so it scores low; a coarser one (a
  sub-lattice) scores about as high but has a larger cell. The smallest cell scoring at least 90%
  of the best wins (the paper's "smallest period among maxima of about the same correlation").
- **Sub-pixel vectors**: the maxima near ``i u + j v`` (``|i|, |j| <= 3``) are located to
  sub-pixel precision by quadratic fits and ``u``, ``v`` fitted to all of them by least squares,
  so rotated lattices are not limited to integer lags.
- **Confidence**: the score of the refined basis (0 if there is none): about 1 for a strictly
  periodic texture, under 0.3 for a stochastic one.

Vectors are ``(dy, dx)`` in pixels; angles are degrees from the image's +x axis (columns)
towards +y (rows), in ``(-90, 90]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy  # submodules load on first use, not at every btf command (test_layout: HEAVY)
import skimage

CANDIDATES = 24
MIN_AREA = 4.0
SAME_CORRELATION = 0.9
PROMINENCE = 0.03
ANTIALIAS = 1.0
PEAK_FLOOR = 0.15


@dataclass(frozen=True)
class Lattice:
    """Two periodicity vectors ``u``, ``v`` (``(dy, dx)`` pixels) and the confidence."""

    u: tuple[float, float]
    v: tuple[float, float]
    confidence: float

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


def autocorrelation(gray: np.ndarray) -> np.ndarray:
    """Normalised autocorrelation for lags ``(-h/2..h/2, -w/2..w/2)``, centred (see module)."""
    g = np.asarray(gray, np.float64)
    h, w = g.shape
    sigma = max(h, w) / 8.0
    g = scipy.ndimage.gaussian_filter(g, ANTIALIAS, mode="reflect")
    g = g - scipy.ndimage.gaussian_filter(g, sigma, mode="reflect")
    contrast = np.sqrt(scipy.ndimage.gaussian_filter(g * g, sigma, mode="reflect"))
    g = g / np.maximum(contrast, 1e-6 * max(float(contrast.max()), 1e-300))
    g = g - g.mean()
    shape = (scipy.fft.next_fast_len(2 * h, real=True), scipy.fft.next_fast_len(2 * w, real=True))
    spec = scipy.fft.rfft2(g, shape)
    num = scipy.fft.irfft2(np.abs(spec) ** 2, shape)
    ones = scipy.fft.rfft2(np.ones_like(g), shape)
    count = np.maximum(np.rint(scipy.fft.irfft2(np.abs(ones) ** 2, shape)), 1.0)
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


def reduce_basis(u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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


def _peak_map(corr: np.ndarray) -> np.ndarray:
    """``corr`` at its local maxima above the floor and 2 px or more from the origin, else -inf."""
    cy, cx = corr.shape[0] // 2, corr.shape[1] // 2
    yy, xx = np.ogrid[-cy : corr.shape[0] - cy, -cx : corr.shape[1] - cx]
    peak = scipy.ndimage.maximum_filter(corr, size=3, mode="constant", cval=-np.inf) == corr
    peak &= skimage.morphology.h_maxima(corr, PROMINENCE).astype(bool)
    peak &= (corr > PEAK_FLOOR) & (yy * yy + xx * xx >= 4)
    return np.where(peak, corr, -np.inf)


def _near_peak(peaks: np.ndarray, d: np.ndarray) -> float:
    """The largest value of ``peaks`` within a pixel of lag ``d`` (``-inf`` if none)."""
    cy, cx = peaks.shape[0] // 2, peaks.shape[1] // 2
    y, x = round(cy + float(d[0])), round(cx + float(d[1]))
    if not (1 <= y < peaks.shape[0] - 1 and 1 <= x < peaks.shape[1] - 1):
        return -np.inf
    return float(peaks[y - 1 : y + 2, x - 1 : x + 2].max())


def _score(peaks: np.ndarray, u: np.ndarray, v: np.ndarray) -> float:
    """The weakest maximum near ``u``, ``v``, ``u + v`` and ``u - v`` (see module)."""
    return min(_near_peak(peaks, d) for d in (u, v, u + v, u - v))


def _candidates(peaks: np.ndarray) -> np.ndarray:
    """The shortest local maxima of the autocorrelation, one of each +- pair (see module)."""
    cy, cx = peaks.shape[0] // 2, peaks.shape[1] // 2
    ys, xs = np.nonzero(np.isfinite(peaks))
    lags = np.stack([ys - cy, xs - cx], axis=1).astype(float)
    half = (lags[:, 1] > 0) | ((lags[:, 1] == 0) & (lags[:, 0] > 0))
    lags = lags[half]
    return lags[np.argsort(np.hypot(lags[:, 0], lags[:, 1]), kind="stable")][:CANDIDATES]


def detect_lattice(gray: np.ndarray) -> Lattice:
    """The two periodicity vectors of a grey-scale image, and the confidence (see module)."""
    gray = np.asarray(gray, np.float64)
    if gray.ndim != 2 or min(gray.shape) < 16:
        raise ValueError(f"need a grey-scale image of at least 16 x 16, got {gray.shape}")
    corr = autocorrelation(gray)
    peaks = _peak_map(corr)
    lags = _candidates(peaks)
    bases = []
    for i in range(len(lags)):
        for j in range(i + 1, len(lags)):
            area = abs(lags[i, 0] * lags[j, 1] - lags[i, 1] * lags[j, 0])
            if area >= MIN_AREA:
                u, v = reduce_basis(lags[i], lags[j])
                bases.append((_score(peaks, u, v), area, u, v))
    if not bases:
        return Lattice((0.0, 0.0), (0.0, 0.0), 0.0)
    best = max(score for score, *_ in bases)
    if best <= PEAK_FLOOR:
        return Lattice((0.0, 0.0), (0.0, 0.0), max(best, 0.0))
    _, _, u, v = min((b for b in bases if b[0] >= SAME_CORRELATION * best),
                     key=lambda b: (round(b[1], 6), -b[0]))
    refined = reduce_basis(*_refine(corr, peaks, u, v))
    if abs(np.linalg.det(np.stack(refined))) >= MIN_AREA:
        u, v = refined
    u, v = _canonical(u), _canonical(v)
    if _angle(v) < _angle(u):
        u, v = v, u
    confidence = float(np.clip(_score(peaks, u, v), 0.0, 1.0))
    return Lattice((float(u[0]), float(u[1])), (float(v[0]), float(v[1])), confidence)


def _refine(corr: np.ndarray, peaks: np.ndarray, u: np.ndarray, v: np.ndarray, reach: int = 3
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
                win = peaks[y - 1 : y + 2, x - 1 : x + 2]
                if not np.isfinite(win.max()):
                    continue
                oy, ox = np.unravel_index(int(np.argmax(win)), win.shape)
                py, px, val = _subpixel(corr, y - 1 + oy, x - 1 + ox)
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

"""Random periodic and stochastic textures with known lattices, for judging periodicity detection.

Every periodic texture is drawn with :func:`random_lattice_texture`: a primitive lattice (any
orientation, oblique or not, reduced periods 6-64 px), one of four motifs, optional noise (up to
20% of the contrast) and a smooth multiplicative illumination gradient, on a non-square image at
least four periods across. The motif is drawn in the lattice's fractional coordinates ``(a, b)``
so the primitive lattice is known exactly:

- ``blobs``: a soft elliptical blob per cell;
- ``lines``: a grid of lines along both basis vectors;
- ``checkers``: two-tone cells; its primitive lattice is the half-diagonal one, ``(u +- v) / 2``;
- ``weave``: a cell showing two thin threads in one half and one wide crossing thread in the
  other (no sub-period).

:func:`stochastic_texture` draws the negatives: white noise and fBm (power spectrum ``1/f^beta``).
:func:`judge` compares a detected basis with the truth basis-independently: both vectors on the
true lattice (within ``px`` pixels of a lattice point) and the cell area within 5%.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy  # submodules load on first use, not at every btf command (test_layout: HEAVY)

from tasks.periodicity import reduce_basis

MOTIFS = ("blobs", "lines", "checkers", "weave")


@dataclass(frozen=True)
class Case:
    image: np.ndarray
    u: np.ndarray  # the primitive lattice, (dy, dx) pixels
    v: np.ndarray
    motif: str
    noise: float
    gradient: float

    def describe(self) -> str:
        lengths = np.hypot(*self.u), np.hypot(*self.v)
        angle = np.degrees(np.arccos(abs(self.u @ self.v) / lengths[0] / lengths[1]))
        return (f"{self.motif} {self.image.shape[0]}x{self.image.shape[1]} periods "
                f"{lengths[0]:.1f}/{lengths[1]:.1f} px at {np.degrees(np.arctan2(*self.u)):.0f} "
                f"deg, {angle:.0f} deg apart, noise {self.noise:.2f}, gradient {self.gradient:.2f}")


def _primitive(rng: np.random.Generator, low: float, high: float):
    while True:
        theta = rng.uniform(0.0, np.pi)
        between = rng.uniform(np.radians(35.0), np.radians(145.0))
        lengths = rng.uniform(low, high, 2)
        u = lengths[0] * np.array([np.sin(theta), np.cos(theta)])
        v = lengths[1] * np.array([np.sin(theta + between), np.cos(theta + between)])
        u, v = reduce_basis(u, v)
        if low <= np.hypot(*u) and np.hypot(*v) <= high:
            return u, v


def _motif(name: str, a: np.ndarray, b: np.ndarray, u, v, rng) -> np.ndarray:
    fa, fb = a - np.floor(a), b - np.floor(b)
    area = abs(u[0] * v[1] - u[1] * v[0])
    # pixel distances across the lines a = const (spacing area / |v|) and b = const
    ha, hb = area / np.hypot(*v), area / np.hypot(*u)
    if name == "blobs":
        da, db = fa - 0.5, fb - 0.5
        d = da[..., None] * u + db[..., None] * v
        sx, sy = rng.uniform(0.12, 0.25) * min(ha, hb), rng.uniform(0.12, 0.25) * min(ha, hb)
        return np.exp(-0.5 * ((d[..., 0] / sy) ** 2 + (d[..., 1] / sx) ** 2))
    if name == "lines":
        width = rng.uniform(1.5, max(1.6, 0.25 * min(ha, hb)))
        da = np.minimum(fa, 1 - fa) * ha
        db = np.minimum(fb, 1 - fb) * hb
        return np.maximum(np.exp(-0.5 * (da / (0.5 * width)) ** 2),
                          rng.uniform(0.5, 1.0) * np.exp(-0.5 * (db / (0.5 * width)) ** 2))
    if name == "checkers":
        return 0.5 + 0.5 * np.tanh(4.0 * np.sin(2 * np.pi * a) * np.sin(2 * np.pi * b))
    if name == "weave":
        left = fa < 0.5
        along = np.abs(np.sin(2 * np.pi * fa))  # each half: 0 at its ends, 1 in its middle
        two_threads = np.sin(np.pi * (2 * fb % 1.0)) ** 0.5 * along ** 0.3
        one_thread = np.sin(np.pi * fb) ** 0.7 * along ** 0.5
        return np.where(left, 0.9 * two_threads, one_thread)
    raise ValueError(name)


def random_lattice_texture(rng: np.random.Generator, motif: str | None = None,
                           noise: float | None = None, gradient: float | None = None,
                           low: float = 6.0, high: float = 64.0, max_side: int = 384) -> Case:
    """One random periodic texture and its primitive lattice (see module)."""
    motif = motif or MOTIFS[int(rng.integers(len(MOTIFS)))]
    p, q = _primitive(rng, low, high)
    # the motif's own basis: for checkers the primitive lattice is the half-diagonal one
    u, v = (p + q, p - q) if motif == "checkers" else (p, q)
    longest = max(np.hypot(*p), np.hypot(*q))
    least = max(96, int(np.ceil(4 * longest)))
    shape = tuple(int(rng.integers(least, max(least + 1, max_side) + 1)) for _ in range(2))
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]].astype(float)
    origin = rng.uniform(0, 1, 2) * 50
    a, b = np.einsum("ij,jyx->iyx", np.linalg.inv(np.stack([u, v], axis=1)),
                     np.stack([yy - origin[0], xx - origin[1]]))
    image = scipy.ndimage.gaussian_filter(_motif(motif, a, b, u, v, rng), 0.5, mode="wrap")
    image = (image - image.min()) / max(float(image.max() - image.min()), 1e-12)
    noise = float(rng.choice([0.0, rng.uniform(0.02, 0.2)])) if noise is None else noise
    image = image + noise * rng.standard_normal(shape)
    gradient = float(rng.uniform(0.0, 0.6)) if gradient is None else gradient
    direction = rng.normal(size=2)
    ramp = (direction[0] * (yy / shape[0] - 0.5) + direction[1] * (xx / shape[1] - 0.5))
    ramp = ramp / max(float(np.abs(ramp).max()), 1e-12)
    image = (0.2 + 0.6 * image) * (1.0 + gradient * ramp)
    return Case(image, p, q, motif, noise, gradient)


def stochastic_texture(rng: np.random.Generator, kind: str, shape=(256, 256)) -> np.ndarray:
    """White ``noise`` or ``fbm`` (1/f^beta spectrum, beta in [1.5, 3]): no periodicity."""
    white = rng.standard_normal(shape)
    if kind == "noise":
        return 0.5 + 0.1 * white
    if kind != "fbm":
        raise ValueError(kind)
    fy = np.fft.fftfreq(shape[0])[:, None]
    fx = np.fft.rfftfreq(shape[1])[None, :]
    f = np.hypot(fy, fx)
    f[0, 0] = 1.0
    spectrum = np.fft.rfft2(white) / f ** (rng.uniform(1.5, 3.0) / 2)
    spectrum[0, 0] = 0.0
    image = np.fft.irfft2(spectrum, shape)
    return 0.5 + 0.15 * image / image.std()


def judge(found_u, found_v, u, v, px: float = 1.0, area_tol: float = 0.05) -> bool:
    """Both found vectors within ``px`` of the true lattice and the cell area within 5%."""
    basis = np.stack([np.asarray(u, float), np.asarray(v, float)], axis=1)
    for d in (found_u, found_v):
        d = np.asarray(d, float)
        if not np.any(d):
            return False
        coef = np.linalg.solve(basis, d)
        if np.hypot(*(d - basis @ np.rint(coef))) > px:
            return False
    area = abs(basis[0, 0] * basis[1, 1] - basis[0, 1] * basis[1, 0])
    found = abs(found_u[0] * found_v[1] - found_u[1] * found_v[0])
    return abs(found - area) <= area_tol * area


def failure_mode(found_u, found_v, u, v, px: float = 1.0) -> str:
    """Why a detection missed: no lattice, a finer or coarser cell, or vectors off the lattice."""
    if not (np.any(found_u) and np.any(found_v)):
        return "no lattice"
    true_area = abs(u[0] * v[1] - u[1] * v[0])
    area = abs(found_u[0] * found_v[1] - found_u[1] * found_v[0])
    if area < 0.95 * true_area:
        return "finer cell"
    on = judge(found_u, found_u, u, v, px, area_tol=np.inf) and judge(found_v, found_v, u, v, px,
                                                                      area_tol=np.inf)
    if area > 1.05 * true_area:
        return "coarser cell (a sub-lattice)" if on else "wrong lattice"
    return "off by over a pixel"


def detection_rates(count: int, seed: int, threshold: float) -> dict:
    """Detection over ``count`` random lattices and a set of stochastic textures (see module)."""
    import time

    from tasks.periodicity import detect_lattice

    rng = np.random.default_rng(seed)
    rows, seconds = [], 0.0
    for i in range(count):
        case = random_lattice_texture(rng, motif=MOTIFS[i % len(MOTIFS)])
        start = time.perf_counter()
        lattice = detect_lattice(case.image)
        seconds += time.perf_counter() - start
        good = lattice.confidence >= threshold and judge(lattice.u, lattice.v, case.u, case.v)
        mode = "" if good else ("low confidence" if lattice.confidence < threshold
                                and judge(lattice.u, lattice.v, case.u, case.v)
                                else failure_mode(lattice.u, lattice.v, case.u, case.v))
        rows.append({"motif": case.motif, "noise": case.noise, "gradient": case.gradient,
                     "shortest": float(np.hypot(*case.u)), "longest": float(np.hypot(*case.v)),
                     "pixels": int(case.image.size), "found": bool(good), "mode": mode,
                     "confidence": lattice.confidence, "case": case.describe()})
    negatives = {}
    for kind in ("noise", "fbm"):
        for k in range(10):
            image = stochastic_texture(rng, kind, (int(rng.integers(128, 385)),
                                                   int(rng.integers(128, 385))))
            negatives[f"{kind}-{k}"] = detect_lattice(image).confidence
    from tasks.materials import Material

    for k in range(4):
        albedo = Material("stone", seed=k).fields(0, 0, 256, 256).albedo
        negatives[f"stone-{k}"] = detect_lattice(albedo @ np.array([0.2126, 0.7152, 0.0722])
                                                 ).confidence
    return {"count": count, "seed": seed, "threshold": threshold, "rows": rows,
            "seconds_per_image": seconds / max(count, 1), "negatives": negatives}

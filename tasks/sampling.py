"""Direction samplings of the hemisphere: where the lights and the cameras are.

Angles are in degrees. ``theta`` is measured from the surface normal; ``phi`` is the azimuth
measured from the image's +x axis (increasing columns) towards its +y axis, which points to the
top of the picture (decreasing rows: row 0 is the top row): a right-handed frame with z the
normal towards the viewer (docs/formats.md, "The frame"). A BTF holds every
(view, light) combination of its sampling; an ABTF (paper 003) has one view straight above.

``dome151``
    151 directions on 8 rings, theta = 0 to 75 degrees in equal steps, ring populations
    proportional to the ring's circumference (1, 6, 12, 18, 23, 27, 31, 33), alternate rings
    rotated by half a step: the near-uniform layout of the Bonn dome.
``ubo2014``
    Bonn's "Dome 1" of the UBO2014 database: 151 directions as lights and views (151 x 151),
    rings at theta 0, 11, 23.5, 30, 37.5, 45, 52.5, 60, 67.5, 75 degrees with 1, 6, 12, 12,
    12, 18, 18, 24, 24, 24 directions, phi evenly spaced from the ring's offset 0, 15, 0, 15,
    0, 0, 7.5, 0, 7.5, 0 degrees. Bonn's files give phi wrapped to (-180, 180]; here, as in
    every store, phi is in [0, 360), and ingest maps phi into that range
    (:func:`canonical_direction`).
``ubo2003`` (alias ``ubo81``)
    The 81 directions of the UBO2003, ATRIUM and UTIA BTF databases as lights and views
    (81 x 81): rings at 0, 15, ..., 75 degrees with 1, 6, 12, 18, 20, 24 directions, the first
    at azimuth 0 on every ring.
``abtf:R,E``
    One top view; R light rotations x E light elevations, elevations at the centres of E equal
    bins of 0-90 degrees (the quarter light arc and turntable of paper 003). Lights are ordered
    rotation-major (all elevations of the first rotation first).
``hemi:N``
    N directions (the top one, then a Fibonacci spiral out to 75 degrees) used as both lights
    and views: small full BTFs for tests.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

_GOLDEN_ANGLE = 180.0 * (3.0 - math.sqrt(5.0))


def btf_kind(theta_view: np.ndarray) -> str:
    """``"abtf"`` for a single view straight above the sample (paper 003), else ``"btf"``."""
    theta_view = np.asarray(theta_view)
    return "abtf" if theta_view.size == 1 and float(theta_view.ravel()[0]) == 0.0 else "btf"


@dataclass(frozen=True)
class Directions:
    """View and light directions of a BTF, in degrees (float64 arrays)."""

    theta_view: np.ndarray
    phi_view: np.ndarray
    theta_light: np.ndarray
    phi_light: np.ndarray

    @property
    def kind(self) -> str:
        """``"abtf"`` or ``"btf"`` (see :func:`btf_kind`)."""
        return btf_kind(self.theta_view)

    @property
    def views(self) -> int:
        """Number of view directions."""
        return int(np.size(self.theta_view))

    @property
    def lights(self) -> int:
        """Number of light directions."""
        return int(np.size(self.theta_light))

    @staticmethod
    def of(ds) -> Directions:
        """The directions of an opened Dataset (or any mapping of the four coordinates)."""
        return Directions(*(np.asarray(ds[name].values, np.float64) for name in
                            ("theta_view", "phi_view", "theta_light", "phi_light")))

    def select(self, views, lights) -> Directions:
        """The directions of some views and lights (index lists)."""
        v, li = list(views), list(lights)
        return Directions(self.theta_view[v], self.phi_view[v], self.theta_light[li],
                          self.phi_light[li])


@dataclass(frozen=True)
class Sampling(Directions):
    """A named direction sampling (:func:`parse_sampling`)."""

    name: str = ""


def _rings(thetas, counts, *, stagger: bool = False, offsets=None
           ) -> tuple[np.ndarray, np.ndarray]:
    """Rings of evenly spaced directions, the first ring's first direction first.

    ``stagger`` turns alternate rings by half a step; ``offsets`` (degrees, one per ring)
    turns each ring by its own angle.
    """
    offsets = [0.0] * len(thetas) if offsets is None else offsets
    theta, phi = [], []
    for k, (t, n, deg) in enumerate(zip(thetas, counts, offsets, strict=True)):
        offset = 0.5 if stagger and k % 2 == 0 else 0.0
        theta += [float(t)] * n
        phi += [(float(deg) + 360.0 * (j + offset) / n) % 360.0 for j in range(n)]
    return np.array(theta), np.array(phi)


def _dome151() -> tuple[np.ndarray, np.ndarray]:
    thetas = np.linspace(0.0, 75.0, 8)
    weight = np.sin(np.radians(thetas[1:]))
    ideal = 150 * weight / weight.sum()
    counts = np.floor(ideal).astype(int)
    counts[np.argsort(counts - ideal)[: 150 - counts.sum()]] += 1  # largest remainders
    return _rings(thetas, [1, *counts.tolist()], stagger=True)


def _ubo2003() -> tuple[np.ndarray, np.ndarray]:
    return _rings([0, 15, 30, 45, 60, 75], [1, 6, 12, 18, 20, 24])


def _ubo2014() -> tuple[np.ndarray, np.ndarray]:
    return _rings([0, 11, 23.5, 30, 37.5, 45, 52.5, 60, 67.5, 75],
                  [1, 6, 12, 12, 12, 18, 18, 24, 24, 24],
                  offsets=[0, 15, 0, 15, 0, 0, 7.5, 0, 7.5, 0])


_FULL = {"dome151": _dome151, "ubo2014": _ubo2014, "ubo2003": _ubo2003, "ubo81": _ubo2003}


def _hemi(n: int) -> tuple[np.ndarray, np.ndarray]:
    cos_max = math.cos(math.radians(75.0))
    theta, phi = [0.0], [0.0]
    for i in range(1, n):
        z = 1.0 - (i - 0.5) / (n - 1) * (1.0 - cos_max)
        theta.append(math.degrees(math.acos(z)))
        phi.append((i * _GOLDEN_ANGLE) % 360.0)
    return np.array(theta), np.array(phi)


def _ints(spec: str, text: str, count: int) -> list[int]:
    try:
        values = [int(t) for t in text.split(",")]
    except ValueError:
        values = []
    if len(values) != count or min(values) < 1:
        raise ValueError(f"sampling {spec!r}: expected {count} positive integer(s) after ':'")
    return values


SAMPLING_HELP = ("dome151, ubo2014 (Bonn's Dome 1: 151 directions), ubo2003 (the UBO2003/UTIA "
                 "hemisphere: 81 directions; alias ubo81), abtf:R,E (R rotations x E "
                 "elevations, one top view) or hemi:N")


def parse_sampling(spec: str) -> Sampling:
    """Parse a sampling name (see the module docstring) into its directions.

    Raises
    ------
    ValueError
        If the name is unknown or its numbers are malformed.
    """
    name, _, args = spec.partition(":")
    if name in _FULL and not args:
        theta, phi = _FULL[name]()
        return Sampling(theta, phi, theta, phi, name=spec)
    if name == "hemi":
        (n,) = _ints(spec, args, 1)
        theta, phi = _hemi(n)
        return Sampling(theta, phi, theta, phi, name=spec)
    if name == "abtf":
        rotations, elevations = _ints(spec, args, 2)
        elevation = 90.0 * (np.arange(elevations) + 0.5) / elevations
        theta_l = np.tile(90.0 - elevation, rotations)
        phi_l = np.repeat(360.0 * np.arange(rotations) / rotations, elevations)
        return Sampling(np.zeros(1), np.zeros(1), theta_l, phi_l, name=spec)
    raise ValueError(f"unknown sampling {spec!r}; use {SAMPLING_HELP}")


def canonical_direction(theta: float, phi: float) -> tuple[float, float]:
    """A direction in canonical form: phi in [0, 360), and 0 straight above (theta 0).

    Two (theta, phi) pairs name the same direction exactly when their canonical forms agree.
    """
    return theta, (phi % 360.0 if theta > 0 else 0.0)


def direction_vectors(theta_deg: np.ndarray, phi_deg: np.ndarray) -> np.ndarray:
    """Unit vectors ``(x, y, z)`` of directions given in degrees, shape ``(n, 3)``."""
    t = np.radians(np.asarray(theta_deg, np.float64))
    p = np.radians(np.asarray(phi_deg, np.float64))
    return np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1)


def spread_pairs(theta_view, phi_view, theta_light, phi_light, count: int
                 ) -> list[tuple[int, int]]:
    """``count`` (view, light) index pairs spread over the directions (farthest-point sampling).

    Starts from the view and light closest to the normal; each next pair is the one farthest,
    in the joint space of the view and light unit vectors, from those already chosen.
    """
    views = direction_vectors(theta_view, phi_view)
    lights = direction_vectors(theta_light, phi_light)
    pairs = np.array([(v, li) for v in range(len(views)) for li in range(len(lights))])
    points = np.concatenate([views[pairs[:, 0]], lights[pairs[:, 1]]], axis=1)
    first = int(np.lexsort((np.asarray(theta_light)[pairs[:, 1]],
                            np.asarray(theta_view)[pairs[:, 0]]))[0])
    chosen = [first]
    dist = np.linalg.norm(points - points[first], axis=1)
    while len(chosen) < min(count, len(pairs)):
        nxt = int(np.argmax(dist))
        chosen.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(points - points[nxt], axis=1))
    return [(int(pairs[i, 0]), int(pairs[i, 1])) for i in chosen]


def angle_between(theta_a, phi_a, theta_b, phi_b) -> np.ndarray:
    """Angles in degrees between directions ``a`` and ``b`` (broadcast)."""
    a = direction_vectors(np.asarray(theta_a), np.asarray(phi_a))
    b = direction_vectors(np.asarray(theta_b), np.asarray(phi_b))
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1.0, 1.0)))


def nearest_layer(view: tuple[float, float], light: tuple[float, float],
                  views: tuple[np.ndarray, np.ndarray], lights: tuple[np.ndarray, np.ndarray]
                  ) -> tuple[int, int, float]:
    """The (view, light) pair of a sampling nearest to a layer's directions.

    Returns the view and light indices and the larger of the two angular distances (degrees).
    """
    dv = angle_between(view[0], view[1], *views)
    dl = angle_between(light[0], light[1], *lights)
    j, i = int(np.argmin(dv)), int(np.argmin(dl))
    return j, i, float(max(dv[j], dl[i]))


def known_sampling(theta_view, phi_view, theta_light, phi_light, *, tol: float = 0.01
                   ) -> str | None:
    """The name of a measured database's sampling these directions are (in any order).

    ``ubo2014`` or ``ubo2003`` when views and lights are each that sampling's directions to
    within ``tol`` degrees, else None: what a store ingested from a measured file is named.
    """
    def same(theta, phi, ref_theta, ref_phi) -> bool:
        if len(theta) != len(ref_theta):
            return False
        a, b = direction_vectors(theta, phi), direction_vectors(ref_theta, ref_phi)
        gap = np.degrees(np.arccos(np.clip(a @ b.T, -1.0, 1.0))).min(axis=1)
        return bool(gap.max() <= tol)

    for name in ("ubo2014", "ubo2003"):
        theta, phi = _FULL[name]()
        if (same(theta_view, phi_view, theta, phi)
                and same(theta_light, phi_light, theta, phi)):
            return name
    return None

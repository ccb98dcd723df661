"""Radiance in directions that were not measured: nearest and barycentric interpolation.

A scene asks for (light, view) direction pairs; a store holds the measured ones. Each side (the
lights, the views) is interpolated on its own over the measured directions of that side, and a
pair's weights are the products: up to 3 x 3 measured layers per requested pair, weights summing
to one.

``nearest``
    The measured direction at the smallest angle (on the sphere) from the requested one.
``barycentric``
    Measured directions are mapped to the plane by the azimuthal equidistant projection of the
    hemisphere, ``(theta / 90) (cos phi, sin phi)`` (the pole at the centre, the horizon on the
    unit circle; distances from the pole are exact), and triangulated (Delaunay, scipy's
    Qhull); a requested direction gets the barycentric weights of the triangle that holds its
    image. This is the scheme measured-BTF renderers use on their direction maps; it reproduces
    measured directions exactly and is continuous. A direction outside the measured cone (for
    example theta 85 degrees when lights reach 75) takes the weights of the nearest point on the
    triangulation's boundary (two directions), i.e. the radiance is extended constantly outward
    along the boundary's normal. With fewer than three measured directions, or all on one great
    circle through the pole, there is no triangulation and nearest is used.
"""

from __future__ import annotations

import numpy as np

from tasks.errors import InvalidParameter
from tasks.sampling import direction_vectors

METHODS = ("nearest", "barycentric")


def planar(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """The azimuthal equidistant map of the hemisphere, ``(n, 2)``."""
    r = np.asarray(theta, np.float64) / 90.0
    p = np.radians(np.asarray(phi, np.float64))
    return np.stack([r * np.cos(p), r * np.sin(p)], axis=-1)


def nearest(measured_theta, measured_phi, theta, phi) -> np.ndarray:
    """Index of the measured direction at the smallest angle from each requested one."""
    cos = direction_vectors(theta, phi) @ direction_vectors(measured_theta, measured_phi).T
    return np.argmax(np.round(cos, 12), axis=1)  # ties (rounding noise) go to the lower index


def weights(measured_theta, measured_phi, theta, phi, method: str = "barycentric"
            ) -> tuple[np.ndarray, np.ndarray]:
    """Interpolation weights of requested directions over measured ones.

    Returns
    -------
    index, weight
        ``(n, 3)`` arrays: measured direction indices and their weights (rows sum to one;
        unused slots have weight 0 and repeat a used index).
    """
    if method not in METHODS:
        raise InvalidParameter("interpolation", f"must be one of {', '.join(METHODS)}, got "
                                                f"{method!r}")
    mt, mp = np.asarray(measured_theta, np.float64), np.asarray(measured_phi, np.float64)
    theta, phi = np.atleast_1d(np.asarray(theta, np.float64)), np.atleast_1d(
        np.asarray(phi, np.float64))
    near = nearest(mt, mp, theta, phi)
    index = np.repeat(near[:, None], 3, axis=1)
    weight = np.zeros(index.shape)
    weight[:, 0] = 1.0
    if method == "nearest":
        return index, weight
    tri = _triangulation(planar(mt, mp))
    if tri is None:
        return index, weight
    points = planar(theta, phi)
    simplex = tri.find_simplex(points, tol=1e-12)
    inside = simplex >= 0
    if inside.any():
        s = simplex[inside]
        t = tri.transform[s]  # affine maps to barycentric coordinates
        b = np.einsum("nij,nj->ni", t[:, :2], points[inside] - t[:, 2])
        bary = np.concatenate([b, 1.0 - b.sum(axis=1, keepdims=True)], axis=1)
        index[inside] = tri.simplices[s]
        weight[inside] = bary
    if (~inside).any():
        index[~inside], weight[~inside] = _boundary(tri, points[~inside])
    return index, _clean(weight)


def _triangulation(points: np.ndarray):
    from scipy.spatial import Delaunay, QhullError

    if len(points) < 3:
        return None
    try:
        return Delaunay(points)
    except QhullError:  # all points on one line: no triangle
        return None


def _boundary(tri, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weights of the nearest point on the triangulation's boundary (its convex hull)."""
    edges = tri.convex_hull  # (m, 2) point indices
    a, b = tri.points[edges[:, 0]], tri.points[edges[:, 1]]
    d = b - a
    t = np.einsum("pmj,mj->pm", points[:, None, :] - a[None], d) / np.einsum("mj,mj->m", d, d)
    t = np.clip(t, 0.0, 1.0)
    closest = a[None] + t[..., None] * d[None]
    best = np.argmin(np.sum((closest - points[:, None, :]) ** 2, axis=-1), axis=1)
    tb = t[np.arange(len(points)), best]
    index = np.stack([edges[best, 0], edges[best, 1], edges[best, 0]], axis=1)
    weight = np.stack([1.0 - tb, tb, np.zeros_like(tb)], axis=1)
    return index, weight


def _clean(weight: np.ndarray) -> np.ndarray:
    """Weights without rounding noise, rows renormalised to sum to one.

    ``|w| < 1e-12`` becomes 0 and slightly negative weights (a point on a triangle's edge,
    within the search tolerance) are clipped.
    """
    w = np.where(np.abs(weight) < 1e-12, 0.0, weight)
    w = np.clip(w, 0.0, None)
    return w / w.sum(axis=1, keepdims=True)


def pair_weights(lights: tuple[np.ndarray, np.ndarray], views: tuple[np.ndarray, np.ndarray],
                 requests: np.ndarray, method: str = "barycentric"
                 ) -> list[list[tuple[int, int, float]]]:
    """Measured ``(view, light, weight)`` terms of every requested direction pair.

    Parameters
    ----------
    lights, views
        ``(theta, phi)`` of the measured lights and views, degrees.
    requests
        ``(n, 4)``: ``theta_light, phi_light, theta_view, phi_view`` in degrees.

    Returns
    -------
    One list of terms per request: distinct ``(view, light)`` pairs with positive weights
    summing to one (the product of the light's and the view's weights).
    """
    requests = np.asarray(requests, np.float64).reshape(-1, 4)
    li, lw = weights(*lights, requests[:, 0], requests[:, 1], method)
    vi, vw = weights(*views, requests[:, 2], requests[:, 3], method)
    out = []
    for k in range(len(requests)):
        terms: dict[tuple[int, int], float] = {}
        for a in range(3):
            for b in range(3):
                w = vw[k, a] * lw[k, b]
                if w > 0:
                    key = (int(vi[k, a]), int(li[k, b]))
                    terms[key] = terms.get(key, 0.0) + float(w)
        out.append([(v, light, w) for (v, light), w in sorted(terms.items())])
    return out

"""Interpolation of unmeasured directions against brute-force references."""

from __future__ import annotations

import numpy as np
import pytest

from tasks.directions import pair_weights, planar, weights
from tasks.sampling import direction_vectors as unit_vectors
from tasks.sampling import parse_sampling as sampling


def _random_directions(rng, n, theta_max=90.0):
    return rng.uniform(0, theta_max, n), rng.uniform(0, 360, n)


@pytest.mark.parametrize("name", ["dome151", "ubo81", "hemi:17"])
def test_nearest_is_the_smallest_angle(name):
    s = sampling(name)
    rng = np.random.default_rng(1)
    theta, phi = _random_directions(rng, 300)
    index, weight = weights(s.theta_light, s.phi_light, theta, phi, "nearest")
    assert np.all(weight[:, 0] == 1) and np.all(weight[:, 1:] == 0)
    for t, p, i in zip(theta, phi, index[:, 0], strict=True):
        angles = np.degrees(np.arccos(np.clip(
            unit_vectors(s.theta_light, s.phi_light) @ unit_vectors([t], [p])[0], -1, 1)))
        assert angles[i] <= angles.min() + 1e-9


def _brute_barycentric(points, simplices, q):
    """Weights from the first triangle (tried in order) whose barycentric coordinates of q
    are all >= -1e-9: a linear solve per triangle."""
    for tri in simplices:
        a = np.vstack([points[tri].T, np.ones(3)])
        b = np.linalg.solve(a, [q[0], q[1], 1.0])
        if b.min() >= -1e-9:
            return tri, b
    return None, None


@pytest.mark.parametrize("name", ["dome151", "ubo81", "hemi:17", "abtf:12,3"])
def test_barycentric_matches_a_brute_force_solve_and_reproduces_measured(name):
    from scipy.spatial import Delaunay

    s = sampling(name)
    mt, mp = s.theta_light, s.phi_light
    tri = Delaunay(planar(mt, mp))
    rng = np.random.default_rng(2)
    theta, phi = _random_directions(rng, 200, theta_max=float(mt.max()))
    index, weight = weights(mt, mp, theta, phi)
    assert np.allclose(weight.sum(axis=1), 1.0, atol=1e-12) and weight.min() >= 0
    q = planar(theta, phi)
    inside = tri.find_simplex(q) >= 0
    assert inside.sum() > 100
    for k in np.flatnonzero(inside):
        _, b = _brute_barycentric(tri.points, tri.simplices, q[k])
        # the interpolated point is the query: sum w_i p_i == q (whatever triangle was found)
        assert np.allclose(weight[k] @ tri.points[index[k]], q[k], atol=1e-12)
        assert np.allclose(np.sort(weight[k]), np.sort(b), atol=1e-9)
    # measured directions come back as themselves, with weight one
    index, weight = weights(mt, mp, mt, mp)
    for i in range(len(mt)):
        w = {int(j): float(x) for j, x in zip(index[i], weight[i], strict=True) if x > 0}
        same = np.flatnonzero(np.all(planar(mt, mp) == planar(mt[i:i + 1], mp[i:i + 1]),
                                     axis=1))
        assert sum(w.get(int(j), 0.0) for j in same) == pytest.approx(1.0, abs=1e-12)


def test_outside_the_measured_cone_takes_the_nearest_boundary_point():
    s = sampling("dome151")  # lights up to 75 degrees
    index, weight = weights(s.theta_light, s.phi_light, [88.0, 80.0], [10.0, 200.0])
    for i, (t, p) in enumerate(((88.0, 10.0), (80.0, 200.0))):
        used = weight[i] > 0
        assert used.sum() <= 2 and np.all(s.theta_light[index[i][used]] == 75.0)
        # the weighted point lies on the hull, nearer the query than any hull vertex
        pt = weight[i] @ planar(s.theta_light, s.phi_light)[index[i]]
        ring = planar(s.theta_light[s.theta_light == 75], s.phi_light[s.theta_light == 75])
        assert np.linalg.norm(pt - planar([t], [p])[0]) <= np.min(
            np.linalg.norm(ring - planar([t], [p])[0], axis=1)) + 1e-12


def _brdf(tl, pl, tv, pv):
    """A smooth analytic BRDF x cosine: Lambert plus a broad Phong lobe."""
    light, view = unit_vectors(tl, pl), unit_vectors(tv, pv)
    mirror = light * np.array([-1, -1, 1])
    lobe = np.clip(np.sum(mirror * view, axis=-1), 0, None) ** 4
    return light[..., 2] * (0.6 + 0.4 * lobe)


def test_a_smooth_brdf_is_interpolated_within_a_few_percent_of_its_range():
    s = sampling("dome151")
    rng = np.random.default_rng(3)
    n = 500
    req = np.stack([*_random_directions(rng, n, 70), *_random_directions(rng, n, 70)], axis=1)
    table = _brdf(s.theta_light[None, :], s.phi_light[None, :], s.theta_view[:, None],
                  s.phi_view[:, None])  # (view, light)
    truth = _brdf(req[:, 0], req[:, 1], req[:, 2], req[:, 3])
    errors = {}
    for method in ("nearest", "barycentric"):
        terms = pair_weights((s.theta_light, s.phi_light), (s.theta_view, s.phi_view), req,
                             method)
        got = np.array([sum(w * table[v, li] for v, li, w in t) for t in terms])
        assert all(abs(sum(w for *_, w in t) - 1) < 1e-12 for t in terms)
        e = np.abs(got - truth) / np.ptp(table)
        errors[method] = e.max(), np.sqrt(np.mean(e**2))
    # measured on dome151 (seeds 3-5), relative to the BRDF's range: barycentric 3.0-3.6%
    # max, 0.8-0.9% RMS; nearest 13-14% max, 4.0-4.4% RMS
    assert errors["barycentric"][0] < 0.045 and errors["barycentric"][1] < 0.012
    assert errors["barycentric"][1] < errors["nearest"][1] / 3


def test_degenerate_samplings_fall_back_to_nearest():
    # one direction (an ABTF's single view), two directions: no triangle
    for theta, phi in (([0.0], [0.0]), ([0.0, 45.0], [0.0, 90.0])):
        index, weight = weights(theta, phi, [30.0, 44.0], [80.0, 85.0])
        assert np.all(weight[:, 0] == 1)
        assert list(index[:, 0]) == ([0, 0] if len(theta) == 1 else [1, 1])

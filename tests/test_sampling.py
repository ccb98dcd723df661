from __future__ import annotations

import numpy as np
import pytest

from tasks.sampling import direction_vectors, parse_sampling, spread_pairs


def _unique_dirs(theta, phi):
    v = direction_vectors(theta, phi)
    return len(np.unique(np.round(v, 9), axis=0))


@pytest.mark.parametrize(("spec", "views", "lights", "kind"), [
    ("dome151", 151, 151, "btf"), ("ubo81", 81, 81, "btf"), ("ubo2003", 81, 81, "btf"),
    ("ubo2014", 151, 151, "btf"), ("abtf:24,8", 1, 192, "abtf"),
    ("abtf:1,1", 1, 1, "abtf"), ("hemi:5", 5, 5, "btf"), ("hemi:1", 1, 1, "abtf"),
])
def test_samplings_have_their_sizes_and_distinct_directions(spec, views, lights, kind):
    s = parse_sampling(spec)
    assert (s.theta_view.size, s.theta_light.size, s.kind) == (views, lights, kind)
    assert _unique_dirs(s.theta_light, s.phi_light) == lights
    assert _unique_dirs(s.theta_view, s.phi_view) == views
    for theta, phi in ((s.theta_view, s.phi_view), (s.theta_light, s.phi_light)):
        assert theta.min() >= 0 and theta.max() < 90
        assert phi.min() >= 0 and phi.max() < 360


def test_ubo81_rings_are_those_of_the_databases():
    s = parse_sampling("ubo81")
    theta, counts = np.unique(s.theta_light, return_counts=True)
    assert theta.tolist() == [0, 15, 30, 45, 60, 75]
    assert counts.tolist() == [1, 6, 12, 18, 20, 24]


def test_ubo81_is_an_alias_of_ubo2003():
    a, b = parse_sampling("ubo81"), parse_sampling("ubo2003")
    for name in ("theta_view", "phi_view", "theta_light", "phi_light"):
        assert np.array_equal(getattr(a, name), getattr(b, name))
    # 75-degree ring: 24 directions 15 degrees apart from phi 0
    assert np.array_equal(b.phi_light[b.theta_light == 75], 15.0 * np.arange(24))
    assert np.array_equal(b.phi_light[b.theta_light == 60], 18.0 * np.arange(20))


@pytest.mark.parametrize("spec", ["ubo2014", "ubo2003"])
def test_ubo_samplings_are_full_btfs(spec):
    s = parse_sampling(spec)
    assert s.kind == "btf"
    assert np.array_equal(s.theta_view, s.theta_light)
    assert np.array_equal(s.phi_view, s.phi_light)


UBO2014_RINGS = [  # theta, directions, phi of the first direction (Bonn's "Dome 1")
    (0, 1, 0), (11, 6, 15), (23.5, 12, 0), (30, 12, 15), (37.5, 12, 0), (45, 18, 0),
    (52.5, 18, 7.5), (60, 24, 0), (67.5, 24, 7.5), (75, 24, 0),
]


def test_ubo2014_rings_are_those_of_bonns_dome():
    s = parse_sampling("ubo2014")
    theta, counts = np.unique(s.theta_light, return_counts=True)
    assert theta.tolist() == [t for t, _, _ in UBO2014_RINGS]
    assert counts.tolist() == [n for _, n, _ in UBO2014_RINGS]
    for t, n, first in UBO2014_RINGS:
        phi = s.phi_light[s.theta_light == t]
        assert np.allclose(phi, first + 360.0 * np.arange(n) / n, atol=1e-12), t


def test_ubo2014_exact_directions():
    s = parse_sampling("ubo2014")
    pairs = set(zip(s.theta_light.tolist(), s.phi_light.tolist(), strict=True))
    for d in [(0, 0), (11, 15), (11, 75), (11, 315), (23.5, 0), (23.5, 330), (30, 15),
              (30, 345), (45, 20), (52.5, 7.5), (52.5, 27.5), (52.5, 347.5), (60, 15),
              (67.5, 7.5), (67.5, 352.5), (75, 345)]:
        assert d in pairs, d
    for d in [(11, 0), (52.5, 0), (67.5, 0), (30, 0), (52.5, -12.5)]:
        assert d not in pairs, d
    assert s.phi_light.min() >= 0 and s.phi_light.max() < 360  # stores use [0, 360)
    assert s.theta_light[0] == 0 and s.phi_light[0] == 0  # the top direction first


def test_dome151_rings_are_nearly_uniform_over_the_hemisphere():
    s = parse_sampling("dome151")
    theta, counts = np.unique(s.theta_light, return_counts=True)
    assert len(theta) == 8 and theta.max() == 75
    density = counts[1:] / np.sin(np.radians(theta[1:]))  # directions per unit circumference
    assert density.max() / density.min() < 1.15


def test_abtf_lights_are_rotations_times_elevations():
    s = parse_sampling("abtf:4,3")
    assert sorted(set(np.round(90 - s.theta_light, 6))) == [15, 45, 75]
    assert sorted(set(s.phi_light)) == [0, 90, 180, 270]
    assert np.all(s.phi_light[:3] == 0)  # rotation-major order


@pytest.mark.parametrize("spec", ["dome", "abtf:3", "abtf:0,3", "hemi:0", "hemi:x", "ubo81:2",
                                  "ubo2014:1", "ubo2003:3", "ubo"])
def test_bad_sampling_names_are_rejected(spec):
    with pytest.raises(ValueError, match="sampling"):
        parse_sampling(spec)


def test_direction_vectors_follow_the_documented_convention():
    v = direction_vectors([0, 90, 90], [0, 0, 90])
    assert np.allclose(v, [[0, 0, 1], [1, 0, 0], [0, 1, 0]], atol=1e-12)


def test_spread_pairs_cover_the_directions():
    s = parse_sampling("abtf:12,4")
    picked = spread_pairs(s.theta_view, s.phi_view, s.theta_light, s.phi_light, 8)
    assert len(set(picked)) == 8
    assert picked[0] == (0, int(np.argmin(s.theta_light)))
    assert len({round(s.phi_light[li]) for _, li in picked}) >= 5
    b = parse_sampling("hemi:4")
    pairs = spread_pairs(b.theta_view, b.phi_view, b.theta_light, b.phi_light, 16)
    assert sorted(pairs) == [(v, li) for v in range(4) for li in range(4)]  # all, no repeats


def test_a_measured_database_s_sampling_is_recognised_in_any_order():
    from tasks.sampling import known_sampling

    s = parse_sampling("ubo2014")
    order = np.random.default_rng(0).permutation(151)
    assert known_sampling(s.theta_view[order], s.phi_view[order] - 360 * (order % 2),
                          s.theta_light, s.phi_light) == "ubo2014"
    s = parse_sampling("ubo2003")
    assert known_sampling(s.theta_view, s.phi_view, s.theta_light, s.phi_light) == "ubo2003"
    assert known_sampling(s.theta_view, s.phi_view + 0.5, s.theta_light,
                          s.phi_light) is None
    h = parse_sampling("hemi:5")
    assert known_sampling(h.theta_view, h.phi_view, h.theta_light, h.phi_light) is None

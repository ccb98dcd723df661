from __future__ import annotations

import numpy as np
import pytest

from tasks.sampling import direction_vectors, parse_sampling, spread_pairs


def _unique_dirs(theta, phi):
    v = direction_vectors(theta, phi)
    return len(np.unique(np.round(v, 9), axis=0))


@pytest.mark.parametrize(("spec", "views", "lights", "kind"), [
    ("dome151", 151, 151, "btf"), ("ubo81", 81, 81, "btf"), ("abtf:24,8", 1, 192, "abtf"),
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


@pytest.mark.parametrize("spec", ["dome", "abtf:3", "abtf:0,3", "hemi:0", "hemi:x", "ubo81:2"])
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

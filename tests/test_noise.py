from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tasks.hashing import hash_coords, hash_uniform
from tasks.noise import fbm, gradient_noise, worley


def test_hash_is_a_pure_function_of_coordinates_and_seed():
    y, x = np.meshgrid(np.arange(-50, 50), np.arange(-50, 50), indexing="ij")
    a = hash_coords(y, x, seed=7)
    assert np.array_equal(a, hash_coords(y, x, seed=7))
    assert np.array_equal(a[10:20, 30:40], hash_coords(y[10:20, 30:40], x[10:20, 30:40], seed=7))
    assert np.mean(a == hash_coords(y, x, seed=8)) < 1e-3
    assert np.mean(a == hash_coords(x, y, seed=7)) < 0.02  # not symmetric in its arguments


def test_hash_uniform_is_uniform():
    u = hash_uniform(np.arange(200_000), seed=1)
    assert u.min() >= 0 and u.max() < 1
    counts, _ = np.histogram(u, bins=20, range=(0, 1))
    expected = u.size / 20
    chi2 = np.sum((counts - expected) ** 2 / expected)
    assert chi2 < 50  # 19 degrees of freedom: p < 1e-4 beyond ~45
    assert abs(np.corrcoef(u[:-1], u[1:])[0, 1]) < 0.01


@settings(max_examples=25, deadline=None)
@given(st.integers(-300, 300), st.integers(-300, 300), st.integers(1, 40), st.integers(1, 40))
def test_gradient_noise_of_a_window_equals_the_same_texels_of_a_larger_one(y0, x0, ny, nx):
    big_y = np.arange(-320, 360)[:, None] / 7.3
    big_x = np.arange(-320, 360)[None, :] / 7.3
    full = gradient_noise(big_x, big_y, seed=5)
    sub = gradient_noise(big_x[:, x0 + 320 : x0 + 320 + nx], big_y[y0 + 320 : y0 + 320 + ny],
                         seed=5)
    assert np.array_equal(sub, full[y0 + 320 : y0 + 320 + ny, x0 + 320 : x0 + 320 + nx])


def test_gradient_noise_is_zero_on_lattice_points_and_smooth_between():
    lattice = gradient_noise(np.arange(10.0)[None, :], np.arange(10.0)[:, None], seed=3)
    assert np.allclose(lattice, 0, atol=1e-12)
    x = np.linspace(0, 8, 801)[None, :]
    n = gradient_noise(x, np.full((1, 1), 0.37), seed=3)[0]
    assert np.abs(n).max() <= 1.0 + 1e-9
    assert np.abs(np.diff(n)).max() < 0.05  # steps of 0.01 cells: continuous


def test_periodic_noise_repeats_with_its_period():
    period = 6
    u = (np.arange(0, 3 * 64) * period / 64.0 + 0.013)[None, :]
    v = np.full((1, 1), 1.3)
    n = fbm(u, v, seed=2, octaves=3, period=period)  # not wrapped: the lattice must wrap
    assert np.allclose(n[:, :64], n[:, 64:128], rtol=0, atol=1e-12)
    assert np.allclose(n[:, :64], n[:, 128:], rtol=0, atol=1e-12)
    assert not np.allclose(n[:, :32], n[:, 32:64], atol=1e-3)
    n = fbm(u % period, v, seed=2, octaves=3, period=period)
    # and continuous across the wrap: no jump larger than between any other neighbours
    wrap_jump = abs(n[0, 64] - n[0, 63])
    assert wrap_jump <= np.abs(np.diff(n[0, :64])).max() * 1.5


def test_worley_matches_brute_force_nearest_feature_points():
    rng = np.random.default_rng(0)
    u, v = rng.uniform(-5, 5, 300), rng.uniform(-5, 5, 300)
    f1, f2, _ = worley(u, v, seed=9, jitter=0.9)
    cells = np.arange(-8, 9)
    gv, gu = np.meshgrid(cells, cells, indexing="ij")
    pu = gu + 0.5 + 0.9 * (hash_uniform(gv, gu, seed=9) - 0.5)
    pv = gv + 0.5 + 0.9 * (hash_uniform(gv, gu, seed=10) - 0.5)
    d = np.sqrt((pu.ravel()[None] - u[:, None]) ** 2 + (pv.ravel()[None] - v[:, None]) ** 2)
    d.sort(axis=1)
    assert np.allclose(f1, d[:, 0], rtol=0, atol=1e-12)
    assert np.allclose(f2, d[:, 1], rtol=0, atol=1e-12)


@pytest.mark.parametrize("octaves", [1, 4])
def test_fbm_has_bounded_range_and_depends_on_seed(octaves):
    y, x = np.mgrid[0:64, 0:64] / 9.0
    a, b = fbm(x, y, seed=1, octaves=octaves), fbm(x, y, seed=2, octaves=octaves)
    assert np.abs(a).max() <= 1.0 + 1e-9
    assert a.std() > 0.1
    assert np.abs(a - b).mean() > 0.1

from __future__ import annotations

import numpy as np
import pytest

from tasks.materials import MATERIALS, Material, image_fields

ALL = sorted(MATERIALS)


@pytest.mark.parametrize("name", ALL)
def test_fields_stay_in_their_physical_ranges(name):
    m = Material(name, seed=1)
    f = m.fields(-20, 30, 96, 80)
    assert f.height.shape == (96, 80) and f.albedo.shape == (96, 80, 3)
    assert all(a.dtype == np.float32 for a in (f.height, f.albedo, f.roughness, f.specular))
    assert f.height.min() >= 0 and f.height.max() <= m.relief + 1e-5
    assert f.height.max() - f.height.min() > 0.3 * m.relief  # real relief, not a flat plate
    assert f.albedo.min() > 0 and f.albedo.max() <= 1
    assert f.roughness.min() > 0.02 and f.roughness.max() <= 1
    assert 0 < f.specular.min() and f.specular.max() < 0.2


@pytest.mark.parametrize("name", ALL)
def test_any_window_agrees_with_a_larger_window(name):
    m = Material(name, seed=4)
    big = m.fields(-16, -8, 80, 72)
    small = m.fields(5, 11, 30, 25)
    for a, b in ((big.height, small.height), (big.albedo, small.albedo),
                 (big.roughness, small.roughness), (big.specular, small.specular)):
        assert np.array_equal(a[21:51, 19:44], b)


@pytest.mark.parametrize("name", ALL)
def test_seeds_give_different_materials_and_the_same_seed_the_same(name):
    a = Material(name, seed=0).fields(0, 0, 64, 64)
    b = Material(name, seed=1).fields(0, 0, 64, 64)
    assert np.array_equal(a.height, Material(name, seed=0).fields(0, 0, 64, 64).height)
    assert not np.array_equal(a.albedo, b.albedo)


def test_tiles_repeat_exactly_with_their_period():
    m = Material("tiles", seed=2, scale=24)
    f = m.fields(0, 0, 72, 72)
    for field in (f.height, f.albedo, f.roughness, f.specular):
        assert np.array_equal(field[:48], field[24:])
        assert np.array_equal(field[:, :48], field[:, 24:])
    assert not np.array_equal(f.height[:60], f.height[12:])  # half a period is not a period


def test_gloss_is_correlated_with_structure():
    f = Material("tiles", seed=0, scale=32).fields(0, 0, 64, 64)
    glaze = f.height > 0.9 * f.height.max()
    assert f.roughness[glaze].mean() < 0.2 < f.roughness[~glaze].mean()


def test_unknown_material_and_bad_scale_are_rejected():
    with pytest.raises(ValueError, match="unknown material"):
        Material("marble")
    with pytest.raises(ValueError, match="scale"):
        Material("wood", scale=0.5)


def test_photo_fields_use_the_photo_as_albedo():
    rng = np.random.default_rng(0)
    photo = rng.uniform(0.1, 0.9, (40, 50, 3)).astype(np.float32)
    f = image_fields(photo, relief=4.0)
    assert np.array_equal(f.albedo, photo)
    assert f.height.min() >= 0 and f.height.max() <= 4.0 and f.height.std() > 0.1
    grey = image_fields(photo[..., 0], relief=4.0)
    assert np.array_equal(grey.albedo[..., 1], photo[..., 0])

"""HLS fitting of an ABTF (paper 003, section 2.5): ``btf fit``."""

from __future__ import annotations

import numpy as np
import pytest
import zarr

from helpers import generate_store
from pipeline.errors import BTFError
from pipeline.stores.base import RADIANCE, Directions
from pipeline.stores.radiance import Layout, create_radiance_store, open_radiance
from tasks.materials import Material


def _lambertian_abtf(path, rotations=6, elevations=8, size=24):
    """A purely diffuse ABTF: albedo times cos(theta) (hue and saturation exactly constant)."""
    from tasks.sampling import parse_sampling

    s = parse_sampling(f"abtf:{rotations},{elevations}")
    d = Directions(s.theta_view, s.phi_view, s.theta_light, s.phi_light)
    group = create_radiance_store(path, directions=d, ny=size, nx=size,
                                  channels=("R", "G", "B"), layout=Layout(chunk=8),
                                  attrs={"btf_kind": "abtf"})
    albedo = Material("wood", seed=1).fields(0, 0, size, size).albedo
    shade = np.cos(np.radians(s.theta_light))[:, None, None, None]
    group[RADIANCE][0] = (albedo[None] * shade).astype(np.float32)
    return path


def test_the_hls_fit_of_a_diffuse_material_is_close_and_rebuilds_from_its_parameters(
        tmp_path, btf):
    from pipeline.stores.fitted import open_fitted
    from tasks.hls import rebuild

    src = _lambertian_abtf(tmp_path / "d.zarr")
    assert btf("fit", src, tmp_path / "fit.zarr", "--quiet").code == 0
    ds = open_fitted(tmp_path / "fit.zarr")
    err = ds.attrs["fit_error"]
    original = open_radiance(src)[RADIANCE].values
    assert err["rmse"] < 1e-3 * original.mean() and err["max"] < 1e-2 * original.max()
    rebuilt = ds[RADIANCE].values
    assert rebuilt.shape == original.shape
    assert np.sqrt(np.mean((rebuilt - original) ** 2)) == pytest.approx(err["rmse"], rel=1e-3)
    grid = np.asarray(ds.attrs["light_grid"])
    direct = rebuild(ds["hue"].values[0], ds["saturation"].values[0],
                     ds["lightness"].values[0], grid, np.asarray(ds.attrs["elevations"]))
    assert np.allclose(rebuilt[0], direct, atol=1e-6)
    assert ds.attrs["size_ratio"] == pytest.approx(48 * 3 / (2 + 6 * 6))


def test_the_hls_fit_of_a_generated_material_reports_its_error(tmp_path, btf):
    import json

    from pipeline.stores.fitted import open_fitted

    src = generate_store(tmp_path / "l.zarr", "--material", "leather", "--size", "32",
                         "--sampling", "abtf:4,8")
    assert btf("fit", src, tmp_path / "fit.zarr", "--quiet").code == 0
    fit = json.loads(btf("inspect", tmp_path / "fit.zarr", "--json").out)["fit"]
    assert fit["rotations"] == 4 and fit["elevations"] == 8
    original = open_radiance(src)[RADIANCE].values.astype(np.float64)
    rebuilt = open_fitted(tmp_path / "fit.zarr")[RADIANCE].values
    difference = rebuilt - original
    assert np.sqrt(np.mean(difference**2)) == pytest.approx(fit["error"]["rmse"], rel=1e-4)
    assert np.abs(difference).max() == pytest.approx(fit["error"]["max"], rel=1e-4)
    # six parameters over elevation do much better than each texel's mean over the lights
    flat = original - original.mean(axis=1, keepdims=True)
    assert fit["error"]["rmse"] < 0.3 * np.sqrt(np.mean(flat**2))


def test_fit_refuses_radiance_with_nan(tmp_path, btf):
    src = generate_store(tmp_path / "n.zarr", "--material", "fabric", "--size", "32",
                         "--sampling", "abtf:6,3", "--chunk", "16")
    zarr.open_array(src, path=RADIANCE, mode="r+")[0, 4, 20, 3] = np.nan
    result = btf("fit", src, tmp_path / "fit.zarr", "--quiet")
    assert result.code == 1
    assert "variable 'radiance' has 3 NaN or Inf values in view 0, y 16:32, x 0:16" in result.err
    assert not (tmp_path / "fit.zarr").exists()


def test_fit_refuses_lights_that_are_not_a_grid(tmp_path, btf):
    src = generate_store(tmp_path / "h.zarr", "--material", "stone", "--size", "16",
                         "--sampling", "hemi:5")
    result = btf("fit", src, tmp_path / "fit.zarr", "--quiet")
    assert result.code == 1 and "not a grid of" in result.err
    with pytest.raises(BTFError):
        from pipeline.stores.fitted import open_fitted

        open_fitted(src)

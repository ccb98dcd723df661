"""btf pyramid: levels of detail against block means of level 0, metadata other tools read."""

from __future__ import annotations

import json

import numpy as np
import pytest
import zarr

from helpers import generate_store
from pipeline.stores.compressed import open_compressed
from tasks.transform import Transform


def _block_means(a: np.ndarray, f: int, ay: int, ax: int) -> np.ndarray:
    """Means of f x f blocks over axes ``ay``, ``ax`` (whole blocks only), in float64."""
    a = np.asarray(a, np.float64)
    ny, nx = a.shape[ay] // f * f, a.shape[ax] // f * f
    a = np.take(np.take(a, range(ny), ay), range(nx), ax)
    shape = list(a.shape)
    shape[ay:ay + 1] = [ny // f, f]
    shape[ax + 1:ax + 2] = [nx // f, f]
    return a.reshape(shape).mean(axis=(ay + 1, ax + 2))


@pytest.mark.parametrize("size", [48, 37])  # an odd size: edge blocks are left out
def test_levels_are_block_means_of_level_0_and_described_as_multiscales(tmp_path, btf, size):
    store = generate_store(tmp_path / "s.zarr", "--material", "wood", "--size", str(size),
                           "--sampling", "abtf:4,2", "--chunk", "16", "--dir-chunk", "4",
                           "--seed", "2")
    result = btf("pyramid", store, "--levels", "3", "--quiet")
    assert result.code == 0, result.err
    g = zarr.open_group(store, mode="r")
    level0 = g["radiance"][...]
    for n in (1, 2, 3):
        level = g[f"pyramid/{n}/radiance"]
        assert level.shape == (*level0.shape[:2], size >> n, size >> n, 3)
        assert level.chunks[:2] == g["radiance"].chunks[:2]  # chunked like level 0
        assert level.chunks[2] == min(16, size >> n)
        assert np.allclose(level[...], _block_means(level0, 2**n, 2, 3), rtol=1e-6, atol=0)
    (scales,) = g.attrs["multiscales"]
    assert [d["path"] for d in scales["datasets"]] == [
        "radiance", "pyramid/1/radiance", "pyramid/2/radiance", "pyramid/3/radiance"]
    assert scales["axes"][2] == {"name": "y", "type": "space"}
    assert scales["datasets"][2]["coordinateTransformations"] == [
        {"type": "scale", "scale": [1.0, 1.0, 4.0, 4.0, 1.0]},
        {"type": "translation", "translation": [0.0, 0.0, 1.5, 1.5, 0.0]}]
    # consolidated metadata covers the levels: zarr opens them from it
    consolidated = json.loads((store / "zarr.json").read_text())["consolidated_metadata"]
    assert "pyramid/3/radiance" in consolidated["metadata"]
    inspect = btf("inspect", store, "--json")
    levels = json.loads(inspect.out)["levels"]
    assert [v["level"] for v in levels] == [0, 1, 2, 3]
    assert "levels of detail: 0:" in btf("inspect", store).out
    # level 0 is untouched and still what every stage reads
    assert np.array_equal(zarr.open_group(store, mode="r")["radiance"][...], level0)


def test_existing_levels_are_kept_unless_overwrite_and_bad_requests_fail(tmp_path, btf):
    store = generate_store(tmp_path / "s.zarr", "--material", "stone", "--size", "32",
                           "--sampling", "hemi:2", "--chunk", "16")
    assert btf("pyramid", store, "--levels", "1", "--quiet").code == 0
    again = btf("pyramid", store, "--levels", "2", "--quiet")
    assert again.code == 1 and "already has levels" in again.err
    assert btf("pyramid", store, "--levels", "2", "--overwrite", "--quiet").code == 0
    g = zarr.open_group(store, mode="r")
    assert len(g.attrs["multiscales"][0]["datasets"]) == 3 and "pyramid/2/radiance" in g
    too_many = btf("pyramid", store, "--levels", "9", "--overwrite", "--quiet")
    assert too_many.code == 1 and "below one texel" in too_many.err
    assert len(zarr.open_group(store, mode="r").attrs["multiscales"][0]["datasets"]) == 3
    assert not list(store.glob("pyramid.partial-*"))
    assert btf("pyramid", store, "--levels", "0").code == 2
    tiles = tmp_path / "t.zarr"  # a tile set of 24 x 24 tiles: levels halve them exactly
    assert btf("quilt", store, tiles, "--block", "16", "--overlap", "4", "--quiet").code == 0
    small = btf("pyramid", tiles, "--quiet")  # 12 x 12 tiles would fall below 16 texels
    assert small.code == 1 and "tiles of 24 x 24 texels are too small" in small.err
    inexact = btf("pyramid", tiles, "--levels", "4", "--quiet")  # 24 = 3 x 2^3
    assert inexact.code == 1 and "halve exactly 3 time(s)" in inexact.err
    assert btf("pyramid", tiles, "--levels", "3", "--quiet").code == 0
    assert zarr.open_group(tiles, mode="r")["pyramid/3/radiance"].shape[-3:-1] == (3, 3)
    spec = tmp_path / "scene.yaml"
    spec.write_text(f"source: {store}\ndirections: [[0, 0, 0, 0]]\n")
    assert btf("scene", spec, tmp_path / "scene.zarr", "--quiet").code == 0
    refused = btf("pyramid", tmp_path / "scene.zarr", "--quiet")
    assert refused.code == 1 and "a scene store; btf pyramid takes a radiance" in refused.err


@pytest.fixture(scope="module")
def leather_svd(tmp_path_factory):
    from pipeline.cli import main

    tmp = tmp_path_factory.mktemp("pyramid")
    store = generate_store(tmp / "s.zarr", "--material", "leather", "--size", "64",
                           "--sampling", "abtf:6,2", "--chunk", "32", "--seed", "5")
    c = tmp / "c.zarr"
    assert main(["compress", str(store), str(c), "--rank", "12", "--quiet"]) == 0
    return c


def _level_errors(c, method: str, btf) -> list[tuple[float, float]]:
    """Relative RMS error and mean bias of each level against the exact one (block means of
    the reconstructed level-0 radiance)."""
    assert btf("pyramid", c, "--levels", "2", "--method", method, "--overwrite",
               "--quiet").code == 0
    g = zarr.open_group(c, mode="r")
    rebuilt = open_compressed(c)["radiance"].values.astype(np.float64)  # level 0, linear
    eps = g.attrs["transform"]["eps"]
    u = g["U"][...].reshape(-1, 12).astype(np.float64) * g["S"][...]
    out = []
    for n in (1, 2):
        v = g[f"pyramid/{n}/V"][...]
        approx = np.exp(v.reshape(-1, 12) @ u.T) - eps  # (texels, rows)
        exact = _block_means(rebuilt, 2**n, 2, 3)  # (view, light, y, x, channel)
        # rows of U are (view, light, channel): the same order here
        exact = np.moveaxis(exact, (2, 3), (0, 1)).reshape(approx.shape[0], -1)
        out.append((np.sqrt(np.mean((approx - exact) ** 2)) / np.sqrt(np.mean(exact**2)),
                    np.mean(approx) / np.mean(exact) - 1))
    return out


def test_mean_v_levels_are_log_domain_means_biased_low(leather_svd, btf):
    errors = _level_errors(leather_svd, "mean-v", btf)
    g = zarr.open_group(leather_svd, mode="r")
    v0 = g["V"][...]
    for n in (1, 2):
        assert np.allclose(g[f"pyramid/{n}/V"][...], _block_means(v0, 2**n, 0, 1), rtol=1e-5,
                           atol=1e-7)
    # the geometric mean stays below the arithmetic one (Jensen), more so for larger blocks
    assert errors[1][1] < errors[0][1] < 0, errors
    assert 0 < errors[0][0] < errors[1][0] < 0.25, errors


def test_projected_levels_are_several_times_closer_to_the_exact_ones(leather_svd, btf):
    mean_v = _level_errors(leather_svd, "mean-v", btf)
    projected = _level_errors(leather_svd, "projected", btf)
    for (rel, bias), (rel_v, bias_v) in zip(projected, mean_v, strict=True):
        assert rel < rel_v / 2 and abs(bias) < abs(bias_v) / 2, (projected, mean_v)
    g = zarr.open_group(leather_svd, mode="r")
    assert "projected on U" in g.attrs["multiscales"][0]["metadata"]["method"]
    assert g["pyramid/2/V"].shape == (16, 16, 12)


def test_projected_levels_of_many_tiles_equal_the_kernel_on_the_whole(tmp_path, btf,
                                                                      small_tasks):
    """Odd size, small task blocks: the tiles, their rounding and the edge trimming."""
    from tasks.svd import projected_level

    store = generate_store(tmp_path / "s.zarr", "--material", "fabric", "--size", "75",
                           "--sampling", "abtf:4,2", "--chunk", "8", "--seed", "6")
    c = tmp_path / "c.zarr"
    assert btf("compress", store, c, "--rank", "6", "--quiet").code == 0
    assert btf("pyramid", c, "--levels", "2", "--quiet").code == 0
    g = zarr.open_group(c, mode="r")
    u, s, v0 = g["U"][...].reshape(-1, 6), g["S"][...], g["V"][...]
    eps = g.attrs["transform"]["eps"]
    for n in (1, 2):
        f = 2**n
        whole = projected_level(v0[: 75 // f * f, : 75 // f * f], u=u, s=s, factor=f,
                                 transform=Transform("log", eps))
        level = g[f"pyramid/{n}/V"]
        assert level.shape == (75 >> n, 75 >> n, 6) and level.chunks == (8, 8, 6)
        assert np.allclose(level[...], whole, rtol=1e-5, atol=1e-6)

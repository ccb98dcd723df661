"""Every stage on a factor store (issue 53, part 3): compress, crop and preview of U, S, V.

A compressed store is brought to a lower rank from its factors (truncated when they are an SVD
already, else re-factored exactly), cut in its factors, and previewed; stages that need
radiance say what to run first. Checked against numpy's SVD of the stored values.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import zarr

from helpers import no_partial_outputs
from pipeline.stores import open_layers


@pytest.fixture(scope="module")
def compressed(tmp_path_factory, small_btf):
    from pipeline.cli import main

    out = tmp_path_factory.mktemp("factors") / "c.zarr"
    assert main(["compress", str(small_btf), str(out), "--rank", "8", "--quiet"]) == 0
    return out


def _factors(path):
    g = zarr.open_group(path, mode="r")
    return (np.asarray(g["U"][...], np.float64), np.asarray(g["S"][...], np.float64),
            np.asarray(g["V"][...], np.float64))


def _values(u, s, v):
    """The stored matrix of values ``(rows, texels)``."""
    return (u.reshape(-1, len(s)) * s) @ v.reshape(-1, len(s)).T


def test_compress_truncates_a_compressed_store_whose_factors_are_an_svd(tmp_path, btf,
                                                                         compressed):
    r = btf("compress", compressed, tmp_path / "t.zarr", "--rank", "3")
    assert r.code == 0, r.err
    assert "truncated" in r.err and "re-factored" not in r.err
    u, s, v = _factors(compressed)
    tu, ts, tv = _factors(tmp_path / "t.zarr")
    assert np.array_equal(tu, u[..., :3]) and np.array_equal(ts, s[:3])
    assert np.array_equal(tv, v[..., :3])  # the same bits: nothing recomputed
    g = zarr.open_group(tmp_path / "t.zarr", mode="r")
    assert g.attrs["transform"] == zarr.open_group(compressed, mode="r").attrs["transform"]
    part = g.attrs["error"]["dropped_relative_frobenius"]
    assert part == pytest.approx(np.sqrt(np.sum(s[3:] ** 2) / np.sum(s**2)), rel=1e-6)
    # the report of such a store says it was made from factors (no radiance to compare)
    r = btf("report", tmp_path / "r.html", "--compressed", tmp_path / "t.zarr", "--quiet")
    assert r.code == 0, r.err
    assert "made from a compressed store" in (tmp_path / "r.html").read_text()
    # the rank a compressed store does not hold is refused, and nothing is written
    r = btf("compress", compressed, tmp_path / "x.zarr", "--rank", "9")
    assert r.code == 1 and "more than the 8 components" in r.err, r.err
    assert no_partial_outputs(tmp_path / "x.zarr")


def test_compress_refactors_factors_that_are_no_svd_exactly(tmp_path, btf, compressed):
    # the same values, U and V mixed by an invertible matrix: no longer orthonormal
    mixed = tmp_path / "mixed.zarr"
    shutil.copytree(compressed, mixed)
    u, s, v = _factors(compressed)
    m = np.random.default_rng(5).normal(size=(8, 8)) + 3 * np.eye(8)
    g = zarr.open_group(mixed, mode="r+")
    g["U"][...] = (u * s) @ np.linalg.inv(m).T
    g["S"][...] = np.ones(8)
    g["V"][...] = v @ m
    exact = _values(*_factors(mixed))
    left, sigma, right = np.linalg.svd(exact, full_matrices=False)
    r = btf("compress", mixed, tmp_path / "r.zarr", "--rank", "4")
    assert r.code == 0 and "re-factored exactly" in r.err, r.err
    ru, rs, rv = _factors(tmp_path / "r.zarr")
    assert np.allclose(rs, sigma[:4], rtol=1e-4)
    best = (left[:, :4] * sigma[:4]) @ right[:4]  # Eckart-Young: the best rank-4 values
    assert np.abs(_values(ru, rs, rv) - best).max() <= 1e-4 * np.abs(exact).max()
    k = ru.shape[-1]
    assert np.allclose(ru.reshape(-1, k).T @ ru.reshape(-1, k), np.eye(k), atol=1e-5)
    assert np.allclose(rv.reshape(-1, k).T @ rv.reshape(-1, k), np.eye(k), atol=1e-5)
    part = zarr.open_group(tmp_path / "r.zarr").attrs["error"]["dropped_relative_frobenius"]
    assert part == pytest.approx(np.sqrt(np.sum(sigma[4:] ** 2) / np.sum(sigma**2)), rel=1e-4)


def test_crop_of_a_compressed_store_is_an_exact_svd_of_the_part(tmp_path, btf, compressed):
    r = btf("crop", compressed, tmp_path / "c.zarr", "--region", "5:29,3:20", "--light", "0,2",
            "--chunk", "8")
    assert r.code == 0, r.err
    whole = open_layers(compressed)["radiance"].values
    part = open_layers(tmp_path / "c.zarr")["radiance"].values
    assert part.shape == (3, 2, 24, 17, 3)
    expected = whole[:, [0, 2], 5:29, 3:20]
    assert np.allclose(part, expected, rtol=1e-4, atol=1e-6 * np.abs(expected).max())
    u, s, v = _factors(tmp_path / "c.zarr")
    k = len(s)
    assert np.all(np.diff(s) <= 0) and k <= 8
    assert np.allclose(v.reshape(-1, k).T @ v.reshape(-1, k), np.eye(k), atol=1e-5)
    assert np.allclose(u.reshape(-1, k).T @ u.reshape(-1, k), np.eye(k), atol=1e-5)
    g = zarr.open_group(tmp_path / "c.zarr", mode="r")
    assert g.attrs["btf_kind"] == "compressed" and g["V"].chunks == (8, 8, k)
    assert g.attrs["cropped_from"]["y"] == [5, 29]


def test_preview_draws_a_compressed_store_and_radiance_stages_say_what_to_run(
        tmp_path, btf, compressed):
    r = btf("preview", compressed, tmp_path / "p.png", "--count", "4", "--size", "32",
            "--quiet")
    assert r.code == 0, r.err
    assert (tmp_path / "p.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    r = btf("fit", compressed, tmp_path / "f.zarr")
    assert r.code == 1 and "btf reconstruct" in r.err and "compressed" in r.err, r.err
    assert no_partial_outputs(tmp_path / "f.zarr")

"""btf export's DFMF files read by an independent reader, btf-extractor (issue 32, part 3).

btf-extractor 1.7.0 lives in .venv-btfx (installed by .ci/run); without it these tests skip,
unless BTF_REQUIRE_BTFX=1 (CI's slow run), where they fail. It decodes colour models 0 and 11
and returns the raw channel sums for others (model 12 here), flipped and BGR (tests/btfx.py).
"""

from __future__ import annotations

import os

import numpy as np
import pytest
from btfx import as_store_layers, btfx_available, btfx_images
from dfmf_files import write_dfmf

from pipeline.stores.base import RADIANCE
from pipeline.stores.compressed import open_compressed

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module", autouse=True)
def _btfx():
    if not btfx_available():
        msg = "btf-extractor is not installed in .venv-btfx (the install commands are in .ci/run)"
        if os.environ.get("BTF_REQUIRE_BTFX") == "1":
            pytest.fail(f"BTF_REQUIRE_BTFX=1 but {msg}")
        pytest.skip(msg)


def _pairs(ds):
    """(theta_light, phi_light, theta_view, phi_view) of every layer, view-major, degrees."""
    tv, pv = ds["theta_view"].values, ds["phi_view"].values
    tl, pl = ds["theta_light"].values, ds["phi_light"].values
    return [(tl[li], pl[li], tv[v], pv[v]) for v in range(len(tv)) for li in range(len(tl))]


def test_a_model_11_store_exports_to_a_file_btf_extractor_decodes_alike(tmp_path, btf):
    rng = np.random.default_rng(3)
    views = [(0.0, 0.0), (0.5, 1.0), (1.0, -2.5)]  # radians
    rows, w, h, ks = 9, 12, 9, (4, 2, 3)
    u = [rng.normal(size=(rows, k)) * 0.1 for k in ks]
    sxv = [rng.normal(size=(w * h, k)) * 0.3 for k in ks]
    u[0][:, 0], sxv[0][:, 0] = -1.2 + rng.normal(size=rows) * 0.3, 1.0
    write_dfmf(tmp_path / "a.btf", views=views, lights=views, u=u, sxv=sxv, width=w, height=h,
               color_model=11, scalar_size=4)
    assert btf("ingest", tmp_path / "a.btf", tmp_path / "a.zarr", "--quiet").code == 0
    # the file as btf ingested it and as btf-extractor decodes it: the same images, the same
    # way up (both reverse the file's texel rows)
    ds = open_compressed(tmp_path / "a.zarr")
    ingested = ds[RADIANCE].values.reshape(-1, h, w, 3)
    theirs = as_store_layers(btfx_images(tmp_path / "a.btf", _pairs(ds)))
    assert np.allclose(theirs, np.clip(ingested, 0, 1), atol=5e-5)
    assert np.abs(theirs[:, ::-1] - np.clip(ingested, 0, 1)).max() > 0.05  # a flip would show
    for half, tol in ((False, 5e-5), (True, 3e-3)):  # btf-extractor's eps: up to 2.5e-5
        out = tmp_path / f"b{int(half)}.btf"
        args = ("--half",) if half else ()
        assert btf("export", tmp_path / "a.zarr", out, "--quiet", *args).code == 0
        ds = open_compressed(tmp_path / "a.zarr")
        ours = ds[RADIANCE].values.reshape(-1, h, w, 3)
        theirs = as_store_layers(btfx_images(out, _pairs(ds)))
        # btf-extractor clamps to [0, 1] and writes U = c1 Y + eps (btflib: c1 (Y + eps))
        assert np.allclose(theirs, np.clip(ours, 0, 1), atol=tol), (
            half, np.abs(theirs - np.clip(ours, 0, 1)).max())
        assert 0.05 < ours.mean() < 0.9  # a test that would see a wrong decoding


def test_a_compressed_store_exports_as_model_12_whose_sums_btf_extractor_reads(tmp_path, btf,
                                                                             small_btf):
    out = tmp_path / "c.zarr"
    assert btf("compress", small_btf, out, "--rank", "5", "--eps", "1e-5", "--quiet").code == 0
    assert btf("export", out, tmp_path / "c.btf", "--quiet").code == 0
    ds = open_compressed(out)
    ours = ds[RADIANCE].values
    sums = as_store_layers(btfx_images(tmp_path / "c.btf", _pairs(ds)))  # model 12: raw sums
    decoded = np.maximum(np.exp(sums) - 1e-5, 0).reshape(ours.shape)
    assert np.allclose(decoded, ours, rtol=1e-4, atol=1e-6 * ours.max()), (
        np.abs(decoded - ours).max(), ours.max())


@pytest.mark.slow  # a benchmark suite end to end (about 20 s)
def test_btf_bench_formats_decodes_side_by_side_and_ingests_an_archive():
    import argparse

    from benchmarks import formats as suite

    args = argparse.Namespace(sampling="ubo2003", texels="32,48", components=4, batch=64,
                              views=2, archive=True, archive_views=2, json=None)
    result = suite.run(args)
    text = suite.report(result)
    for row in result["files"]:
        assert row["btf"]["images"] == row["btfx"]["images"] == 2 * 81
        assert row["btf"]["whole"] > 0 and row["btfx"]["whole"] > 0
        assert row["ingest"]["peak_rss"] > 0
    assert "| 48^2 |" in text and "btf-extractor 1.7.0" in text
    assert result["archive"]["images"] == 2 * 81 and result["archive"]["ingest_per_s"] > 0
    assert "UBO2003-style zip, 162 JPEGs" in text

"""btf inspect: metadata by default, --scan statistics, --plot, --json."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import zarr

from helpers import no_partial_outputs
from pipeline.images import read_image
from pipeline.stores.base import RADIANCE, Directions
from pipeline.stores.radiance import Layout, create_radiance_store


def test_metadata_report_describes_the_store(btf, small_abtf):
    result = btf("inspect", small_abtf, "--json")
    assert result.code == 0
    report = json.loads(result.out)
    assert report["kind"] == "abtf" and report["source"] == "generate"
    rad = report["variables"][RADIANCE]
    assert rad["dims"] == ["view", "light", "y", "x", "channel"]
    assert rad["shape"] == [1, 18, 48, 48, 3] and rad["dtype"] == "float32"
    assert rad["chunks"] == [1, 4, 8, 8, 3] and rad["shards"] == [1, 4, 16, 16, 3]
    assert any(c.startswith("blosc") for c in rad["codecs"])
    assert rad["bytes"] == 18 * 48 * 48 * 3 * 4
    assert 0 < rad["stored_bytes"] < rad["bytes"] and rad["ratio"] > 1
    assert report["sampling"]["lights"] == 18 and report["sampling"]["views"] == 1
    assert report["sampling"]["light"]["theta_rings"] == 3
    assert report["attrs"]["provenance"]["command"].startswith("btf generate")


def test_text_report_is_readable(btf, small_abtf):
    result = btf("inspect", small_abtf)
    assert result.code == 0
    assert "abtf store, made by generate" in result.out
    assert "1 view(s) x 18 light(s) = 18 layers" in result.out
    assert "compression" in result.out and "made by: btf generate" in result.out


def test_default_inspect_reads_no_data(btf, small_abtf, tmp_path):
    store = tmp_path / "s.zarr"
    shutil.copytree(small_abtf, store)
    for chunk in (store / RADIANCE / "c").rglob("*"):
        if chunk.is_file():
            chunk.write_bytes(b"not a shard" * 10)  # any read of data would now fail
    assert btf("inspect", store, "--json").code == 0
    result = btf("inspect", store, "--scan", "--quiet")
    assert result.code == 1
    array = zarr.open_group(small_abtf, mode="r")[RADIANCE]  # every (inner) chunk is bad
    chunks = int(np.prod([-(-n // c) for n, c in zip(array.shape, array.chunks, strict=True)]))
    assert f"{store}: {chunks} chunk(s) fail their checksum" in result.err, result.err
    assert "\n  radiance (0, 0, 0, 0, 0) [0:1, " in result.err
    assert no_partial_outputs(store.parent / "never")  # (scan writes nothing)


def test_scan_counts_match_numpy(btf, tmp_path, small_tasks):
    path = tmp_path / "s.zarr"
    d = Directions(np.zeros(1), np.zeros(1), np.array([0.0, 45.0, 60.0]), np.zeros(3))
    group = create_radiance_store(path, directions=d, ny=20, nx=24, channels=("R", "G", "B"),
                                  layout=Layout(chunk=8, dir_chunk=2, shard=16),
                                  attrs={"btf_kind": "abtf"})
    values = np.random.default_rng(0).uniform(-0.5, 3.0, group[RADIANCE].shape).astype("f4")
    values[0, 1, 3, 4, 2] = np.nan
    values[0, 2, 19, 23, 0] = np.inf
    values[0, 0, 0, 0, 0] = -np.inf
    group[RADIANCE][:] = values
    result = btf("inspect", path, "--scan", "--json", "--quiet")
    assert result.code == 0
    stats = json.loads(result.out)["scan"][RADIANCE]
    finite = values[np.isfinite(values)]
    assert stats["count"] == values.size and stats["nan"] == 1 and stats["inf"] == 2
    assert stats["negative"] == int(np.sum(values < 0))
    assert stats["min"] == pytest.approx(float(finite.min()))
    assert stats["max"] == pytest.approx(float(finite.max()))
    assert stats["mean"] == pytest.approx(float(finite.astype(np.float64).mean()), rel=1e-12)


def test_plot_and_report_files(btf, small_btf, tmp_path):
    plot, report = tmp_path / "dirs.png", tmp_path / "report.json"
    assert btf("inspect", small_btf, "--plot", plot, "--report", report).code == 0
    pixels, _ = read_image(plot)
    assert pixels.shape[1] > 400 and pixels.std() > 0.02
    assert json.loads(report.read_text())["sampling"]["layers"] == 9


def test_inspect_works_on_any_zarr_group(btf, tmp_path):
    group = zarr.open_group(tmp_path / "other.zarr", mode="w", zarr_format=3)
    group.create_array("weights", shape=(10,), dtype="f8", dimension_names=("k",))[:] = 1.0
    result = btf("inspect", tmp_path / "other.zarr", "--scan", "--quiet")
    assert result.code == 0 and "unknown store" in result.out and "weights" in result.out


@pytest.mark.parametrize(("target", "message"), [("missing.zarr", "no such store"),
                                                 ("plain", "not a zarr v3 store")])
def test_inspect_refuses_what_is_not_a_store(btf, tmp_path, target, message):
    (tmp_path / "plain").mkdir()
    result = btf("inspect", tmp_path / target)
    assert result.code == 1 and message in result.err and target in result.err

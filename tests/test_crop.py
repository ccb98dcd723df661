"""``btf crop``: a region and some layers of a radiance store as a new store."""

from __future__ import annotations

import numpy as np
import zarr

from helpers import no_partial_outputs


def test_crop_keeps_the_values_the_truth_and_says_where_it_came_from(small_abtf, btf,
                                                                      tmp_path):
    m = zarr.open_group(small_abtf, mode="r")
    assert btf("crop", small_abtf, tmp_path / "s.zarr", "--region", "5:37,11:30",
               "--quiet").code == 0
    s = zarr.open_group(tmp_path / "s.zarr", mode="r")
    ys, xs = slice(5, 37), slice(11, 30)  # odd sides, across shards
    assert np.array_equal(s["radiance"][...], m["radiance"][:, :, ys, xs])
    assert np.array_equal(s["albedo"][...], m["albedo"][ys, xs])
    assert s.attrs["cropped_from"]["y"] == [ys.start, ys.stop]
    assert s.attrs["btf_kind"] == "abtf" and "crop" in s.attrs["provenance"]["command"]
    top = int(np.argmin(m["theta_light"][...]))
    assert btf("crop", small_abtf, tmp_path / "c.zarr", "--light", f"{top},{top + 1}",
               "--quiet").code == 0
    c = zarr.open_group(tmp_path / "c.zarr", mode="r")
    assert c["radiance"].shape == (1, 2, 48, 48, 3)
    assert np.array_equal(c["radiance"][0, 0], m["radiance"][0, top])
    assert np.array_equal(c["radiance"][0, 1], m["radiance"][0, top + 1])
    assert c["theta_light"][0] == m["theta_light"][top]
    # a list option given twice joins its lists, as a comma would
    assert btf("crop", small_abtf, tmp_path / "d.zarr", "--light", top, "--light", top + 1,
               "--quiet").code == 0
    d = zarr.open_group(tmp_path / "d.zarr", mode="r")
    assert np.array_equal(d["radiance"][...], c["radiance"][...])


def test_crop_refuses_regions_and_lights_out_of_range(small_abtf, btf, tmp_path):
    beyond = btf("crop", small_abtf, tmp_path / "x.zarr", "--region", "0:10,40:50", "--quiet")
    assert beyond.code == 1 and "reaches beyond the 48 x 48 texels" in beyond.err
    assert no_partial_outputs(tmp_path / "x.zarr")
    bad = btf("crop", small_abtf, tmp_path / "x.zarr", "--light", "99", "--quiet")
    assert bad.code == 1 and "--light 99 is out of range" in bad.err
    assert btf("crop", small_abtf, tmp_path / "x.zarr", "--region", "5:2,0:3").code == 2
    assert no_partial_outputs(tmp_path / "x.zarr")


def test_a_region_is_read_in_its_output_blocks_and_no_texel_outside_it(small_abtf, btf,
                                                                       tmp_path, small_tasks,
                                                                       monkeypatch):
    """A region on the source's grid of write units (shards of 16 texels) is read one output
    block at a time (task blocks of 16 here: 16:45 as 16:32 and 32:45, not the source's
    16:32 and 32:48 cut); one off that grid, or a selection of lights, in the source's own
    blocks, which two output blocks would otherwise both decode. The same values each way."""
    from pipeline import chunk_io

    reads = []
    read = chunk_io.Reader.__getitem__

    def spy(self, region):
        if self.array.path == "radiance":
            reads.append(tuple((r.start, r.stop) for r in region[2:4]))
        return read(self, region)

    monkeypatch.setattr(chunk_io.Reader, "__getitem__", spy)
    m = zarr.open_group(small_abtf, mode="r")
    for name, region, lights, read_as in [
            ("a", "16:45,0:27", [], {((y0, y1), (x0, x1)) for y0, y1 in ((16, 32), (32, 45))
                                     for x0, x1 in ((0, 16), (16, 27))}),
            ("b", "5:37,11:30", [], None),
            ("c", "16:45,0:27", ["--light", "1,4"], None)]:
        reads.clear()
        assert btf("crop", small_abtf, tmp_path / f"{name}.zarr", "--region", region,
                   *lights, "--quiet").code == 0
        (y0, y1), (x0, x1) = (map(int, r.split(":")) for r in region.split(","))
        out = zarr.open_group(tmp_path / f"{name}.zarr", mode="r")
        layers = [1, 4] if lights else slice(None)
        assert np.array_equal(out["radiance"][...], m["radiance"][:, layers, y0:y1, x0:x1])
        if not lights:
            assert np.array_equal(out["albedo"][...], m["albedo"][y0:y1, x0:x1])
        if read_as is not None:
            assert set(reads) == read_as
        else:  # within the source's own blocks of 16 (dask may trim them to the region)
            assert reads and all(a // 16 == (b - 1) // 16 for read in reads for a, b in read)


def test_a_store_with_some_of_the_truth_is_cropped_without_it(small_abtf, btf, tmp_path):
    """The truth arrays are written only when all four are there; a store with some of them
    (or any other variable) is cropped, its radiance read in the output's blocks."""
    import shutil
    import warnings

    source = tmp_path / "partial.zarr"
    shutil.copytree(small_abtf, source)
    group = zarr.open_group(source, mode="a")
    del group["specular"]
    with warnings.catch_warnings():  # zarr's note that consolidated metadata is not in v3
        warnings.simplefilter("ignore")
        zarr.consolidate_metadata(source)  # as btf's stores keep theirs
    assert btf("crop", source, tmp_path / "c.zarr", "--region", "16:48,0:32",
               "--quiet").code == 0
    c = zarr.open_group(tmp_path / "c.zarr", mode="r")
    assert "height" not in c and "specular" not in c
    assert np.array_equal(c["radiance"][...], group["radiance"][:, :, 16:48, 0:32])


def test_lights_in_any_order_and_a_region_are_the_source_s_values(small_abtf, btf, tmp_path):
    m = zarr.open_group(small_abtf, mode="r")
    assert btf("crop", small_abtf, tmp_path / "s.zarr", "--light", "5,1,9", "--region",
               "3:40,7:21", "--quiet").code == 0
    s = zarr.open_group(tmp_path / "s.zarr", mode="r")
    assert np.array_equal(s["radiance"][...], m["radiance"][:, [5, 1, 9], 3:40, 7:21])
    assert np.array_equal(s["theta_light"][...], m["theta_light"][[5, 1, 9]])
    assert np.array_equal(s["height"][...], m["height"][3:40, 7:21])


def test_a_variable_xarray_would_decode_is_read_as_xarray_reads_it(small_abtf, tmp_path):
    """Variables are read without xarray where xarray would give the stored values; one it
    would decode (a scale factor, a fill value to mask) is read through it, as before."""
    import shutil

    from pipeline.graphs.blocks import read_chunks
    from pipeline.stores import open_store
    from pipeline.stores.radiance import lazy_variable, open_dataset, plain

    path = tmp_path / "s.zarr"
    shutil.copytree(small_abtf, path)
    group = zarr.open_group(path, mode="r+")
    raw = group["height"][...]
    group["height"].attrs["add_offset"] = 1.0
    group["albedo"].attrs["scale_factor"] = 2.0
    store = open_store(path)
    assert plain(store.group["radiance"]) and not plain(store.group["height"])
    assert not plain(store.group["albedo"])
    dataset = open_dataset(path)
    for name in ("radiance", "height", "albedo"):
        data, dims = lazy_variable(store, name, read_chunks(store.group, name))
        assert dims == dataset[name].dims
        assert np.array_equal(data.compute(), dataset[name].values), name
    height = lazy_variable(store, "height", read_chunks(store.group, "height"))[0].compute()
    assert np.allclose(height, raw + 1, rtol=1e-6, atol=0)  # decoded, as xarray decodes it
    masked = zarr.create_array(zarr.storage.MemoryStore(), shape=(2,), dtype="f4",
                               attributes={"_FillValue": 0.0})
    assert not plain(masked)
    masked.attrs["_FillValue"] = float("nan")  # NaN masks nothing xarray would not
    assert plain(masked)

"""Whole chunks written past zarr's event loop (pipeline.chunk_io): zarr's own bytes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import zarr

from pipeline import checksums, chunk_io, storage


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and p.name != "zarr.json"}


def _array(path: Path, shape, chunks, dtype, **kw):
    group = zarr.open_group(storage.store(path), mode="w")
    return group.create_array("a", shape=shape, chunks=chunks, dtype=dtype,
                              compressors=[zarr.codecs.BloscCodec(cname="lz4"),
                                           checksums.codec()],
                              fill_value=np.nan, dimension_names=None, **kw)


CASES = [  # shape, chunks, dtype, regions written (each block a task's)
    ((5, 7, 33, 3), (2, 3, 16, 3), np.float32,
     [(slice(0, 2), slice(0, 6), slice(0, 32), slice(0, 3)),
      (slice(4, 5), slice(6, 7), slice(32, 33), slice(0, 3)),  # the last, clipped chunk
      (slice(2, 4), slice(0, 7), slice(0, 33), slice(0, 3))]),
    ((3, 17, 9), (1, 4, 9), np.float16, [(slice(0, 3), slice(0, 17), slice(0, 9))]),
    ((4, 4), (4, 4), np.float32, [(slice(0, 4), slice(0, 4))]),
]


@pytest.mark.parametrize("shape,chunks,dtype,regions", CASES)
def test_whole_chunks_are_written_as_zarr_writes_them(tmp_path, shape, chunks, dtype, regions):
    rng = np.random.default_rng(7)
    ours, theirs = _array(tmp_path / "o.zarr", shape, chunks, dtype), \
        _array(tmp_path / "t.zarr", shape, chunks, dtype)
    assert chunk_io._writer(ours) is not None  # the path under test is taken
    for region in regions:
        block = rng.standard_normal(tuple(s.stop - s.start for s in region)).astype(dtype)
        if dtype == np.float32:
            block[..., :1] = np.nan  # the fill value inside a block is written too
        chunk_io.write(ours, region, block)
        theirs[region] = block
    mine, zarrs = _files(tmp_path / "o.zarr"), _files(tmp_path / "t.zarr")
    assert mine.keys() == zarrs.keys() and mine == zarrs
    np.testing.assert_array_equal(zarr.open_array(storage.store(tmp_path / "o.zarr"),
                                                  path="a", mode="r")[...], theirs[...])
    assert not list((tmp_path / "o.zarr").rglob("*.partial"))


def test_integer_and_open_indices_as_zarr_takes_them(tmp_path, monkeypatch):
    put, keys = chunk_io._put, []
    monkeypatch.setattr(chunk_io, "_put", lambda store, key, data: (
        keys.append(key), put(store, key, data)))
    ours, theirs = (_array(tmp_path / n, (3, 4, 6, 2), (1, 2, 6, 2), np.float32)
                    for n in ("o.zarr", "t.zarr"))
    block = np.arange(2 * 6 * 2, dtype=np.float32).reshape(2, 6, 2)
    for index in [(1, slice(2, 4)), (0, slice(0, 2), slice(None), slice(None)),
                  (np.int64(2), slice(-2, None))]:
        chunk_io.write(ours, index, block)
        theirs[index] = block
    assert _files(tmp_path / "o.zarr") == _files(tmp_path / "t.zarr")
    assert len(keys) == 3  # each a whole chunk, written here


def test_a_float64_block_is_stored_in_the_arrays_type(tmp_path):
    ours = _array(tmp_path / "o.zarr", (4, 8), (2, 8), np.float16)
    block = np.linspace(0, 1, 32).reshape(4, 8)
    chunk_io.write(ours, (slice(0, 4), slice(0, 8)), block)
    np.testing.assert_array_equal(ours[...], block.astype(np.float16))


def test_part_of_a_chunk_goes_through_zarr_and_keeps_the_rest(tmp_path):
    ours = _array(tmp_path / "o.zarr", (4, 8), (4, 4), np.float32)
    chunk_io.write(ours, (slice(0, 4), slice(0, 8)), np.ones((4, 8), np.float32))
    chunk_io.write(ours, (slice(1, 3), slice(2, 6)), np.zeros((2, 4), np.float32))
    expected = np.ones((4, 8), np.float32)
    expected[1:3, 2:6] = 0
    np.testing.assert_array_equal(ours[...], expected)


def test_sharded_and_read_only_arrays_are_left_to_zarr(tmp_path):
    sharded = _array(tmp_path / "s.zarr", (4, 8), (2, 2), np.float32, shards=(4, 4))
    assert chunk_io._writer(sharded) is None
    chunk_io.write(sharded, (slice(0, 4), slice(0, 4)), np.full((4, 4), 2, np.float32))
    np.testing.assert_array_equal(sharded[:, :4], 2)
    plain = _array(tmp_path / "p.zarr", (4, 8), (2, 2), np.float32)
    reader = zarr.open_array(storage.store(tmp_path / "p.zarr"), path="a", mode="r")
    assert chunk_io._writer(reader) is None and chunk_io._writer(plain) is not None


def test_a_failed_write_leaves_no_partial_file(tmp_path, monkeypatch):
    ours = _array(tmp_path / "o.zarr", (2, 2), (2, 2), np.float32)

    class Full(OSError):
        pass

    def fail(*args):
        raise Full("no space left on device")

    monkeypatch.setattr(chunk_io.os, "replace", fail)
    with pytest.raises(Full):
        chunk_io.write(ours, (slice(0, 2), slice(0, 2)), np.ones((2, 2), np.float32))
    monkeypatch.undo()
    assert not [p for p in (tmp_path / "o.zarr").rglob("*") if p.is_file()
                and p.name != "zarr.json"]


@pytest.mark.parametrize("dtype", [np.float32, np.float16])
def test_reads_of_any_region_are_zarrs_values_read_here(tmp_path, monkeypatch, dtype):
    array = _array(tmp_path / "r.zarr", (3, 10, 37, 2), (2, 4, 16, 2), dtype)
    rng = np.random.default_rng(3)
    values = rng.standard_normal(array.shape).astype(dtype)
    array[...] = values
    reader = chunk_io.Reader(zarr.open_array(storage.store(tmp_path / "r.zarr"), path="a",
                                             mode="r"))
    regions = [tuple(slice(a, b) for a, b in (sorted(rng.integers(0, n + 1, 2)) for n in
                                               array.shape)) for _ in range(40)]
    regions += [(slice(None),) * 4, (slice(2, 3), slice(8, 10), slice(32, 37), slice(0, 2))]

    def no_zarr(self, selection):
        raise AssertionError("read through zarr")

    with monkeypatch.context() as m:
        m.setattr(zarr.Array, "__getitem__", no_zarr)
        got = [reader[r] for r in regions]
        np.testing.assert_array_equal(chunk_io.read(reader.array, (2, slice(3, 9))),
                                      values[2, 3:9])
        np.testing.assert_array_equal(chunk_io.read(reader.array, (1, 7, np.int64(20))),
                                      values[1, 7, 20])
    for region, values_read in zip(regions, got, strict=True):
        assert values_read.dtype == dtype
        np.testing.assert_array_equal(values_read, values[region])


def test_a_missing_or_damaged_chunk_is_read_by_zarr_with_its_error(tmp_path):
    from pipeline.checksums import ChecksumError

    array = _array(tmp_path / "r.zarr", (4, 8), (2, 4), np.float32)
    array[...] = np.arange(32, dtype=np.float32).reshape(4, 8)
    reader = chunk_io.Reader(zarr.open_array(storage.store(tmp_path / "r.zarr"), path="a",
                                             mode="r"))
    (tmp_path / "r.zarr" / "a" / "c" / "0" / "1").unlink()  # not sealed: zarr's fill value
    got = reader[(slice(0, 4), slice(0, 8))]
    assert np.isnan(got[:2, 4:]).all() and np.array_equal(got[2:], array[2:])
    chunk = tmp_path / "r.zarr" / "a" / "c" / "1" / "0"
    data = bytearray(chunk.read_bytes())
    data[5] ^= 0x01
    chunk.write_bytes(bytes(data))
    with pytest.raises(ChecksumError):
        reader[(slice(2, 4), slice(0, 4))]


def test_stages_read_stores_here(tmp_path, monkeypatch):
    """A stage's dataset reads its radiance chunks here, not through zarr."""
    from helpers import generate_store
    from pipeline.stores.radiance import open_radiance

    store = generate_store(tmp_path / "s.zarr", "--material", "wood", "--size", "32",
                           "--sampling", "abtf:4,1", "--chunk", "16", "--dir-chunk", "2")
    expected = zarr.open_group(store, mode="r")["radiance"][...]
    ds = open_radiance(store)

    def no_zarr(self, selection):
        raise AssertionError("read through zarr")

    monkeypatch.setattr(zarr.Array, "__getitem__", no_zarr)
    np.testing.assert_array_equal(ds["radiance"].values, expected)


def test_negative_and_inner_integers_as_zarr_takes_them(tmp_path):
    ours, theirs = (_array(tmp_path / n, (3, 4, 5), (1, 1, 5), np.float32)
                    for n in ("o.zarr", "t.zarr"))
    for index, block in [((-1, slice(None)), np.ones((4, 5))),
                         ((slice(None), 1), np.arange(15.0).reshape(3, 5)),
                         ((0, -2, slice(0, 5)), np.full(5, 7.0))]:
        chunk_io.write(ours, index, block)
        theirs[index] = block
        np.testing.assert_array_equal(chunk_io.read(ours, index), theirs[index])
    assert _files(tmp_path / "o.zarr") == _files(tmp_path / "t.zarr")
    with pytest.raises(IndexError):
        chunk_io.read(ours, (3,))  # out of range: zarr's error


def test_variables_xarray_decodes_are_left_to_xarray(tmp_path):
    import xarray as xr

    from pipeline.stores.radiance import open_dataset

    values = np.array([[1, -1, 2], [3, 4, -1]], np.float32)
    xr.Dataset({"plain": (("y", "x"), values), "masked": (("y", "x"), values),
                "unfilled": (("y", "x"), values)}).to_zarr(
        tmp_path / "d.zarr", zarr_format=3, consolidated=False,
        encoding={"masked": {"_FillValue": -1.0}, "plain": {"_FillValue": np.nan},
                  "unfilled": {"_FillValue": None}})
    ds = open_dataset(tmp_path / "d.zarr")
    np.testing.assert_array_equal(ds["plain"].values, [[1, -1, 2], [3, 4, -1]])
    np.testing.assert_array_equal(ds["masked"].values, [[1, np.nan, 2], [3, 4, np.nan]])
    np.testing.assert_array_equal(ds["unfilled"].values, values)
    assert ds["plain"].data.name.startswith("read-")  # read here

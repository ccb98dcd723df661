"""The store contract (docs/README.md): layout, validation, and shard-safe writes."""

from __future__ import annotations

import functools
import json
import tempfile
import warnings
from pathlib import Path

import dask
import dask.array as da
import numpy as np
import pytest
import xarray as xr
import zarr
from dask.array.core import slices_from_chunks
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.errors import BTFError
from pipeline.graphs.blocks import aligned_chunks, read_chunks, store_aligned
from pipeline.stores.base import RADIANCE, Directions
from pipeline.stores.radiance import Layout, create_radiance_store, open_radiance

DIRS = Directions(np.array([0.0, 30.0]), np.array([0.0, 90.0]), np.arange(5.0) * 10,
                  np.arange(5.0) * 45)


LAYOUT = Layout(chunk=8, dir_chunk=2, shard=16)


def _create(path, ny=40, nx=24, layout=LAYOUT):
    return create_radiance_store(path, directions=DIRS, ny=ny, nx=nx, channels=("R", "G", "B"),
                                 layout=layout, attrs={"btf_kind": "btf", "source": "test"})


def _values(shape):
    return np.arange(np.prod(shape), dtype=np.float32).reshape(shape)


@settings(deadline=None)
@given(st.integers(1, 2000), st.sampled_from([8, 16, 64, 128]), st.integers(0, 8),
       st.integers(1, 600))
def test_layout_chunks_divide_shards_and_cover_the_axis(n, chunk, shard_chunks, task_texels):
    import pipeline.graphs.blocks as blocks

    layout = Layout(chunk=chunk, shard=chunk * shard_chunks)
    c, s = layout.spatial(n)
    assert 1 <= c <= max(n, 1) and c <= chunk
    if s is not None:
        assert s % c == 0 and c < s <= max(layout.shard, c) and s < n + c
    # An axis laid out so, as zarr stores it: the task blocks over it cover every element
    # exactly once, each made of whole write units (the last one may be partial).
    array = zarr.create_array(zarr.storage.MemoryStore(), shape=(n,), dtype="f4", chunks=(c,),
                              shards=(s,) if s else None, dimension_names=("y",))
    unit = s or c
    assert blocks.write_unit(array) == (unit,)
    count = np.zeros(n, np.int32)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(blocks, "TASK_TEXELS", task_texels)
        regions = slices_from_chunks(blocks.aligned_chunks(array))
    for (region,) in regions:
        count[region] += 1
        assert region.start % unit == 0 and (region.stop % unit == 0 or region.stop == n)
    assert (count == 1).all()
    assert len(regions) == -(-n // (unit * max(1, task_texels // unit)))


@settings(max_examples=25, deadline=None)
@given(st.integers(1, 90), st.integers(1, 70), st.integers(1, 7),
       st.sampled_from([8, 16]), st.integers(0, 3), st.integers(8, 40),
       st.sampled_from([None, 1, 500, 5000]))
def test_task_blocks_cover_every_element_once_in_whole_write_units(ny, nx, lights, chunk,
                                                                   shard_chunks, task_texels,
                                                                   grouped_values):
    """Also grouped across directions (``grouped_values``: TASK_VALUES, None: not grouped):
    still whole units, and no larger than the budget unless one direction's block is."""
    import pipeline.graphs.blocks as blocks

    with pytest.MonkeyPatch.context() as mp, tempfile.TemporaryDirectory() as tmp:
        mp.setattr(blocks, "TASK_TEXELS", task_texels)
        mp.setattr(blocks, "TASK_VALUES", grouped_values or 1)
        d = Directions(np.zeros(2), np.zeros(2), np.arange(lights) * 5.0, np.zeros(lights))
        array = create_radiance_store(
            Path(tmp) / "s.zarr", directions=d, ny=ny, nx=nx, channels=("R",),
            layout=Layout(chunk=chunk, dir_chunk=3, shard=chunk * shard_chunks),
            attrs={})[RADIANCE]
        count = np.zeros(array.shape, np.int32)
        unit = blocks.write_unit(array)
        grouped = grouped_values is not None
        one = np.prod([min(b, n) for b, n in zip(blocks.task_block(array), array.shape,
                                                  strict=True)])
        chunks = blocks.aligned_chunks(array, grouped=grouped)
        for region in slices_from_chunks(chunks):
            count[region] += 1
            for r, u, n in zip(region, unit, array.shape, strict=True):
                assert r.start % u == 0 and (r.stop % u == 0 or r.stop == n)
            size = np.prod([r.stop - r.start for r in region])
            assert size <= max(one, grouped_values or 0)
        assert (count == 1).all()
        if grouped and grouped_values >= array.size:  # one block per spatial block: all
            spatial = blocks.aligned_chunks(array)[2:4]  # directions in each
            assert len(slices_from_chunks(chunks)) == len(spatial[0]) * len(spatial[1])


def test_layout_rejects_shards_that_are_not_chunk_multiples():
    with pytest.raises(ValueError, match="multiple"):
        Layout(chunk=64, shard=100)


def test_created_store_opens_with_xarray_as_the_contract_says(tmp_path):
    group = _create(tmp_path / "s.zarr")
    group[RADIANCE][:] = _values(group[RADIANCE].shape)
    ds = xr.open_zarr(tmp_path / "s.zarr", consolidated=False)  # plain xarray, no helper
    assert ds[RADIANCE].dims == ("view", "light", "y", "x", "channel")
    assert ds[RADIANCE].dtype == np.float32
    assert ds["theta_light"].dims == ("light",) and ds["phi_view"].dims == ("view",)
    assert [str(c) for c in ds["channel"].values] == ["R", "G", "B"]
    assert np.array_equal(ds["theta_light"].values, DIRS.theta_light)
    assert ds.attrs["btf_kind"] == "btf"
    assert np.array_equal(ds[RADIANCE].values, _values(group[RADIANCE].shape))


@pytest.fixture
def shard_sized_tasks(monkeypatch):
    """Tasks of exactly one shard: the most concurrent writers a store can have."""
    monkeypatch.setattr("pipeline.graphs.blocks.TASK_TEXELS", 16)


def test_open_radiance_reads_whole_write_units(tmp_path, shard_sized_tasks):
    _create(tmp_path / "s.zarr")
    ds = open_radiance(tmp_path / "s.zarr", read_chunks)
    assert ds[RADIANCE].data.chunksize == (1, 2, 16, 16, 3)


def test_task_blocks_are_whole_write_units_of_about_task_texels(tmp_path):
    group = _create(tmp_path / "s.zarr", ny=1100, nx=700, layout=Layout(chunk=96, shard=192))
    chunks = aligned_chunks(group[RADIANCE])
    assert chunks[2] == (384, 384, 332) and chunks[3] == (384, 316)
    assert chunks[1] == (5,)  # dir_chunk 16 covers all 5 lights


def test_store_aligned_refuses_chunks_that_split_shards(tmp_path):
    group = _create(tmp_path / "s.zarr")
    data = da.zeros(group[RADIANCE].shape, chunks=(1, 2, 8, 8, 3), dtype=np.float32)
    with pytest.raises(ValueError, match="split write units"):
        store_aligned([data], [group[RADIANCE]])


# a pool of fresh interpreters in the slow set, as a local cluster's worker processes writing
# (test_shard_aligned_writes_from_a_local_cluster_keep_every_value)
@pytest.mark.parametrize("scheduler", ["threads", pytest.param("processes",
                                                               marks=pytest.mark.slow)])
def test_shard_aligned_parallel_writes_keep_every_value(tmp_path, scheduler, shard_sized_tasks):
    group = _create(tmp_path / "s.zarr", ny=70, nx=52)
    shape = group[RADIANCE].shape
    data = da.from_array(_values(shape), chunks=aligned_chunks(group[RADIANCE]))
    with dask.config.set(scheduler=scheduler, num_workers=2):
        dask.compute(store_aligned([data], [group[RADIANCE]]))
    assert np.array_equal(zarr.open_array(tmp_path / "s.zarr", path=RADIANCE)[:], _values(shape))


def test_an_input_several_outputs_share_is_computed_once_per_block(tmp_path):
    """As in ``btf generate``: radiance and four truth arrays from one block of fields each.

    Optimised output by output, dask would fuse the shared input into each output's tasks and
    compute every block of fields five times.
    """
    from pipeline.resume import Progress

    group = zarr.open_group(tmp_path / "s.zarr", mode="w")
    targets = [group.create_array(f"a{k}", shape=(16, 12), chunks=(8, 4), dtype="f4")
               for k in range(3)]
    calls = []

    def fields(block_info=None):
        calls.append(tuple(block_info[None]["chunk-location"]))
        return np.full((8, 4, 2), len(calls), np.float32)

    shared = da.map_blocks(fields, chunks=((8, 8), (4, 4, 4), (2,)), dtype=np.float32,
                           meta=np.empty((0, 0, 0), np.float32))
    sources = [shared.sum(-1), shared[..., 0], shared[..., 1] * 2]
    dask.compute(store_aligned(sources, targets, progress=Progress(tmp_path / "s.zarr")),
                 scheduler="sync")
    assert len(calls) == len(set(calls)) == 6  # 2 x 3 blocks, each once
    first = targets[1][:]
    np.testing.assert_array_equal(targets[0][:], first * 2)
    np.testing.assert_array_equal(targets[2][:], first * 2)


@pytest.mark.slow  # 3 s (a cluster): kept out of the default run (4 min), run by .ci/run
@pytest.mark.distributed
def test_shard_aligned_writes_from_a_local_cluster_keep_every_value(tmp_path, local_cluster,
                                                                    shard_sized_tasks):
    from distributed import Client

    group = _create(tmp_path / "s.zarr", ny=70, nx=52)
    shape = group[RADIANCE].shape
    data = da.from_array(_values(shape), chunks=aligned_chunks(group[RADIANCE]))
    with Client(local_cluster) as client:
        client.compute(store_aligned([data], [group[RADIANCE]])).result()
    assert np.array_equal(zarr.open_array(tmp_path / "s.zarr", path=RADIANCE)[:], _values(shape))


@settings(deadline=None, max_examples=60)
@given(st.lists(st.integers(0, 300), min_size=1, max_size=5), st.data())
def test_aligned_chunks_are_dasks_normal_chunks_of_the_task_blocks(shape, data):
    """aligned_chunks covers an array as dask's normalize_chunks does (without dask.array)."""
    from dask.array.core import normalize_chunks

    import pipeline.graphs.blocks as blocks

    class Array:  # the attributes task_block reads
        def __init__(self, shape, block):
            self.shape, self.ndim, self.shards = tuple(shape), len(shape), None
            self.chunks = block
            self.metadata = type("M", (), {"dimension_names": None})()

    block = tuple(data.draw(st.integers(1 if n else 0, 400)) for n in shape)
    array = Array(shape, block)
    assert blocks.aligned_chunks(array) == normalize_chunks(blocks.task_block(array), array.shape)
    if len(shape) == 5:  # a radiance array's axes, grouped: an empty one's block may be 0
        array.metadata.dimension_names = ("view", "light", "y", "x", "channel")
        grouped = blocks.task_block(array, grouped=True)
        assert blocks.aligned_chunks(array, grouped=True) == normalize_chunks(grouped, shape)


@pytest.mark.parametrize("scheduler", ["threads", "sync"])
def test_blocks_made_by_plain_tasks_are_written_whole(tmp_path, scheduler, shard_sized_tasks):
    """store_blocks: every block made by its own task and written where it lies; blocks that
    split a write unit or do not cover the array are refused."""
    from pipeline.graphs.blocks import store_blocks

    group = _create(tmp_path / "s.zarr", ny=70, nx=52)
    target = group[RADIANCE]
    values = _values(target.shape)
    chunks = aligned_chunks(target)
    starts = [np.cumsum((0, *c)) for c in chunks]
    made = []

    def make(index):
        region = tuple(slice(s[i], s[i + 1]) for s, i in zip(starts, index, strict=True))
        return lambda: made.append(index) or values[region]

    with dask.config.set(scheduler=scheduler, num_workers=2):
        (count,) = dask.compute(store_blocks(target, chunks, make))
    assert count == len(made) == len(set(made)) == np.prod([len(c) for c in chunks]) > 4
    assert np.array_equal(zarr.open_array(tmp_path / "s.zarr", path=RADIANCE)[:], values)
    split = (chunks[0], chunks[1], (8, *chunks[2][1:-1], chunks[2][-1] + chunks[2][0] - 8),
             *chunks[3:])
    with pytest.raises(ValueError, match="split write units"):
        store_blocks(target, split, make)
    with pytest.raises(ValueError, match="do not cover"):
        store_blocks(target, (*chunks[:-1], (2,)), make)


def test_blocks_made_by_plain_tasks_resume_as_store_aligneds_units(tmp_path, shard_sized_tasks):
    """store_blocks marks the units store_aligned marks (a run killed under one resumes under
    the other), and refuses a block of another type or shape than its place."""
    from pipeline.graphs.blocks import store_blocks
    from pipeline.resume import Progress

    names = []
    for how in ("aligned", "blocks"):
        group = _create(tmp_path / f"{how}.zarr", ny=70, nx=52)
        target, progress = group[RADIANCE], Progress(tmp_path / f"{how}.zarr")
        chunks = aligned_chunks(target)
        values = _values(target.shape)
        write = (store_aligned([da.from_array(values, chunks=chunks)], [target],
                               progress=progress) if how == "aligned" else
                 store_blocks(target, chunks, _cut(values, chunks), progress=progress))
        dask.compute(write, scheduler="sync")
        names.append(sorted(progress._names()))
        assert np.array_equal(target[...], values)
    assert names[0] == names[1] and len(names[0]) > 4
    group = _create(tmp_path / "bad.zarr", ny=70, nx=52)
    chunks = aligned_chunks(group[RADIANCE])
    for bad in (np.zeros((1, 2, 16, 16, 3), np.float64), np.zeros((1, 1, 16, 16, 3), np.float32)):
        with pytest.raises(ValueError, match="a block of"):
            dask.compute(store_blocks(group[RADIANCE], chunks, lambda index, bad=bad: lambda: bad),
                         scheduler="sync")


@pytest.mark.slow  # 5 s (a cluster): kept out of the default run (4 min), run by .ci/run
@pytest.mark.distributed
def test_blocks_made_by_plain_tasks_are_written_from_a_local_cluster(tmp_path, local_cluster,
                                                                     shard_sized_tasks):
    from distributed import Client

    from pipeline.graphs.blocks import store_blocks

    group = _create(tmp_path / "s.zarr", ny=70, nx=52)
    target = group[RADIANCE]
    chunks = aligned_chunks(target)
    starts = [np.cumsum((0, *c)) for c in chunks]
    with Client(local_cluster) as client:
        client.compute(store_blocks(target, chunks, lambda index: functools.partial(
            _block_of, target.shape, tuple((int(s[i]), int(s[i + 1])) for s, i in zip(
                starts, index, strict=True))))).result()
    assert np.array_equal(zarr.open_array(tmp_path / "s.zarr", path=RADIANCE)[:],
                          _values(target.shape))


def _cut(values, chunks):
    """``make`` of store_blocks: block ``index`` of ``values`` cut by ``chunks``."""
    starts = [np.cumsum((0, *c)) for c in chunks]
    return lambda index: lambda: values[tuple(slice(s[i], s[i + 1]) for s, i in zip(
        starts, index, strict=True))]


def _block_of(shape, bounds):
    return _values(shape)[tuple(slice(a, b) for a, b in bounds)]


def _break(path, how):
    group = zarr.open_group(path, mode="r+")
    if how == "no radiance":
        del group[RADIANCE]
    elif how == "wrong dims":
        del group[RADIANCE]
        group.create_array(RADIANCE, shape=(2, 5, 4, 4), dtype="float32",
                           dimension_names=("view", "light", "y", "x"))
    elif how == "wrong dtype":
        del group[RADIANCE]
        group.create_array(RADIANCE, shape=(2, 5, 4, 4, 3), dtype="float64",
                           dimension_names=("view", "light", "y", "x", "channel"))
    elif how == "no coordinate":
        del group["phi_light"]


@pytest.mark.parametrize(("how", "message"), [
    ("no radiance", "no variable 'radiance'"), ("wrong dims", "has dims"),
    ("wrong dtype", "is float64, expected float32"), ("no coordinate", "'phi_light' is missing"),
])
def test_invalid_stores_are_refused_with_the_reason(tmp_path, how, message):
    path = tmp_path / "s.zarr"
    _create(path)
    _break(path, how)
    with pytest.raises(BTFError, match=message) as info:
        open_radiance(path)
    assert str(path) in str(info.value)


def test_things_that_are_not_stores_are_refused(tmp_path):
    with pytest.raises(BTFError, match="no such store"):
        open_radiance(tmp_path / "missing.zarr")
    (tmp_path / "folder").mkdir()
    with pytest.raises(BTFError, match="not a zarr v3 store"):
        open_radiance(tmp_path / "folder")
    v2 = tmp_path / "v2.zarr"
    v2.mkdir()
    (v2 / ".zgroup").write_text(json.dumps({"zarr_format": 2}))
    with pytest.raises(BTFError, match="zarr v2"):
        open_radiance(v2)
    zarr.create_array(tmp_path / "array.zarr", shape=(3,), dtype="f4")
    with pytest.raises(BTFError, match="not a group"):
        open_radiance(tmp_path / "array.zarr")


def _members(path: Path, consolidated: bool) -> dict:
    group = zarr.open_group(path, mode="r", use_consolidated=consolidated)
    return {name: (a.shape, str(a.dtype), dict(a.attrs)) for name, a in group.arrays()}


def test_every_store_a_stage_writes_opens_quietly_with_consolidated_metadata(btf, tmp_path):
    """xarray.open_zarr(path) warned on every store; the consolidated copy matches the files."""
    s = tmp_path
    runs = [("generate", s / "g.zarr", "--material", "fabric", "--size", "48", "--sampling",
             "abtf:4,2"),
            ("crop", s / "g.zarr", s / "c.zarr", "--region", "0:40,8:48"),
            ("compress", s / "c.zarr", s / "svd.zarr", "--rank", "4"),
            ("reconstruct", s / "svd.zarr", s / "r.zarr", "--light", "0,1"),
            ("quilt", s / "c.zarr", s / "q.zarr", "--block", "16", "--overlap", "4"),
            ("render", s / "q.zarr", s / "surface.zarr", "--light", "0", "--size", "64,64"),
            ("fit", s / "g.zarr", s / "f.zarr"),
            ("crop", s / "g.zarr", s / "photo.zarr", "--light", "0"),
            ("crop", s / "g.zarr", s / "sample.zarr", "--region", "12:36,12:36"),
            ("compress", s / "sample.zarr", s / "sample_svd.zarr", "--rank", "4"),
            ("enlarge", s / "sample_svd.zarr", s / "photo.zarr", s / "e.zarr",
             "--sample-origin", "12,12", "--levels", "1", "--iterations", "1", "--rounds", "1")]
    outputs = []
    for stage, *args in runs:
        result = btf(stage, *args, "--quiet")
        assert result.code == 0, (stage, result.err)
        outputs.append(Path(args[1] if stage != "generate" else args[0]))
        if stage == "enlarge":
            outputs[-1] = Path(args[2])
    for path in dict.fromkeys(outputs):
        meta = json.loads((path / "zarr.json").read_text())
        assert "consolidated_metadata" in meta, path
        assert _members(path, True) == _members(path, False), path
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            xr.open_zarr(path).close()

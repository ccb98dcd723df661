"""Precision is the store's: float16 radiance stores and eigentextures, read as float32.

A float16 store is the float32 store rounded once: every stage reads it as float32, so what it
computes from it differs from the float32 run by what that rounding moves (at most 2^-11 of a
value), and nothing else.
"""

from __future__ import annotations

import numpy as np
import pytest
import zarr

from helpers import HALF_ROUNDING, generate_store, no_partial_outputs, stored_dtype
from pipeline.images import write_exr
from pipeline.planning import shape_of
from pipeline.stores import open_layers
from pipeline.stores.radiance import Layout, LayoutOptions, stored
from tasks.colour import DECODINGS, decoding_table
from tasks.errors import InvalidParameter


def _radiance(path) -> np.ndarray:
    return zarr.open_group(path, mode="r")["radiance"][...]


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    """A generated float32 store and the same material generated as float16."""
    tmp = tmp_path_factory.mktemp("precision")
    args = ("--material", "stone", "--size", "72", "--sampling", "abtf:8,3", "--seed", "5",
            "--chunk", "32", "--dir-chunk", "8")
    single = generate_store(tmp / "f32.zarr", *args)
    half = generate_store(tmp / "f16.zarr", *args, "--dtype", "float16")
    return tmp, single, half


@pytest.mark.parametrize("decoding", DECODINGS)
def test_every_8bit_code_survives_float16(decoding):
    # what "loses nothing" means: each of the 256 codes, decoded to linear and stored as
    # float16, is still nearer its own decoded value than any other code's
    table = decoding_table(decoding).astype(np.float64)
    half = table.astype(np.float16).astype(np.float64)
    nearest = np.abs(half[:, None] - table[None, :]).argmin(axis=1)
    assert np.array_equal(nearest, np.arange(256))
    assert np.all(np.abs(half - table) <= HALF_ROUNDING * table + 6e-8)  # subnormals near 0


def test_a_float16_store_is_the_float32_store_rounded_once(pair):
    tmp, single, half = pair
    assert stored_dtype(single) == "float32" and stored_dtype(half) == "float16"
    assert np.array_equal(_radiance(half), _radiance(single).astype(np.float16))
    # truth fields stay float32, and a crop to float16 rounds the same way
    assert zarr.open_group(half, mode="r")["height"].dtype == np.float32
    from pipeline.cli import main

    assert main(["crop", str(single), str(tmp / "crop16.zarr"), "--dtype", "float16",
                 "-q"]) == 0
    assert np.array_equal(_radiance(tmp / "crop16.zarr"), _radiance(half))
    # stages read it as float32
    layers = open_layers(half)["radiance"]
    assert layers.dtype == np.float32 and layers.encoding["chunks"] == (1, 8, 32, 32, 3)


def test_estimates_take_the_bytes_per_value_from_the_store(pair):
    _, single, half = pair
    assert shape_of(str(single)).itemsize == 4 and shape_of(str(half)).itemsize == 2
    from pipeline.stages.compress import STAGE as COMPRESS
    from pipeline.stages.crop import STAGE as CROP

    for stage, extra in ((COMPRESS, {"rank": 4}), (CROP, {})):
        plans = {}
        for name, path in (("single", single), ("half", half)):
            params = stage.params(store=str(path), out="/tmp/never.zarr", **extra)
            plans[name], _ = stage.estimate(params, {str(path): shape_of(str(path))})
        values = int(np.prod(shape_of(str(single)).radiance))
        passes = plans["single"].input_reads  # the truth fields stay float32
        assert plans["single"].bytes_read - plans["half"].bytes_read == 2 * values * passes


def test_compressing_a_float16_store_moves_s_by_its_rounding_only(pair, btf):
    tmp, single, half = pair
    for name, src in (("c32", single), ("c16", half)):
        assert btf("compress", src, tmp / f"{name}.zarr", "--rank", "6", "-q").code == 0
    s32 = zarr.open_group(tmp / "c32.zarr", mode="r")["S"][...].astype(np.float64)
    s16 = zarr.open_group(tmp / "c16.zarr", mode="r")["S"][...].astype(np.float64)
    # log(x + eps) moves by at most 2^-11 x / (x + eps) per value: S by at most that norm
    assert np.all(np.abs(s16 - s32) <= HALF_ROUNDING * np.linalg.norm(s32))
    assert np.abs(s16 - s32).max() > 0  # the rounding is there: the stage read the float16


def test_float16_eigentextures_add_at_most_their_rounding(pair, btf):
    tmp, single, _ = pair
    for name, extra in (("v32", ()), ("v16", ("--v-dtype", "float16"))):
        assert btf("compress", single, tmp / f"{name}.zarr", "--rank", "5", "-q",
                   *extra).code == 0
    g32, g16 = (zarr.open_group(tmp / f"{n}.zarr", mode="r") for n in ("v32", "v16"))
    assert g16["V"].dtype == np.float16 and g32["V"].dtype == np.float32
    v32 = g32["V"][...].astype(np.float64)
    assert np.array_equal(g16["V"][...], v32.astype(np.float16))  # the same SVD, V rounded
    # a compressed store brought to a lower rank keeps its V's type unless told
    assert btf("compress", tmp / "v16.zarr", tmp / "v16r3.zarr", "--rank", "3", "-q").code == 0
    assert zarr.open_group(tmp / "v16r3.zarr", mode="r")["V"].dtype == np.float16
    rebuilt = {n: open_layers(tmp / f"{n}.zarr")["radiance"].values for n in ("v32", "v16")}
    assert rebuilt["v16"].dtype == np.float32
    # each log value moves by at most 2^-11 sum_k |u_k s_k v_k|: bounded by the
    # layer's norm times that rounding (a loose form of the bound, still 1000x under 1)
    log32, log16 = (np.log(rebuilt[n].astype(np.float64) + 1e-3) for n in ("v32", "v16"))
    s = g32["S"][...].astype(np.float64)
    u = np.abs(g32["U"][...].astype(np.float64))
    bound = HALF_ROUNDING * np.einsum("vlck,k,yxk->vlyxc", u, s, np.abs(v32)) * 1.01 + 1e-6
    assert np.all(np.abs(log16 - log32) <= bound)


def test_a_tile_set_keeps_the_float16_of_its_sample(pair, btf):
    tmp, _, half = pair
    assert btf("quilt", half, tmp / "q16.zarr", "-q").code == 0
    tiles = zarr.open_group(tmp / "q16.zarr", mode="r")
    assert tiles["radiance"].dtype == np.float16
    assert btf("render", tmp / "q16.zarr", tmp / "s.exr", "--size", "90,70", "--light", "2",
               "-q").code == 0


def test_float32_values_beyond_float16_are_refused_by_name(tmp_path, btf):
    src = tmp_path / "src"
    src.mkdir()
    for phi in (0, 90):
        pixels = np.full((8, 8, 3), 0.5, np.float32)
        if phi == 90:
            pixels[3, 4, 1] = 1e6  # a bright highlight: fine in float32, not in float16
        write_exr(src / f"tl30_pl{phi}_tv0_pv0.exr", pixels, ("R", "G", "B"))
    assert btf("ingest", src, tmp_path / "ok.zarr", "-q").code == 0
    assert stored_dtype(tmp_path / "ok.zarr") == "float32"  # float EXRs: float32 by default
    result = btf("ingest", src, tmp_path / "bad.zarr", "--dtype", "float16", "-q")
    assert result.code != 0
    assert "tl30_pl90_tv0_pv0.exr" in result.err and "float16" in result.err, result.err
    assert "--dtype float32" in result.err
    assert no_partial_outputs(tmp_path / "bad.zarr")


def test_half_exr_layers_are_stored_as_float16_exactly(tmp_path, btf):
    src = tmp_path / "src"
    src.mkdir()
    rng = np.random.default_rng(1)
    pictures = {}
    for phi in (0, 90):
        pictures[phi] = (rng.random((6, 7, 3)) * 40).astype(np.float16)
        write_exr(src / f"tl30_pl{phi}_tv0_pv0.exr", pictures[phi], ("R", "G", "B"), half=True)
    result = btf("ingest", src, tmp_path / "s.zarr")
    assert result.code == 0 and "stored as float16 (half samples" in result.err
    values = _radiance(tmp_path / "s.zarr")
    assert values.dtype == np.float16
    phis = zarr.open_group(tmp_path / "s.zarr", mode="r")["phi_light"][...]
    for j, phi in enumerate(phis):
        assert np.array_equal(values[0, j], pictures[int(phi)])  # bit for bit


def test_layout_options_take_the_input_store_where_unset():
    like = Layout(chunk=64, dir_chunk=4, shard=256, dtype="float16")
    assert LayoutOptions().layout() == Layout()
    assert LayoutOptions().layout(like) == like
    assert LayoutOptions(chunk=32).layout(like) == Layout(32, 4, 0, "float16")  # no shard
    assert LayoutOptions(dtype="float32").layout(like).dtype == "float32"
    assert LayoutOptions().layout(dtype="float16").dtype == "float16"
    with pytest.raises(InvalidParameter, match="float64"):
        Layout(dtype="float64")


def test_stored_refuses_overflow_and_keeps_what_fits():
    values = np.array([0.5, 65504.0, np.nan, np.inf], np.float32)
    assert np.array_equal(stored(values, np.float16, "x"), values.astype(np.float16),
                          equal_nan=True)  # NaN and infinity given stay what they were
    with pytest.raises(Exception, match="x: a value of 70000 exceeds float16"):
        stored(np.array([70000.0], np.float32), np.float16, "x")

"""Bonn DFMF .btf files in and out (issue 32): ingest without expansion, export, bad files.

The files are written by tests/dfmf_files.py from the format description (not by the exporter
under test), and decoded there by a plain reimplementation of btflib's colour models.
"""

from __future__ import annotations

import struct

import numpy as np
import pytest
import zarr
from dfmf_files import reference_decode, write_dfmf

from helpers import no_partial_outputs
from pipeline.dfmf_io import read_header
from pipeline.stores.base import RADIANCE
from pipeline.stores.compressed import open_compressed
from tasks.transform import DFMF_MODELS

WIDTH, HEIGHT = 19, 11  # odd, not square, more than one 8-texel tile: a transposed order fails
VIEWS = [(0.0, 0.0), (0.3, 1.2), (0.6, -2.0)]  # radians, phi in (-pi, pi] as Bonn's files
LIGHTS = [(0.0, 0.0), (0.5, 0.4), (0.9, 3.0), (1.1, -1.5)]


def _factors(rng, model: int, ks=(3, 2, 4)):
    """Per-channel U and S x V whose decoded radiance is moderate and mostly positive."""
    rows, texels = len(VIEWS) * len(LIGHTS), WIDTH * HEIGHT
    u, sxv = [], []
    for c, k in enumerate(ks):
        uc = rng.normal(size=(rows, k)) * 0.3
        vc = rng.normal(size=(texels, k)) * 0.3
        log_like = model in (9, 10, 11, 12) and (c == 0 or model == 12)
        uc[:, 0] = (-1.0 if log_like else 0.5) + rng.normal(size=rows) * 0.1
        vc[:, 0] = 1.0
        if model in (9, 10, 11) and c > 0:
            uc *= 0.1  # chroma well inside the gamut
        if model in (0, 1, 3, 4) and c > 0:
            uc *= 0.2
        u.append(uc)
        sxv.append(vc)
    return u, sxv


def _write(path, rng, model, *, scalar_size=4, ks=(3, 2, 4), **kw):
    u, sxv = _factors(rng, model, ks)
    if model == 3:
        kw.setdefault("color_matrix", np.array([[0.9, 0.1, 0.05], [0.2, 0.7, -0.1],
                                                [0.0, 0.3, 1.1]]))
        kw.setdefault("color_mean", (0.2, 0.3, 0.25))
    write_dfmf(path, views=VIEWS, lights=LIGHTS, u=u, sxv=sxv, width=WIDTH, height=HEIGHT,
               color_model=model, scalar_size=scalar_size, **kw)
    return u, sxv, kw


def _expected(u, sxv, model, kw, scalar_size):
    if scalar_size == 2:  # what the file holds
        u = [x.astype(np.float16).astype(np.float64) for x in u]
        sxv = [x.astype(np.float16).astype(np.float64) for x in sxv]
    return np.maximum(reference_decode(u, sxv, color_model=model, width=WIDTH, height=HEIGHT,
                                       lights=LIGHTS, **kw), 0)


@pytest.mark.parametrize("model", sorted(DFMF_MODELS))
@pytest.mark.parametrize("scalar_size", [2, 4])
def test_a_dfmf_file_becomes_a_compressed_store_that_decodes_like_bonns_reader(
        tmp_path, btf, model, scalar_size):
    rng = np.random.default_rng(model * 10 + scalar_size)
    u, sxv, kw = _write(tmp_path / "m.btf", rng, model, scalar_size=scalar_size)
    r = btf("ingest", tmp_path / "m.btf", tmp_path / "m.zarr", "--chunk", "8", "--quiet")
    assert r.code == 0, r.err
    ds = open_compressed(tmp_path / "m.zarr")
    got = ds[RADIANCE].values  # (view, light, y, x, channel)
    expected = _expected(u, sxv, model, kw, scalar_size)
    scale = np.abs(expected).max()
    assert got.shape == expected.shape == (3, 4, HEIGHT, WIDTH, 3)
    assert np.allclose(got, expected, rtol=1e-4, atol=1e-5 * scale), (
        model, np.abs(got - expected).max(), scale)
    # the exact SVD of the file's factors: orthonormal U and V, decreasing S
    g = zarr.open_group(tmp_path / "m.zarr", mode="r")
    k = g["S"].shape[0]
    uu = g["U"][...].reshape(-1, k).astype(np.float64)
    vv = g["V"][...].reshape(-1, k).astype(np.float64)
    assert np.allclose(uu.T @ uu, np.eye(k), atol=1e-5)
    assert np.allclose(vv.T @ vv, np.eye(k), atol=1e-5)
    assert np.all(np.diff(g["S"][...]) <= 0)
    assert g.attrs["transform"]["dfmf_colour_model"] == model
    # directions in degrees, phi in [0, 360)
    assert np.allclose(ds["theta_light"].values, np.degrees([t for t, _ in LIGHTS]))
    phi = np.degrees([p for _, p in LIGHTS]) % 360
    phi[0] = 0.0
    assert np.allclose(ds["phi_light"].values, phi)
    assert np.allclose(ds["phi_view"].values[2], np.degrees(-2.0) % 360)


@pytest.mark.parametrize(("model", "args"), [(11, ()), (12, ("--dtype", "float16")),
                                           (9, ("--chunk", "8", "--dir-chunk", "3"))])
def test_radiance_decodes_every_layer_into_a_radiance_store(tmp_path, btf, model, args):
    """``--radiance``: the layers Bonn's reader decodes, in a radiance store of the layout
    asked for (tiles and light blocks cut at odd places), the same as the factors' store."""
    from pipeline.stores.radiance import open_radiance

    rng = np.random.default_rng(40 + model)
    u, sxv, kw = _write(tmp_path / "m.btf", rng, model, scalar_size=2)
    r = btf("ingest", tmp_path / "m.btf", tmp_path / "r.zarr", "--radiance", *args, "--quiet")
    assert r.code == 0, r.err
    ds = open_radiance(tmp_path / "r.zarr")
    got = ds[RADIANCE].values.astype(np.float64)
    expected = _expected(u, sxv, model, kw, 2)
    scale = np.abs(expected).max()
    tol = dict(rtol=1e-3, atol=1e-3 * scale) if "float16" in args else dict(rtol=1e-4,
                                                                             atol=1e-5 * scale)
    assert got.shape == expected.shape == (3, 4, HEIGHT, WIDTH, 3)
    assert np.allclose(got, expected, **tol), (model, np.abs(got - expected).max(), scale)
    stored = zarr.open_group(tmp_path / "r.zarr", mode="r")[RADIANCE]
    assert stored.dtype == (np.float16 if "float16" in args else np.float32)
    assert ds.attrs["dfmf"]["colour_model"] == model and ds.attrs["ingest"]["decoded"]
    assert np.allclose(ds["theta_light"].values, np.degrees([t for t, _ in LIGHTS]))
    assert btf("ingest", tmp_path / "m.btf", tmp_path / "f.zarr", "--quiet").code == 0
    factors = open_compressed(tmp_path / "f.zarr")[RADIANCE].values
    assert np.allclose(got, factors, **tol)


def test_radiance_refuses_a_layer_that_decodes_to_inf_naming_its_place(tmp_path, btf,
                                                                       monkeypatch):
    import pipeline.dfmf_io as dfmf_io

    _write(tmp_path / "m.btf", np.random.default_rng(3), 11, scalar_size=2)
    real = dfmf_io.decode_pairs

    def overflowing(*args, **kwargs):  # as exp(a) of a huge log value would
        out = real(*args, **kwargs).copy()
        if args[2][0] == (2, 0):
            out[3, 4, 5, 1], out[3, 4, 6, 1] = np.inf, -np.inf  # their sum is NaN
        return out

    monkeypatch.setattr(dfmf_io, "decode_pairs", overflowing)
    r = btf("ingest", tmp_path / "m.btf", tmp_path / "r.zarr", "--radiance", "--quiet")
    assert r.code == 1
    assert "2 layer value(s) decode to NaN or Inf, the first at view=2, light=3, y=4, x=5, " \
           "channel=1" in r.err
    assert not (tmp_path / "r.zarr").exists()


def test_the_file_s_metadata_is_kept_and_a_rotations_block_is_skipped(tmp_path, btf):
    rng = np.random.default_rng(4)
    _write(tmp_path / "r.btf", rng, 11, rotations=True, channel_names=("R", "G", "B"))
    header = read_header(tmp_path / "r.btf")
    assert header.rotations > 0 and header.colour_model == 11
    assert btf("ingest", tmp_path / "r.btf", tmp_path / "r.zarr", "--quiet").code == 0
    meta = zarr.open_group(tmp_path / "r.zarr", mode="r").attrs["dfmf"]
    assert meta["components"] == [3, 2, 4] and meta["colour_model"] == 11


def test_export_writes_each_channel_at_its_own_rank_and_ingest_reads_it_back(tmp_path, btf):
    rng = np.random.default_rng(7)
    _write(tmp_path / "a.btf", rng, 11, scalar_size=4)
    assert btf("ingest", tmp_path / "a.btf", tmp_path / "a.zarr", "--quiet").code == 0
    r = btf("export", tmp_path / "a.zarr", tmp_path / "b.btf")
    assert r.code == 0, r.err
    header = read_header(tmp_path / "b.btf")
    assert [c.k for c in header.channels] == [3, 2, 4]  # the file's own ranks come back
    assert header.colour_model == 11 and header.channels[0].scalar == 4
    assert btf("ingest", tmp_path / "b.btf", tmp_path / "b.zarr", "--quiet").code == 0
    a = open_compressed(tmp_path / "a.zarr")[RADIANCE].values
    b = open_compressed(tmp_path / "b.zarr")[RADIANCE].values
    assert np.allclose(a, b, rtol=1e-5, atol=1e-6 * np.abs(a).max())
    a_dirs = open_compressed(tmp_path / "a.zarr")
    b_dirs = open_compressed(tmp_path / "b.zarr")
    for name in ("theta_view", "phi_view", "theta_light", "phi_light"):
        assert np.array_equal(a_dirs[name].values, b_dirs[name].values), name
    # half floats: a smaller file, float16's error
    assert btf("export", tmp_path / "a.zarr", tmp_path / "h.btf", "--half", "--quiet").code == 0
    assert (tmp_path / "h.btf").stat().st_size < 0.6 * (tmp_path / "b.btf").stat().st_size
    assert btf("ingest", tmp_path / "h.btf", tmp_path / "h.zarr", "--quiet").code == 0
    h = open_compressed(tmp_path / "h.zarr")[RADIANCE].values
    err = np.abs(h - a).max() / np.abs(a).max()
    assert 1e-6 < err < 1e-2, err


def test_a_compressed_store_of_the_pipeline_exports_as_colour_model_12(tmp_path, btf,
                                                                       small_btf):
    out = tmp_path / "c.zarr"
    assert btf("compress", small_btf, out, "--rank", "6", "--eps", "1e-5", "--quiet").code == 0
    r = btf("export", out, tmp_path / "c.btf")
    assert r.code == 0, r.err
    assert "off" not in r.err  # eps 1e-5: exact, no note
    header = read_header(tmp_path / "c.btf")
    assert header.colour_model == 12 and [c.k for c in header.channels] == [6, 6, 6]
    # decoded from the file's own matrices by the test's reader
    u = [np.fromfile(tmp_path / "c.btf", "<f4", c.rows * c.k, offset=c.u_offset).reshape(
        c.rows, c.k) for c in header.channels]
    sxv = [np.fromfile(tmp_path / "c.btf", "<f4", c.columns * c.k, offset=c.sxv_offset
                       ).reshape(c.columns, c.k) for c in header.channels]
    lights = list(zip(header.theta_light, header.phi_light, strict=True))
    decoded = reference_decode(u, sxv, color_model=12, width=header.width,
                               height=header.height, lights=lights)
    expected = open_compressed(out)[RADIANCE].values
    assert np.allclose(np.maximum(decoded, 0), expected, rtol=1e-4,
                       atol=1e-6 * expected.max())
    # another eps: exported with a note saying how far off every value is
    assert btf("compress", small_btf, tmp_path / "d.zarr", "--rank", "6", "--quiet").code == 0
    r = btf("export", tmp_path / "d.zarr", tmp_path / "d.btf")
    assert r.code == 0 and "eps is 0.001" in r.err and "--eps 1e-05" in r.err, r.err


def test_a_radiance_store_is_refused_with_the_way_to_compress_it(tmp_path, btf, small_btf):
    r = btf("export", small_btf, tmp_path / "x.btf")
    assert r.code != 0 and "compress it first" in r.err
    assert no_partial_outputs(tmp_path / "x.btf")


def _corrupt(path, how):
    data = bytearray(path.read_bytes())
    if how == "truncated":
        return bytes(data[: len(data) - 7])
    if how == "signature":
        return b"!FMF12FCE" + bytes(data[9:])
    if how == "garbage":
        return b"GIF89a" + bytes(data[6:])
    if how == "metadata size":
        (size,) = struct.unpack_from("<I", data, 9)
        struct.pack_into("<I", data, 9, size + 4)
        return bytes(data)
    raise AssertionError(how)


@pytest.mark.parametrize("how,message", [
    ("truncated", "truncated"),
    ("signature", "FMF12"),
    ("garbage", "not a DFMF file"),
    ("metadata size", "metadata block says"),  # btflib refuses it too
])
def test_a_bad_file_gets_one_clear_error_and_nothing_at_out(tmp_path, btf, how, message):
    rng = np.random.default_rng(1)
    _write(tmp_path / "good.btf", rng, 11)
    bad = tmp_path / "bad.btf"
    bad.write_bytes(_corrupt(tmp_path / "good.btf", how))
    r = btf("ingest", bad, tmp_path / "o.zarr")
    assert r.code != 0 and message in r.err and "bad.btf" in r.err, r.err
    assert len(r.err.strip().splitlines()) == 1
    assert no_partial_outputs(tmp_path / "o.zarr")


def test_what_btflib_reads_is_read_and_said_and_what_it_refuses_is_refused(tmp_path, btf):
    """Bonn's own reader (btflib) reads later views' light lists as view 0's, channels stored
    texels first, a channel with more components than the file's count, and bytes after the
    last channel: so does btf, saying so; other light counts and colour models it does not
    decode are refused by name."""
    rng = np.random.default_rng(2)
    u, sxv, _ = _write(tmp_path / "plain.btf", rng, 0)
    assert btf("ingest", tmp_path / "plain.btf", tmp_path / "plain.zarr", "-q").code == 0
    expected = open_compressed(tmp_path / "plain.zarr")[RADIANCE].values
    shifted = [(t + 0.01, p) for t, p in LIGHTS]
    files = {
        "lists": ({"light_lists": [LIGHTS, shifted, LIGHTS]}, "list other light directions"),
        "transposed": ({"transposed": True}, "store the texels' matrix first"),
        "count": ({"n_components": 2}, "where the file's count says 2"),
        "trailing": ({"trailing": b"\0" * 8}, "8 bytes after the last channel's factors"),
    }
    for name, (kw, note) in files.items():
        write_dfmf(tmp_path / f"{name}.btf", views=VIEWS, lights=LIGHTS, u=u, sxv=sxv,
                   width=WIDTH, height=HEIGHT, color_model=0, scalar_size=4, **kw)
        r = btf("ingest", tmp_path / f"{name}.btf", tmp_path / f"{name}.zarr")
        assert r.code == 0 and note in r.err, (name, r.err)
        got = open_compressed(tmp_path / f"{name}.zarr")[RADIANCE].values
        assert np.allclose(got, expected, rtol=1e-5, atol=1e-6), name
        attrs = zarr.open_group(tmp_path / f"{name}.zarr").attrs["dfmf"]
        assert any(note in n for n in attrs["notes"]), name
        listing = btf("inspect", tmp_path / f"{name}.zarr")
        assert note in listing.out, (name, listing.out)
    assert "0.573 degrees" in btf("inspect", tmp_path / "lists.btf").out  # 0.01 rad
    _write(tmp_path / "d.btf", rng, 0, light_lists=[LIGHTS, LIGHTS[:3], LIGHTS])
    r = btf("ingest", tmp_path / "d.btf", tmp_path / "d.zarr")
    assert r.code != 0 and "view 1 lists 3 lights where view 0 has 4" in r.err, r.err
    for model, message in ((7, "unknown colour model 7"), (5, "btflib decodes it")):
        _write(tmp_path / "m.btf", rng, 0)
        data = bytearray((tmp_path / "m.btf").read_bytes())
        header = read_header(tmp_path / "m.btf")
        model_at = header.channels[0].s_offset - 13 - 4 * 13  # i32 model, f32[3], f32[9]
        assert struct.unpack_from("<i", data, model_at)[0] == 0
        struct.pack_into("<i", data, model_at, model)
        (tmp_path / "m.btf").write_bytes(bytes(data))
        r = btf("ingest", tmp_path / "m.btf", tmp_path / "m.zarr")
        assert r.code != 0 and message in r.err, r.err
    assert no_partial_outputs(tmp_path / "m.zarr") and no_partial_outputs(tmp_path / "d.zarr")


@pytest.mark.parametrize("model", sorted(DFMF_MODELS))
def test_images_decoded_straight_from_the_file_match_the_reference(tmp_path, model):
    from pipeline.dfmf_io import decode_pairs

    rng = np.random.default_rng(11)
    u, sxv, kw = _write(tmp_path / "f.btf", rng, model, scalar_size=2, cosine=model in (1, 10))
    header = read_header(tmp_path / "f.btf")
    expected = _expected(u, sxv, model, {**kw, "cosine": model in (1, 10)}, 2)
    every = [(v, li) for v in range(len(VIEWS)) for li in range(len(LIGHTS))][::-1]
    # one image, a few (the compiled product) and many (converted once, then BLAS)
    for pairs in ([(2, 1)], [(2, 1), (0, 3), (1, 0)], every):
        got = decode_pairs(str(tmp_path / "f.btf"), header, pairs, band=3 * WIDTH + 5)
        want = np.stack([expected[v, li] for v, li in pairs])  # 4 bands above: a short one
        assert np.allclose(got, want, rtol=1e-4, atol=1e-5 * np.abs(want).max())


def test_a_cosine_flag_is_folded_into_linear_models(tmp_path, btf):
    rng = np.random.default_rng(12)
    u, sxv, _ = _write(tmp_path / "c.btf", rng, 1, cosine=True)
    assert btf("ingest", tmp_path / "c.btf", tmp_path / "c.zarr", "--quiet").code == 0
    got = open_compressed(tmp_path / "c.zarr")[RADIANCE].values
    expected = _expected(u, sxv, 1, {"cosine": True}, 4)
    assert np.allclose(got, expected, rtol=1e-4, atol=1e-5 * np.abs(expected).max())
    assert "cosine" not in zarr.open_group(tmp_path / "c.zarr").attrs["transform"]


@pytest.mark.parametrize("model", [9, *(pytest.param(m, marks=pytest.mark.slow) for m in (10, 11)),
                                   12])
def test_a_cosine_flag_with_a_log_model_is_divided_out_after_the_colour_model(tmp_path, btf,
                                                                              model):
    """Decoded as the flag means (btflib: the colour model, then / cos(theta_light)), against
    numpy, in every stage that rebuilds layers: the store, btf reconstruct, btf export (EXR and
    back to a .btf file with the flag set), a scene at a measured direction, and a tile set's
    render."""
    from pipeline.images import read_image

    rng = np.random.default_rng(40 + model)
    u, sxv, kw = _write(tmp_path / "c.btf", rng, model, cosine=True)
    r = btf("ingest", tmp_path / "c.btf", tmp_path / "c.zarr", "--chunk", "8")
    assert r.code == 0, r.err
    assert "divided by cos(theta_light)" in r.err
    expected = _expected(u, sxv, model, {**kw, "cosine": True}, 4)
    plain = _expected(u, sxv, model, {**kw, "cosine": False}, 4)  # ignoring it (btf-extractor)
    tol = {"rtol": 1e-4, "atol": 1e-5 * np.abs(expected).max()}
    ds = open_compressed(tmp_path / "c.zarr")
    assert ds.attrs["transform"]["cosine"] is True
    got = ds[RADIANCE].values
    assert np.allclose(got, expected, **tol), np.abs(got - expected).max()
    assert not np.allclose(got, plain, **tol)  # the lights at 0.9 and 1.1 rad: far from 1
    # btf reconstruct, and btf export's EXR layers
    assert btf("reconstruct", tmp_path / "c.zarr", tmp_path / "r.zarr", "--quiet").code == 0
    rebuilt = zarr.open_group(tmp_path / "r.zarr", mode="r")[RADIANCE][...]
    assert np.allclose(rebuilt, expected, **tol)
    assert btf("export", tmp_path / "c.zarr", tmp_path / "layers", "--view", "2", "--light",
               "3", "--quiet").code == 0
    (layer,) = (tmp_path / "layers").glob("*.exr")
    assert np.allclose(read_image(layer)[0], expected[2, 3], **tol)
    # back out as a DFMF file: the flag is written and read back
    assert btf("export", tmp_path / "c.zarr", tmp_path / "back.btf", "--quiet").code == 0
    assert read_header(tmp_path / "back.btf").cosine
    assert btf("ingest", tmp_path / "back.btf", tmp_path / "back.zarr", "--quiet").code == 0
    assert np.allclose(open_compressed(tmp_path / "back.zarr")[RADIANCE].values, expected,
                       **tol)
    # a scene at a measured pair (view 1, light 3) equals that layer
    (tmp_path / "s.yaml").write_text(
        f"source: {tmp_path / 'c.zarr'}\ndirections:\n  - [{np.degrees(LIGHTS[3][0])}, "
        f"{np.degrees(LIGHTS[3][1]) % 360}, {np.degrees(VIEWS[1][0])}, "
        f"{np.degrees(VIEWS[1][1]) % 360}]\nformat: zarr\n")
    assert btf("scene", tmp_path / "s.yaml", tmp_path / "s.zarr", "--quiet").code == 0
    scene = zarr.open_group(tmp_path / "s.zarr", mode="r")[RADIANCE][0]
    assert np.allclose(scene, expected[1, 3], **tol)
    # a tile set's render: a texel with one source is that source's texel of the layer
    assert btf("quilt", tmp_path / "c.zarr", tmp_path / "q.zarr", "--corners", "1",
               "--block", "6", "--overlap", "2", "--size", "12,12", "--quiet").code == 0
    assert btf("render", tmp_path / "q.zarr", tmp_path / "surface.zarr", "--size", "12,12",
               "--view", "2", "--light", "3", "--quiet").code == 0
    q = zarr.open_group(tmp_path / "q.zarr", mode="r")
    index, weight = q["prescription_index"][0], q["prescription_weight"][0]
    single = (weight > 0).sum(axis=1) == 1
    source = index[np.arange(len(index)), np.argmax(weight, axis=1)]
    tile = zarr.open_group(tmp_path / "surface.zarr", mode="r")[RADIANCE][...].reshape(-1, 3)
    assert single.mean() > 0.2
    assert np.allclose(tile[single], expected[2, 3].reshape(-1, 3)[source[single]], **tol)


def test_layers_of_an_ingested_file_export_as_exr_and_a_scene_reads_only_its_chunks(
        tmp_path, btf):
    rng = np.random.default_rng(13)
    big = {"width": 64, "height": 48}
    ks = (3, 2, 2)
    rows = len(VIEWS) * len(LIGHTS)
    u = [rng.normal(size=(rows, k)) * 0.1 for k in ks]
    sxv = [rng.normal(size=(64 * 48, k)) * 0.3 for k in ks]
    u[0][:, 0], sxv[0][:, 0] = -1.0, 1.0
    write_dfmf(tmp_path / "s.btf", views=VIEWS, lights=LIGHTS, u=u, sxv=sxv, color_model=11,
               scalar_size=2, **big)
    assert btf("ingest", tmp_path / "s.btf", tmp_path / "s.zarr", "--chunk", "16",
               "--dir-chunk", "2", "--quiet").code == 0
    ds = open_compressed(tmp_path / "s.zarr")
    r = btf("export", tmp_path / "s.zarr", tmp_path / "layers", "--view", "1", "--light", "0,3",
            "--quiet")
    assert r.code == 0, r.err
    from pipeline.images import read_image

    for li in (0, 3):
        name = (f"tl{ds['theta_light'].values[li]:.4f}".rstrip("0").rstrip(".")
                + f"_pl{ds['phi_light'].values[li]:.4f}".rstrip("0").rstrip("."))
        (path,) = (tmp_path / "layers").glob(f"{name}_tv*.exr")
        pixels, _ = read_image(path)
        assert np.allclose(pixels, ds[RADIANCE].values[1, li], rtol=1e-6, atol=1e-7)
    # a scene of one 16 x 16 tile of the 12 and one layer reads that tile and its U chunks
    (tmp_path / "scene.yaml").write_text(
        f"source: {tmp_path / 's.zarr'}\ndirections:\n"
        f"  - [{np.degrees(LIGHTS[1][0])}, {np.degrees(LIGHTS[1][1]) % 360}, 0, 0]\n"
        "region: [16, 32, 32, 48]\nformat: zarr\n")
    assert btf("scene", tmp_path / "scene.yaml", tmp_path / "out.zarr", "--quiet").code == 0
    reads = zarr.open_group(tmp_path / "out.zarr", mode="r").attrs["reads"]
    assert reads["V"] == [1, 12] and reads["U"][0] <= 2 and reads["U"][1] == 6, reads
    got = zarr.open_group(tmp_path / "out.zarr", mode="r")[RADIANCE][...]
    assert got.shape == (1, 16, 16, 3), got.shape  # (direction, y, x, channel)
    assert np.allclose(got[0], ds[RADIANCE].values[0, 1, 16:32, 32:48], rtol=1e-5,
                       atol=1e-7)


def test_channels_other_than_three_the_signature_and_the_limits_of_half_floats(tmp_path, btf):
    rng = np.random.default_rng(14)
    rows = len(VIEWS) * len(LIGHTS)
    names = ("L450", "L550", "L650", "L750", "L850")  # multispectral, log model 12
    u = [rng.normal(size=(rows, 2)) * 0.1 - 1.0 for _ in names]
    sxv = [np.c_[np.ones(WIDTH * HEIGHT), rng.normal(size=WIDTH * HEIGHT) * 0.2] for _ in names]
    write_dfmf(tmp_path / "spectral.dat", views=VIEWS, lights=LIGHTS, u=u, sxv=sxv,
               width=WIDTH, height=HEIGHT, color_model=12, channel_names=names, scalar_size=4)
    # no .btf suffix: known by its signature
    assert btf("ingest", tmp_path / "spectral.dat", tmp_path / "s.zarr", "--quiet").code == 0
    ds = open_compressed(tmp_path / "s.zarr")
    assert list(ds["channel"].values) == list(names)
    expected = np.maximum(reference_decode(u, sxv, color_model=12, width=WIDTH, height=HEIGHT,
                                           lights=LIGHTS), 0)
    assert np.allclose(ds[RADIANCE].values, expected, rtol=1e-4, atol=1e-7)
    r = btf("ingest", tmp_path / "spectral.dat", tmp_path / "x.zarr", "--shard", "256")
    assert r.code != 0 and "--shard does not apply" in r.err
    # a YUV model needs three channels
    write_dfmf(tmp_path / "two.btf", views=VIEWS, lights=LIGHTS, u=u[:2], sxv=sxv[:2],
               width=WIDTH, height=HEIGHT, color_model=11, channel_names=names[:2])
    r = btf("ingest", tmp_path / "two.btf", tmp_path / "t.zarr")
    assert r.code != 0 and "colour model 11 needs 3 channels" in r.err, r.err
    # values beyond float16's range: --half is refused, float32 is exact
    big = [np.c_[np.full(rows, 3.0), rng.normal(size=rows) * 0.01] for _ in range(3)]
    wide = [np.c_[np.full(WIDTH * HEIGHT, 3e4), rng.normal(size=WIDTH * HEIGHT)]
            for _ in range(3)]
    write_dfmf(tmp_path / "hdr.btf", views=VIEWS, lights=LIGHTS, u=big, sxv=wide, width=WIDTH,
               height=HEIGHT, color_model=0, scalar_size=4)
    assert btf("ingest", tmp_path / "hdr.btf", tmp_path / "h.zarr", "--quiet").code == 0
    r = btf("export", tmp_path / "h.zarr", tmp_path / "h.btf", "--half")
    assert r.code != 0 and "do not fit float16" in r.err, r.err
    assert no_partial_outputs(tmp_path / "h.btf")
    assert btf("export", tmp_path / "h.zarr", tmp_path / "h.btf", "--quiet").code == 0


@pytest.mark.parametrize("way", ["chosen", "integer"])
def test_halves_become_float32_exactly_as_numpy_converts_them(way):
    """Both conversions: the one this CPU uses (its instruction where it has one) and the
    integer one a CPU without it would use."""
    import numba

    from tasks import dfmf_kernel

    if way == "integer":
        half = dfmf_kernel._half_integer

        @numba.njit
        def convert(bits, out):
            for i in range(bits.size):
                out[i] = half(bits[i])
    else:
        convert = dfmf_kernel.halves_to_float32
    bits = np.arange(1 << 16, dtype=np.uint16)
    halves = bits.view(np.float16)
    finite = np.isfinite(halves)
    out = np.empty(bits.shape, np.float32)
    convert(bits, out)
    assert np.array_equal(out[finite], halves[finite].astype(np.float32))  # subnormals too
    assert np.array_equal(np.signbit(out[finite]), np.signbit(halves[finite]))
    if dfmf_kernel.HALF_INSTRUCTION and way == "chosen":  # the instruction's are exact too
        assert np.array_equal(out, halves.astype(np.float32), equal_nan=True)


def test_inspect_quilt_and_enlarge_take_an_ingested_file(tmp_path, btf):
    rng = np.random.default_rng(15)
    views = [(0.0, 0.0), (0.4, 1.0)]
    lights = [(0.0, 0.0), (0.6, 0.5), (0.9, 2.5)]
    rows, side, ks = 6, 64, (3, 2, 2)
    y, x = np.mgrid[0:side, 0:side] / side
    texture = np.sin(2 * np.pi * 4 * x) * np.cos(2 * np.pi * 3 * y)  # structure to quilt
    u = [rng.normal(size=(rows, k)) * 0.05 for k in ks]
    sxv = [np.c_[np.ones(side * side), texture.ravel(),
                 rng.normal(size=(side * side, k - 2)) * 0.1] for k in ks]
    u[0][:, 0], u[0][:, 1] = -1.0, 0.4
    # with the cosine flag: the photos are radiance, the sample's values radiance x cos
    write_dfmf(tmp_path / "m.btf", views=views, lights=lights, u=u, sxv=sxv, width=side,
               height=side, color_model=11, cosine=True)
    assert btf("ingest", tmp_path / "m.btf", tmp_path / "m.zarr", "--chunk", "32",
               "--quiet").code == 0
    r = btf("inspect", tmp_path / "m.zarr")
    # 7 components in the file, but ones and the texture repeat in every channel: rank 3
    assert r.code == 0 and "compressed store" in r.out and "rank 3," in r.out, r.out
    r = btf("quilt", tmp_path / "m.zarr", tmp_path / "q.zarr", "--corners", "1", "--block",
            "16", "--overlap", "4", "--quiet")
    assert r.code == 0, r.err
    q = zarr.open_group(tmp_path / "q.zarr", mode="r")
    assert q.attrs["transform"]["name"] == "ylog-uv-over-y"
    # the enlarged store keeps the sample's colour model, and meets its photo
    assert btf("reconstruct", tmp_path / "m.zarr", tmp_path / "photo.zarr", "--view", "0",
               "--light", "1", "--quiet").code == 0
    # the sample: the file's first 32 texel rows, the picture's bottom half (rows 32:64 of
    # the store), once cut from the ingested store and once written as a file of its own
    assert btf("crop", tmp_path / "m.zarr", tmp_path / "c.zarr", "--region", "32:64,0:32",
               "--quiet").code == 0
    small = [c.reshape(side, side, -1)[:32, :32].reshape(32 * 32, -1) for c in sxv]
    write_dfmf(tmp_path / "s.btf", views=views, lights=lights, u=u, sxv=small, width=32,
               height=32, color_model=11, cosine=True)
    assert btf("ingest", tmp_path / "s.btf", tmp_path / "s.zarr", "--quiet").code == 0
    cut, own = (open_compressed(tmp_path / n)[RADIANCE].values for n in ("c.zarr", "s.zarr"))
    assert np.allclose(cut, own, rtol=1e-4, atol=1e-6 * own.max())
    r = btf("enlarge", tmp_path / "s.zarr", tmp_path / "photo.zarr", tmp_path / "e.zarr",
            "--sample-origin", "32,0", "--levels", "2", "--patch", "5", "--quiet")
    assert r.code == 0, r.err
    e = open_compressed(tmp_path / "e.zarr")
    assert e.attrs["transform"]["name"] == "ylog-uv-over-y"
    # the photo (radiance) is encoded as the sample's values are (radiance x cos): on the
    # sample's own place it meets them (ignoring the cosine leaves 0.19 in log Y there)
    assert e.attrs["enlargement"]["sample_constraint_residual_rms"] < 1e-3
    # the report's eq. 11 against the truth divides by the cosine too (ignoring it, the
    # oracle's error alone is 0.10 of a mean radiance of 0.48)
    from pipeline.stages.report import ReportParams, _enlargement

    assert btf("reconstruct", tmp_path / "m.zarr", tmp_path / "truth.zarr", "--quiet").code == 0
    truth = zarr.open_group(tmp_path / "truth.zarr", mode="r")[RADIANCE][...]
    section = _enlargement(str(tmp_path / "e.zarr"),
                           ReportParams(out=str(tmp_path / "r.html"),
                                        truth=str(tmp_path / "truth.zarr")))
    errors = {row[0]: float(row[1]) for row in section.tables[0].rows}
    assert errors["oracle (nearest sample ABRDF)"] < 0.02 * truth.mean(), errors
    assert errors["enlargement"] < 0.1 * truth.mean(), (errors, truth.mean())
    photo = zarr.open_group(tmp_path / "photo.zarr", mode="r")[RADIANCE][0, 0]
    got = e[RADIANCE].values[0, 1]
    assert np.abs(got - photo).mean() < 0.05 * photo.mean()  # the photo is met

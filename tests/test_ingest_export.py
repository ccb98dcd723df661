"""btf export / ingest / preview: round trips, formats, and errors that name the file."""

from __future__ import annotations

import csv
import shutil
import time

import numpy as np
import pytest
import zarr

from helpers import HALF_ROUNDING, SLOW_CLUSTER, SLOW_PROCESSES, no_partial_outputs, stored_dtype
from pipeline.images import read_image, write_exr, write_png
from pipeline.stores.base import RADIANCE
from pipeline.stores.radiance import open_radiance


def _store_values(path):
    ds = open_radiance(path)
    coords = {k: ds[k].values for k in ("theta_view", "phi_view", "theta_light", "phi_light")}
    return ds[RADIANCE].values, coords, [str(c) for c in ds["channel"].values]


def test_exr_export_then_ingest_gives_back_the_same_float32_values(tmp_path, btf, small_btf,
                                                                   small_tasks):
    assert btf("export", small_btf, tmp_path / "layers", "--quiet").code == 0
    files = sorted((tmp_path / "layers").glob("*.exr"))
    assert len(files) == 9 and (tmp_path / "layers" / "manifest.csv").is_file()
    assert btf("ingest", tmp_path / "layers", tmp_path / "back.zarr", "--quiet").code == 0
    original, coords, channels = _store_values(small_btf)
    back, back_coords, back_channels = _store_values(tmp_path / "back.zarr")
    assert np.array_equal(back, original)  # bit for bit
    assert back_channels == channels == ["R", "G", "B"]
    for key, values in coords.items():
        assert np.array_equal(back_coords[key], values), key
    assert sorted(zarr.open_group(tmp_path / "back.zarr").array_keys()) == [
        "channel", "phi_light", "phi_view", "radiance", "theta_light", "theta_view"]


def test_utia_names_alone_are_enough_to_ingest(tmp_path, btf, small_abtf):
    assert btf("export", small_abtf, tmp_path / "layers", "--light", "0,4,9", "--quiet").code == 0
    (tmp_path / "layers" / "manifest.csv").unlink()
    assert btf("ingest", tmp_path / "layers", tmp_path / "back.zarr", "--quiet").code == 0
    original, coords, _ = _store_values(small_abtf)
    back, back_coords, _ = _store_values(tmp_path / "back.zarr")
    assert back.shape == (1, 3, 48, 48, 3)
    for j in range(3):  # names carry the angles to 4 decimals; lights are sorted by angle
        match = np.flatnonzero(
            (np.abs(coords["theta_light"] - back_coords["theta_light"][j]) < 1e-3)
            & (np.abs(coords["phi_light"] - back_coords["phi_light"][j]) < 1e-3))
        assert len(match) == 1 and match[0] in (0, 4, 9)
        assert np.array_equal(back[0, j], original[0, match[0]])


def test_half_export_is_close_and_png_export_is_tone_mapped(tmp_path, btf, small_abtf):
    assert btf("export", small_abtf, tmp_path / "half", "--half", "--view", "0", "--light",
               "1,2", "--quiet").code == 0
    original, coords, _ = _store_values(small_abtf)
    with (tmp_path / "half" / "manifest.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 2
    found = []
    for row in rows:  # each file holds the layer of its own directions, and only that one
        # the (view, light) pair of the row's four angles: exactly one of each in the store
        view = np.flatnonzero((coords["theta_view"] == float(row["theta_view"]))
                              & (coords["phi_view"] == float(row["phi_view"])))
        light = np.flatnonzero((coords["theta_light"] == float(row["theta_light"]))
                               & (coords["phi_light"] == float(row["phi_light"])))
        assert len(view) == 1 and len(light) == 1, row
        view, light = int(view[0]), int(light[0])
        assert view == 0 and light in (1, 2)
        found.append((view, light))
        pixels, channels = read_image(tmp_path / "half" / row["file"])
        assert channels == ("R", "G", "B") and pixels.shape == original.shape[2:]
        assert np.allclose(pixels, original[view, light], rtol=1e-3, atol=1e-4)
        other = 3 - light
        assert not np.allclose(pixels, original[view, other], rtol=1e-3, atol=1e-4)
    assert sorted(found) == [(0, 1), (0, 2)]  # both layers, once each
    assert btf("export", small_abtf, tmp_path / "png", "--format", "png", "--light", "0,1",
               "--quiet").code == 0
    pngs = sorted((tmp_path / "png").glob("*.png"))
    assert len(pngs) == 2
    pixels, _ = read_image(pngs[0])
    assert pixels.shape == (48, 48, 3) and 0.05 < pixels.mean() < 0.95


@pytest.mark.parametrize("depth", [8, 16])
@pytest.mark.parametrize("srgb", [False, True])
def test_png_layers_are_read_linear_or_srgb_decoded(tmp_path, btf, depth, srgb):
    rng = np.random.default_rng(depth)
    top = (1 << depth) - 1
    src = tmp_path / "src"
    src.mkdir()
    images = {}
    for phi in (0, 90):
        pixels = rng.integers(0, top, (10, 12, 3), endpoint=True).astype(
            np.uint8 if depth == 8 else np.uint16)
        write_png(src / f"tl30_pl{phi}_tv0_pv0.png", pixels)
        images[phi] = pixels / top
    args = ("--srgb",) if srgb else ()
    assert btf("ingest", src, tmp_path / "s.zarr", *args, "--quiet").code == 0
    values, coords, _ = _store_values(tmp_path / "s.zarr")
    for j, phi in enumerate(coords["phi_light"]):
        expected = images[int(phi)]
        if srgb:
            expected = np.where(expected <= 0.04045, expected / 12.92,
                                ((expected + 0.055) / 1.055) ** 2.4)
        # 8-bit codes are stored as float16 (each decodes to one that encodes back to it)
        assert np.allclose(values[0, j], expected, rtol=HALF_ROUNDING if depth == 8 else 1e-6,
                           atol=1e-7)
    assert stored_dtype(tmp_path / "s.zarr") == ("float16" if depth == 8 else "float32")


def test_single_channel_half_exr_layers_keep_their_channel_name(tmp_path, btf):
    src = tmp_path / "src"
    src.mkdir()
    rng = np.random.default_rng(0)
    rows = []
    for k in range(3):
        pixels = rng.uniform(0, 4, (8, 9, 1)).astype(np.float16)
        write_exr(src / f"layer{k}.exr", pixels, ("Y",), half=True)
        rows.append((f"layer{k}.exr", 10 * k, 0, 20, 45))
    with (src / "dirs.csv").open("w", newline="") as f:
        csv.writer(f).writerows([("file", "theta_light", "phi_light", "theta_view", "phi_view"),
                                 *rows])
    assert btf("ingest", src, tmp_path / "s.zarr", "--manifest", src / "dirs.csv",
               "--quiet").code == 0
    values, coords, channels = _store_values(tmp_path / "s.zarr")
    assert channels == ["Y"] and values.shape == (1, 3, 8, 9, 1)
    assert coords["theta_view"].tolist() == [20.0]
    assert coords["theta_light"].tolist() == [0.0, 10.0, 20.0]


def _folder(tmp_path, n=4, shape=(6, 7, 3)):
    src = tmp_path / "src"
    src.mkdir()
    for k in range(n):
        write_exr(src / f"tl{10 * k}_pl0_tv0_pv0.exr", np.full(shape, k, np.float32),
                  ("R", "G", "B"))
    return src


def _manifest(src, rows):
    with (src / "manifest.csv").open("w", newline="") as f:
        csv.writer(f).writerows([("file", "theta_light", "phi_light", "theta_view", "phi_view"),
                                 *rows])


def _corrupt(src):
    (src / "tl10_pl0_tv0_pv0.exr").write_bytes(b"\x76\x2f\x31\x01 then garbage")
    return "tl10_pl0_tv0_pv0.exr", "corrupt or unreadable EXR"


def _truncated(src):
    path = src / "tl20_pl0_tv0_pv0.exr"
    path.write_bytes(path.read_bytes()[:-40])
    return "tl20_pl0_tv0_pv0.exr", "corrupt or unreadable EXR"


def _other_size(src):
    write_exr(src / "tl20_pl0_tv0_pv0.exr", np.zeros((6, 8, 3), np.float32), ("R", "G", "B"))
    return "tl20_pl0_tv0_pv0.exr", "6x8"


def _missing_file(src):
    _manifest(src, [("tl0_pl0_tv0_pv0.exr", 0, 0, 0, 0), ("gone.exr", 10, 0, 0, 0)])
    return "manifest.csv:3", "'gone.exr' not found"


def _duplicate(src):
    _manifest(src, [("tl0_pl0_tv0_pv0.exr", 0, 0, 0, 0), ("tl10_pl0_tv0_pv0.exr", 0, 360, 0, 0)])
    return "tl10_pl0_tv0_pv0.exr", "same directions as tl0_pl0_tv0_pv0.exr"


def _non_finite(src):
    pixels = np.ones((6, 7, 3), np.float32)
    pixels[2, 3, 1] = np.nan
    pixels[4, 0, 0] = np.inf
    write_exr(src / "tl30_pl0_tv0_pv0.exr", pixels, ("R", "G", "B"))
    return "tl30_pl0_tv0_pv0.exr", "2 non-finite pixel value(s) (NaN or Inf), the first at y=2, x=3"


def _incomplete(src):
    write_exr(src / "tl0_pl0_tv30_pv0.exr", np.zeros((6, 7, 3), np.float32), ("R", "G", "B"))
    return "src", "no image for light 10/0 and view 30/0"


def _bad_name(src):
    write_exr(src / "picture.exr", np.zeros((6, 7, 3), np.float32), ("R", "G", "B"))
    return "picture.exr", "name does not follow"


def _corrupt_png(src):
    path = src / "tl40_pl0_tv0_pv0.png"
    write_png(path, np.zeros((6, 7, 3), np.uint8))
    path.write_bytes(path.read_bytes()[:40] + b"garbage" * 5)
    return "tl40_pl0_tv0_pv0.png", "corrupt PNG"


def _not_png(src):
    (src / "tl40_pl0_tv0_pv0.png").write_bytes(b"GIF89a" + b"\0" * 40)
    return "tl40_pl0_tv0_pv0.png", "not a PNG file"


def _bad_angle(src):
    _manifest(src, [("tl0_pl0_tv0_pv0.exr", "north", 0, 0, 0)])
    return "manifest.csv:2", "theta_light 'north' is not a number"


def _below_the_horizon(src):
    _manifest(src, [("tl0_pl0_tv0_pv0.exr", 0, 0, 0, 0), ("tl10_pl0_tv0_pv0.exr", 120, 0, 0, 0)])
    return "manifest.csv:3", "theta_light 120 is outside 0-90 degrees"


def _two_top_views(src):
    # theta 0 is one direction whatever phi says
    _manifest(src, [("tl0_pl0_tv0_pv0.exr", 0, 0, 0, 0), ("tl10_pl0_tv0_pv0.exr", 0, 0, 0, 90)])
    return "tl10_pl0_tv0_pv0.exr", "same directions as tl0_pl0_tv0_pv0.exr"


def _negative_theta_name(src):
    write_exr(src / "tl-5_pl0_tv0_pv0.exr", np.zeros((6, 7, 3), np.float32), ("R", "G", "B"))
    return "tl-5_pl0_tv0_pv0.exr", "theta_light -5 is outside"


@pytest.mark.parametrize("damage", [_corrupt, _truncated, _other_size, _missing_file, _duplicate,
                                    _non_finite, _incomplete, _bad_name, _bad_angle,
                                    _corrupt_png, _not_png, _below_the_horizon, _two_top_views,
                                    _negative_theta_name])
def test_bad_input_names_the_file_and_leaves_no_store(tmp_path, btf, damage):
    src = _folder(tmp_path)
    where, what = damage(src)
    out = tmp_path / "out.zarr"
    result = btf("ingest", src, out, "--quiet", "--dir-chunk", "2")
    assert result.code == 1, result.err
    assert where in result.err and what in result.err, result.err
    assert no_partial_outputs(out)


@pytest.mark.parametrize("scheduler", ["threads", SLOW_PROCESSES, SLOW_CLUSTER])
def test_tasks_still_running_after_a_failure_leave_nothing_behind(tmp_path, btf, scheduler,
                                                                  request):
    # Many images, one bad: when the bad one fails, other tasks are mid-write. Cleanup must wait
    # for them, or they recreate the partial store after it was removed.
    src = tmp_path / "src"
    src.mkdir()
    rng = np.random.default_rng(0)
    for k in range(40):
        pixels = rng.uniform(0, 1, (192, 192, 3)).astype(np.float32)
        if k == 6:
            pixels[5, 5, 0] = np.nan
        write_exr(src / f"tl{k}_pl0_tv0_pv0.exr", pixels, ("R", "G", "B"))
    if scheduler == "cluster":
        scheduler = request.getfixturevalue("local_cluster")
    result = btf("ingest", src, tmp_path / "out.zarr", "--quiet", "--scheduler", scheduler)
    assert result.code == 1 and "tl6_pl0_tv0_pv0.exr" in result.err
    time.sleep(0.5)  # anything still writing would show up now
    assert no_partial_outputs(tmp_path / "out.zarr")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["src"]


def test_a_failed_ingest_keeps_the_previous_good_store(tmp_path, btf):
    src = _folder(tmp_path)
    out = tmp_path / "out.zarr"
    assert btf("ingest", src, out, "--quiet").code == 0
    before = _store_values(out)[0]
    _non_finite(src)
    assert btf("ingest", src, out, "--quiet", "--overwrite").code == 1
    assert np.array_equal(_store_values(out)[0], before)


def test_export_splits_blocks_that_exceed_the_memory_budget(tmp_path, btf, small_abtf,
                                                            monkeypatch):
    layer = 48 * 48 * 3 * 4
    monkeypatch.setattr("pipeline.stages.export.TASK_BUDGET", 3 * layer)  # 3 layers per task
    import pipeline.stages.export as export

    calls = []
    real = export._export_block
    monkeypatch.setattr(export, "_export_block",
                        lambda *a, **k: calls.append(len(a[3])) or real(*a, **k))
    assert btf("export", small_abtf, tmp_path / "all", "--quiet", "--scheduler",
               "synchronous").code == 0
    assert max(calls) == 3 and sum(calls) == 18
    back = tmp_path / "back.zarr"
    assert btf("ingest", tmp_path / "all", back, "--quiet").code == 0
    assert np.array_equal(_store_values(back)[0], _store_values(small_abtf)[0])


def test_export_selection_and_bad_indices(tmp_path, btf, small_btf):
    result = btf("export", small_btf, tmp_path / "sel", "--view", "1", "--light", "0,2",
                 "--quiet")
    assert result.code == 0
    with (tmp_path / "sel" / "manifest.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 2 and {r["file"] for r in rows} == {
        p.name for p in (tmp_path / "sel").glob("*.exr")}
    result = btf("export", small_btf, tmp_path / "bad", "--light", "7", "--quiet")
    assert result.code == 1 and "--light 7 is out of range (the store has 3 lights" in result.err
    assert no_partial_outputs(tmp_path / "bad")


def test_export_refuses_a_store_that_is_not_one(tmp_path, btf, small_btf):
    broken = tmp_path / "broken.zarr"
    shutil.copytree(small_btf, broken)
    shutil.rmtree(broken / "radiance")
    (broken / "zarr.json").write_text((broken / "zarr.json").read_text())
    result = btf("export", broken, tmp_path / "x", "--quiet")
    assert result.code == 1 and str(broken) in result.err and "radiance" in result.err


def test_preview_draws_a_labelled_contact_sheet(tmp_path, btf, small_btf):
    out = tmp_path / "sheet.png"
    assert btf("preview", small_btf, out, "--count", "5", "--quiet").code == 0
    pixels, _ = read_image(out)
    assert pixels.shape[0] > 200 and pixels.shape[1] > 400
    assert pixels.std() > 0.05  # not a blank image

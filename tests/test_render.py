"""``btf render``: one layer of a surface of any size from a tile set, and its placement."""

from __future__ import annotations

import itertools
import shutil

import numpy as np
import pytest
import zarr

from helpers import quilt
from pipeline.errors import BTFError
from pipeline.graphs.surface import lazy_layer
from pipeline.stores.base import RADIANCE

SMALL_TILES = ("--block", "16", "--overlap", "4", "--candidates", "4", "--size", "24,24")


@pytest.fixture(scope="module")
def corner_tiles(samples, tmp_path_factory):
    """16 corner tiles (V = 2) of 24^2 quilted from the fabric sample."""
    out = tmp_path_factory.mktemp("render") / "q.zarr"
    quilt(samples["fabric"], out, *SMALL_TILES, "--corners", "2")
    return out


def test_rendering_is_consistent_where_regions_overlap(corner_tiles):
    a = lazy_layer(corner_tiles, view=0, light=3, size=(100, 130), origin=(-40, 10),
                   seed=9, chunk=32).compute()
    b = lazy_layer(corner_tiles, view=0, light=3, size=(90, 70), origin=(0, 50),
                   seed=9, chunk=48).compute()
    assert np.array_equal(a[40:100, 40:110], b[:60, :70])
    other = lazy_layer(corner_tiles, view=0, light=3, size=(100, 130),
                       origin=(-40, 10), seed=10, chunk=32).compute()
    assert not np.array_equal(a, other)


def test_rendering_follows_the_stored_corner_types_of_each_tile(tmp_path, corner_tiles):
    path = shutil.copytree(corner_tiles, tmp_path / "q.zarr")  # changed below
    before = lazy_layer(path, view=0, light=1, size=(80, 90), origin=(-7, 5)).compute()
    group = zarr.open_group(path, mode="r+")
    perm = np.random.default_rng(1).permutation(16)
    group[RADIANCE][...] = group[RADIANCE][...][perm]
    group["corners"][...] = group["corners"][...][perm]
    after = lazy_layer(path, view=0, light=1, size=(80, 90), origin=(-7, 5)).compute()
    assert np.array_equal(before, after)
    group["corners"][3] = group["corners"][4]
    with pytest.raises(BTFError, match="'corners' does not hold every combination"):
        lazy_layer(path, view=0, light=1, size=(8, 8))


@pytest.mark.parametrize("origin", [(0, 0), (-13, -4), (95, -301)])
def test_a_rendered_texel_is_its_cells_tile_at_its_offset(origin):
    from tasks.placement import cell_tiles, gather

    tiles = np.random.default_rng(0).random((16, 7, 5, 3)).astype(np.float32)
    y0, x0 = origin
    out = gather(tiles, y0, x0, 23, 19, seed=3, corners=2)
    for y, x in itertools.product(range(23), range(19)):
        cy, cx = (y0 + y) // 7, (x0 + x) // 5
        tile = cell_tiles(cy, cx, 1, 1, seed=3, corners=2)[0, 0]
        assert np.array_equal(out[y, x], tiles[tile, (y0 + y) % 7, (x0 + x) % 5])


def test_rendering_one_layer_reads_no_other_layer(tmp_path, btf, samples, monkeypatch):
    from test_compress import ReadCounter

    quilt(samples["tiles"], tmp_path / "q.zarr", *SMALL_TILES)
    counter = ReadCounter(monkeypatch)
    out = tmp_path / "surface.zarr"
    assert btf("render", tmp_path / "q.zarr", out, "--light", "5", "--size", "700,900",
               "--chunk", "256", "--quiet").code == 0
    layers = {key.split("/radiance/c/")[1].split("/")[2] for key in counter.chunks(RADIANCE)
              if "q.zarr" in key}
    assert layers == {"5"}  # chunk keys: tile/view/light/...
    surface = zarr.open_group(out, mode="r")
    assert surface.attrs["btf_kind"] == "surface" and surface.attrs["light"] == 5
    expected = lazy_layer(tmp_path / "q.zarr", view=0, light=5, size=(700, 900)).compute()
    assert np.array_equal(surface[RADIANCE][:], expected)
    report = btf("inspect", out)
    assert report.code == 0 and "surface: 700 x 900 texels of light 5, view 0" in report.out
    again = btf("render", tmp_path / "q.zarr", out, "--light", "2", "--size", "70,90",
                "--overwrite", "--quiet")
    assert again.code == 0 and zarr.open_group(out)[RADIANCE].shape == (70, 90, 3)


def test_render_refuses_what_is_not_a_tile_set(tmp_path, btf, samples):
    result = btf("render", samples["stone"], tmp_path / "x.exr", "--light", "0", "--size",
                 "10,10")
    assert result.code == 1 and "not a tile-set store" in result.err

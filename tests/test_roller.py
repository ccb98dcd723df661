"""The generalized roller (paper 004): lattice detection, double toroidal tiles, rendering."""

from __future__ import annotations

import json

import numpy as np
import pytest
import zarr
from scipy import ndimage

from helpers import generate_store, no_partial_outputs
from pipeline.graphs.surface import lazy_layer
from pipeline.images import read_image, write_exr
from pipeline.stores import open_store
from pipeline.stores.base import RADIANCE
from pipeline.stores.radiance import open_radiance
from tasks.periodicity import detect_lattice
from tasks.placement import lattice_cells
from tasks.prescription import check, to_csr
from tasks.svd import reconstruct_layers
from tasks.transform import Transform

ROT = np.radians(30.0)
LATTICES = {  # (u, v) as (dy, dx)
    "axis-aligned": ((0.0, 20.0), (24.0, 0.0)),
    "rotated-30": ((24 * np.sin(ROT), 24 * np.cos(ROT)),
                   (20 * np.sin(ROT + np.pi / 2), 20 * np.cos(ROT + np.pi / 2))),
    "sheared": ((0.0, 22.0), (18.0, 8.0)),
}


def constructed(u, v, size=160, seed=0, noise=0.05) -> np.ndarray:
    """A texture with exactly the lattice ``u``, ``v``: a random Fourier series on the torus."""
    rng = np.random.default_rng(seed)
    basis_inv = np.linalg.inv(np.array([u, v], float).T)
    yy, xx = np.mgrid[0:size, 0:size].astype(float)
    a, b = np.einsum("ij,jyx->iyx", basis_inv, np.stack([yy, xx]))
    g = np.zeros((size, size))
    for k1 in range(-3, 4):
        for k2 in range(0, 4):
            if k2 == 0 and k1 <= 0:
                continue
            g += rng.random() / (1 + k1 * k1 + k2 * k2) * np.cos(
                2 * np.pi * (k1 * a + k2 * b) + rng.random() * 2 * np.pi)
    g = (g - g.min()) / (g.max() - g.min())
    return 0.15 + 0.7 * np.clip(g + noise * rng.standard_normal(g.shape), 0, 1)


def same_vector(found, truth, px=1.0, deg=2.0) -> bool:
    """Equal up to sign within ``px`` pixels and ``deg`` degrees."""
    found, truth = np.asarray(found), np.asarray(truth)
    if np.linalg.norm(found + truth) < np.linalg.norm(found - truth):
        found = -found
    cos = found @ truth / np.linalg.norm(found) / np.linalg.norm(truth)
    return (np.linalg.norm(found - truth) <= px
            and np.degrees(np.arccos(np.clip(cos, -1, 1))) <= deg)


def same_lattice(found_u, found_v, u, v) -> bool:
    return ((same_vector(found_u, u) and same_vector(found_v, v))
            or (same_vector(found_u, v) and same_vector(found_v, u)))


@pytest.mark.parametrize("name", sorted(LATTICES))
@pytest.mark.parametrize("seed", [0, 1])
def test_detects_a_known_lattice_within_a_pixel_and_two_degrees(name, seed):
    u, v = LATTICES[name]
    lattice = detect_lattice(constructed(u, v, seed=seed))
    assert same_lattice(lattice.u, lattice.v, u, v), (lattice, u, v)
    assert lattice.confidence > 0.8


def _albedo_store(tmp_path, name, image):
    path = tmp_path / f"{name}.exr"
    write_exr(path, np.repeat(image[..., None], 3, axis=-1).astype(np.float32), ("R", "G", "B"))
    return generate_store(tmp_path / f"{name}.zarr", "--albedo", str(path), "--sampling",
                          "abtf:4,2", "--chunk", "64")


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("roller")
    out = {"tiles": generate_store(tmp / "tiles.zarr", "--material", "tiles", "--size", "160",
                                   "--scale", "32", "--sampling", "abtf:4,2", "--seed", "3"),
           "stone": generate_store(tmp / "stone.zarr", "--material", "stone", "--size", "128",
                                   "--sampling", "abtf:4,2", "--seed", "3")}
    for name in ("rotated-30", "sheared"):
        out[name] = _albedo_store(tmp, name, constructed(*LATTICES[name], seed=4))
    return out


def _detect(btf, store):
    result = btf("roller", store, "--detect-only", "--json", "--quiet")
    assert result.code == 0, result.err
    return json.loads(result.out)


@pytest.mark.parametrize("name", ["tiles", "rotated-30", "sheared"])
def test_btf_roller_detects_the_lattice_of_a_store(btf, stores, name):
    found = _detect(btf, stores[name])
    assert set(found) >= {"u", "v", "angles_deg", "lengths_px", "confidence"}
    u, v = ((0.0, 32.0), (32.0, 0.0)) if name == "tiles" else LATTICES[name]
    assert same_lattice(found["u"], found["v"], u, v), found
    for vec, length, angle in zip((found["u"], found["v"]), found["lengths_px"],
                                  found["angles_deg"], strict=True):
        assert length == pytest.approx(np.hypot(*vec), abs=1e-2)
        a = np.radians(angle)  # the line of the vector: cross product with it is 0
        assert np.cos(a) * vec[0] - np.sin(a) * vec[1] == pytest.approx(0.0, abs=1e-2)
    assert found["confidence"] > 0.5 and found["periodic"]


def test_a_texture_without_periodicity_is_reported_and_not_tiled(btf, stores, tmp_path):
    found = _detect(btf, stores["stone"])
    assert found["confidence"] < 0.5 and not found["periodic"]
    assert "no clear periodicity" in found["message"]
    text = btf("roller", stores["stone"], "--detect-only", "--quiet")
    assert text.code == 0 and "no clear periodicity" in text.err
    out = tmp_path / "stone_tiles.zarr"
    result = btf("roller", stores["stone"], out, "--quiet")
    assert result.code == 1
    assert "no clear periodicity" in result.err and "stone.zarr" in result.err
    assert no_partial_outputs(out)


def _roller(btf, store, out, *args):
    result = btf("roller", store, out, "--quiet", *args)
    assert result.code == 0, result.err
    return zarr.open_group(out, mode="r")


@pytest.fixture(scope="module")
def rolled(stores, tmp_path_factory):
    """``rolled(name, *options)``: the path of the roller's tile set of ``stores[name]``, made
    once for the tests that only read it (a plan and its border check each)."""
    from pipeline.cli import main

    made = {}

    def get(name: str, *options: str):
        if (name, options) not in made:
            out = tmp_path_factory.mktemp("rolled") / f"{name}.zarr"
            assert main(["roller", str(stores[name]), str(out), "--quiet", *options]) == 0
            made[name, options] = out
        return made[name, options]

    return get


def _cells(group, size, origin=(0, 0)):
    lat = group.attrs["lattice"]
    return lattice_cells(*origin, *size, hnf=tuple(lat["hnf"]),
                         basis=(tuple(lat["U"]), tuple(lat["V"])),
                         representative=group["representative"][...])


def _seams(cells):
    """Masks of horizontal and vertical neighbour pairs that lie in different cells."""
    return (np.any(cells[:, 1:] != cells[:, :-1], axis=-1),
            np.any(cells[1:] != cells[:-1], axis=-1))


def _pair_differences(img, masks):
    dx = np.abs(np.diff(img, axis=1)).mean(axis=-1)
    dy = np.abs(np.diff(img, axis=0)).mean(axis=-1)
    return np.concatenate([dx[masks[0]], dy[masks[1]]])


def _sample_roughness(img):
    return float(np.mean([np.abs(np.diff(img, axis=a)).mean() for a in (0, 1)]))


TOLERANCE = 1.5


@pytest.mark.parametrize("name", ["tiles", "rotated-30", "sheared"])
def test_roller_output_is_seamless_and_a_naive_repeat_is_not(stores, rolled, name):
    group = zarr.open_group(rolled(name), mode="r")
    sample = open_radiance(stores[name])[RADIANCE].values[0]
    size = (300, 340)
    for light in (0, 5):
        img = lazy_layer(rolled(name), view=0, light=light, size=size).compute()
        seams = _pair_differences(img, _seams(_cells(group, size)))
        assert seams.size > 100
        ratio = seams.mean() / _sample_roughness(sample[light])
        assert ratio < TOLERANCE, (light, ratio)
    # a naive repeat of an arbitrary crop of about the same area (not a multiple of the period)
    ty = tx = int(np.sqrt(np.prod(group["representative"].shape[:2]))) + 11
    crop = sample[0, 7 : 7 + ty, 5 : 5 + tx]
    naive = np.tile(crop, (size[0] // ty + 1, size[1] // tx + 1, 1))[: size[0], : size[1]]
    yy, xx = np.mgrid[0 : size[0], 0 : size[1]]
    cells = np.stack([yy // ty, xx // tx], -1)
    ratio = _pair_differences(naive, _seams(cells)).mean() / _sample_roughness(sample[0])
    assert ratio > TOLERANCE


# Three tiles of the constructed texture, seed 5: several tiles (their interiors differ).
SEVERAL = ("--tiles", "3", "--seed", "5")


def test_every_layer_uses_the_same_cut(stores, rolled):
    group = zarr.open_group(rolled("sheared", *SEVERAL), mode="r")
    sample = open_radiance(stores["sheared"])[RADIANCE].values[0]
    ny, nx = sample.shape[1:3]
    out = group[RADIANCE][:]
    assert out.shape[0] == 3
    for t in range(3):
        index = group["prescription_index"][t]
        weight = group["prescription_weight"][t]
        assert check(index, weight, ny * nx) == []
        matrix = to_csr(index, weight, ny * nx)
        for light in range(sample.shape[0]):
            expected = (matrix @ sample[light].reshape(ny * nx, -1)).reshape(out.shape[3:])
            np.testing.assert_allclose(out[t, 0, light], expected, rtol=1e-5, atol=1e-6)


def test_multiple_tiles_share_their_borders_exactly_and_seeds_reproduce(stores, rolled):
    # the constructed texture has noise: rhomboids one period apart differ (the generated tiles
    # material is exactly periodic, so its extra tiles would equal the first)
    path = rolled("sheared", *SEVERAL)
    group = zarr.open_group(path, mode="r")
    tiles = group[RADIANCE][:, 0, 2]
    assert not np.array_equal(tiles[0], tiles[1]) and not np.array_equal(tiles[1], tiles[2])
    size = (260, 300)

    def render(seed):
        return lazy_layer(path, view=0, light=2, size=size, seed=seed).compute()

    a, b = render(1), render(2)
    assert np.array_equal(a, render(1))
    assert np.array_equal(render(None), render(5))  # the tile set's own seed by default
    cells = _cells(group, size)
    ids = cells[..., 0] * 100003 + cells[..., 1]
    near = (ndimage.maximum_filter(ids, size=5) != ndimage.minimum_filter(ids, size=5))
    assert near.mean() > 0.05
    np.testing.assert_array_equal(a[near], b[near])  # borders: identical in every tile
    assert not np.array_equal(a[~near], b[~near])  # interiors: the seed picks other tiles
    seams = _pair_differences(a, _seams(cells)).mean()
    sample = open_radiance(stores["sheared"])[RADIANCE].values[0, 2]
    assert seams / _sample_roughness(sample) < TOLERANCE


def test_inspect_reports_the_lattice_and_the_ratio(btf, rolled):
    tiles = rolled("rotated-30")
    group = zarr.open_group(tiles, mode="r")
    result = btf("inspect", tiles, "--json")
    assert result.code == 0, result.err
    report = json.loads(result.out)["tileset"]
    lattice = group.attrs["lattice"]
    for key in ("hnf", "U", "V", "periods", "u", "v"):
        assert report["lattice"][key] == lattice[key], key
    h, w, _ = lattice["hnf"]
    assert report["tiles"] == group["radiance"].shape[0] == 1
    assert report["tile_shape"] == [h, w] == list(group["radiance"].shape[3:5])
    assert report["size_vs_source"] == pytest.approx(h * w / np.prod(report["sample_shape"]))
    text = btf("inspect", tiles).out
    assert f"stored as {h} x {w} (Hermite layout, shear {lattice['hnf'][2]})" in text
    assert f"size relative to the sample: 1 : {1 / report['size_vs_source']:.2f}" in text


def test_render_a_roller_tile_set_into_an_exr(btf, rolled, tmp_path):
    tiles = rolled("sheared")
    out = tmp_path / "surface.exr"
    result = btf("render", tiles, out, "--light", "1", "--size", "200,333",
                 "--origin=-17,40", "--quiet")
    assert result.code == 0, result.err
    pixels, channels = read_image(out)
    assert channels == ("R", "G", "B") and pixels.shape == (200, 333, 3)
    expected = lazy_layer(tiles, view=0, light=1, size=(200, 333),
                          origin=(-17, 40)).compute(scheduler="synchronous")
    assert pixels.dtype == expected.dtype == np.float32
    assert expected.std() > 0  # a textured region, not a constant any shift would match
    assert np.array_equal(pixels, expected)  # float32 EXR: bit for bit


def test_bad_roller_options_are_named(btf, stores, tmp_path):
    result = btf("roller", stores["tiles"], "--quiet")
    assert result.code == 2 and "OUT" in result.err
    result = btf("roller", stores["tiles"], tmp_path / "x.zarr", "--json")
    assert result.code == 2 and "--json" in result.err
    result = btf("roller", stores["tiles"], tmp_path / "x.zarr", "--tiles", "0")
    assert result.code == 2 and "--tiles" in result.err


def test_the_roller_on_a_compressed_store_gives_a_compressed_tile_set(btf, stores, tmp_path):
    assert btf("compress", stores["tiles"], tmp_path / "c.zarr", "--rank", "8",
               "--quiet").code == 0
    group = _roller(btf, tmp_path / "c.zarr", tmp_path / "t.zarr", "--tiles", "2")
    plain = _roller(btf, stores["tiles"], tmp_path / "p.zarr", "--tiles", "2")
    assert group.attrs["btf_kind"] == "compressed-tileset"
    # the same lattice and tile as on the radiance store (detected on a reconstructed layer)
    assert group.attrs["lattice"]["hnf"] == plain.attrs["lattice"]["hnf"]
    v = zarr.open_array(tmp_path / "c.zarr", path="V")[:]
    n = v.shape[0] * v.shape[1]
    assert np.array_equal(group["V"][:], v)  # the sample's eigentextures, and prescriptions
    tiles = open_store(tmp_path / "t.zarr").tile_eigentextures(range(2))
    for t in range(2):
        matrix = to_csr(group["prescription_index"][t], group["prescription_weight"][t], n)
        assert np.allclose(tiles[t], (matrix @ v.reshape(n, -1)).reshape(tiles.shape[1:]),
                           atol=1e-6)
    # Each compressed tile is its prescription applied to the measured layer, up to the rank-8
    # compression error (and log-domain blending at the cuts). The two plans need not pick the
    # same tile origin on this exactly periodic material (ties), so the comparison is with the
    # compressed plan applied to the radiance itself.
    layer = zarr.open_array(stores["tiles"], path=RADIANCE)[0, 3]
    eps = group.attrs["transform"]["eps"]
    for t in range(2):
        matrix = to_csr(group["prescription_index"][t], group["prescription_weight"][t], n)
        direct = (matrix @ layer.reshape(n, -1)).reshape(*tiles.shape[1:3], -1)
        tile = reconstruct_layers(group["U"][0, 3], group["S"][:], tiles[t],
                                  transform=Transform("log", eps))
        assert np.abs(tile - direct).mean() < 0.05 * np.abs(direct).mean()
    rendered = lazy_layer(tmp_path / "t.zarr", view=0, light=3, size=(120, 150)).compute()
    assert np.isfinite(rendered).all() and rendered.shape == (120, 150, 3)


@pytest.mark.slow  # a benchmark suite end to end (about 10 s)
def test_btf_bench_roller_reports_its_tables():
    import argparse

    from benchmarks import roller as suite

    args = argparse.Namespace(material="tiles", sizes="256", render=512, repeat=1, json=None,
                              lattices=8, seam_seeds=2, seams_only=False)
    result = suite.run(args)
    text = suite.report(result)
    assert "| 256^2 | 64.0 at 0, 64.0 at 90 | 1.00 |" in text
    assert "Lattice detection on 8 random lattices" in text and "| all |" in text
    assert result["rendering"]["render_gbps"] > 0 and result["rendering"]["tile_gbps"] > 0
    assert "Tile borders of the roller, seed by seed: 2 random lattices" in text
    seams = result["seams"]
    # both are seamless on this periodic material: no rougher than the sample across tiles
    assert seams["roller"]["tile_border"] < 1.5 and seams["quilt"]["tile_border"] < 1.5


@pytest.mark.slow
def test_btf_bench_tradeoff_sweeps_and_plots(tmp_path):
    import argparse

    from benchmarks import tradeoff as suite

    result = suite.run(argparse.Namespace(stages="roller,compress", plots=str(tmp_path)))
    text = suite.report(result)
    for stage in ("roller", "compress"):
        rows = result["stages"][stage]
        assert sum(r["default"] for r in rows) == 1
        assert all(r["seconds"] > 0 and np.isfinite(r["error"]) for r in rows)
        assert (tmp_path / f"tradeoff_{stage}.png").stat().st_size > 10_000
    compress = {r["label"]: r["error"] for r in result["stages"]["compress"]}
    # more components can only lower the optimum's error; power iterations approach it
    assert compress["rank 8"] > compress["rank 16"] > compress["rank 32"] > compress["rank 64"]
    assert compress["rank 32, q = 0"] >= compress["rank 32"]
    assert "| 1 tile(s) * |" in text


@pytest.mark.slow
def test_a_tile_whose_borders_stand_out_is_replaced_by_another_size():
    """A gradient-lit checkerboard (benchmarks.lattices, seed 16): the preferred periods join
    cells whose brightness differs by the gradient across the tile; the border check takes
    another tile size, and a surface of all its tiles, measured independently, passes."""
    from benchmarks.lattices import random_lattice_texture
    from tasks.lattice import lattice_cells
    from tasks.periodicity import detect_lattice
    from tasks.placement import lattice_gather
    from tasks.roller import RollerParams, border_check, period_candidates, plan_roller
    from tasks.seams import PATCH, PatchExemplar, cell_figures

    case = random_lattice_texture(np.random.default_rng(16))
    g = (case.image - case.image.min()) / np.ptp(case.image)
    image = np.stack([g, np.sqrt(g), g * g], axis=-1)
    lattice = detect_lattice(g)
    exemplar = PatchExemplar(image.astype(np.float32))
    params = RollerParams(tiles=3)
    first = period_candidates(image.shape[:2], lattice.u, lattice.v, params)[0]
    unchecked = plan_roller(image, lattice.u, lattice.v,
                            RollerParams(tiles=3, periods=first, max_seam=100))
    assert max(border_check(image, unchecked, exemplar)) > 1.5
    plan = plan_roller(image, lattice.u, lattice.v, params)
    assert plan.periods != first and max(plan.check) <= 1.3
    flat = image.reshape(-1, 3)
    stored = np.einsum("tnk,tnkc->tnc", plan.weight, flat[np.maximum(plan.index, 0)])
    stored = stored.reshape(3, *plan.tile_shape, 3)
    surface = lattice_gather(stored, 0, 0, 384, 384, hnf=plan.hnf, basis=(plan.U, plan.V),
                             representative=plan.representative, seed=7)
    cells = lattice_cells(0, 0, 384, 384, hnf=plan.hnf, basis=(plan.U, plan.V),
                          representative=plan.representative)
    assert max(cell_figures(exemplar, surface, cells, reach=PATCH / 2)) <= 1.5


def test_a_sample_no_tile_size_closes_is_refused_with_the_best_figure():
    from benchmarks.lattices import random_lattice_texture
    from tasks.periodicity import detect_lattice
    from tasks.roller import RollerParams, RollerSeamError, plan_roller

    case = random_lattice_texture(np.random.default_rng(15))  # a weave whose cuts jog
    g = (case.image - case.image.min()) / np.ptp(case.image)
    lattice = detect_lattice(g)
    with pytest.raises(RollerSeamError, match=r"tile size\(s\), the best tile .* bound 1.3"):
        plan_roller(np.stack([g, g, g], -1), lattice.u, lattice.v, RollerParams(attempts=2))

"""btf generate: contract, determinism, physical sanity, and clean failure."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import zarr

from helpers import SLOW_PROCESSES, facing, generate_store, no_partial_outputs
from pipeline.images import write_exr, write_png
from pipeline.session import RuntimeOptions, Session
from pipeline.stages.generate import GenerateParams, generate
from pipeline.stores.base import RADIANCE
from pipeline.stores.radiance import open_radiance
from tasks.materials import bump_height, bump_relief

SMALL = ("--material", "stone", "--size", "40", "--sampling", "hemi:3", "--chunk", "8",
         "--shard", "16", "--dir-chunk", "2", "--seed", "11")
VARIABLES = (RADIANCE, "height", "albedo", "roughness", "specular")


def _arrays(path: Path) -> dict[str, np.ndarray]:
    group = zarr.open_group(path, mode="r")
    return {name: group[name][:] for name in VARIABLES}


def test_generated_store_follows_the_contract(small_abtf):
    ds = open_radiance(small_abtf)
    rad = ds[RADIANCE]
    assert rad.dims == ("view", "light", "y", "x", "channel")
    assert rad.shape == (1, 18, 48, 48, 3) and rad.dtype == np.float32
    assert ds.attrs["btf_kind"] == "abtf" and ds.attrs["source"] == "generate"
    prov = ds.attrs["provenance"]
    assert prov["command"].startswith("btf generate ") and "--material wood" in prov["command"]
    assert prov["parameters"]["seed"] == 3 and prov["version"]
    assert "overwrite" not in prov["parameters"]
    values = rad.values
    assert np.isfinite(values).all() and values.min() >= 0
    for name in ("height", "albedo", "roughness", "specular"):
        assert ds[name].dims[:2] == ("y", "x") and np.isfinite(ds[name].values).all()


# processes in the slow set, as test_a_local_cluster_gives_the_identical_store's worker
# processes
@pytest.mark.parametrize("scheduler", ["synchronous", SLOW_PROCESSES])
def test_same_arguments_give_identical_stores_on_every_scheduler(tmp_path, scheduler,
                                                                 small_tasks):
    reference = generate_store(tmp_path / "threads" / "s.zarr", *SMALL, "--scheduler", "threads")
    other = generate_store(tmp_path / scheduler / "s.zarr", *SMALL, "--scheduler", scheduler)
    a, b = _arrays(reference), _arrays(other)
    for name in VARIABLES:
        assert np.array_equal(a[name], b[name]), name


@pytest.mark.slow  # 10 s (a cluster): kept out of the default run (4 min), run by .ci/run
@pytest.mark.distributed
def test_a_local_cluster_gives_the_identical_store(tmp_path, local_cluster, small_tasks):
    reference = generate_store(tmp_path / "a" / "s.zarr", *SMALL, "--scheduler", "synchronous")
    other = generate_store(tmp_path / "b" / "s.zarr", *SMALL, "--scheduler", local_cluster)
    a, b = _arrays(reference), _arrays(other)
    for name in VARIABLES:
        assert np.array_equal(a[name], b[name]), name


def test_the_tiling_and_chunking_do_not_change_the_values(tmp_path, monkeypatch):
    one_block = generate_store(tmp_path / "a.zarr", *SMALL)  # a single 40 x 40 task block
    monkeypatch.setattr("pipeline.graphs.blocks.TASK_TEXELS", 8)
    many = generate_store(tmp_path / "b.zarr", *SMALL[:-8], "--chunk", "8", "--shard", "0",
                          "--dir-chunk", "3", "--seed", "11")  # 25 blocks of 8 x 8 texels
    a, b = _arrays(one_block), _arrays(many)
    for name in VARIABLES:
        assert np.array_equal(a[name], b[name]), name


def test_different_seeds_give_different_materials(tmp_path):
    a = generate_store(tmp_path / "a.zarr", *SMALL)
    b = generate_store(tmp_path / "b.zarr", *SMALL[:-1], "12")
    ra, rb = _arrays(a)[RADIANCE], _arrays(b)[RADIANCE]
    assert np.abs(ra - rb).mean() > 0.1 * ra.mean()


def test_tiles_layers_are_periodic_with_the_period_set(tmp_path, small_tasks):
    path = generate_store(tmp_path / "t.zarr", "--material", "tiles", "--size", "60",
                          "--scale", "20", "--sampling", "abtf:4,2", "--chunk", "16")
    rad = _arrays(path)[RADIANCE]
    assert np.array_equal(rad[:, :, 20:], rad[:, :, :40])
    assert np.array_equal(rad[:, :, :, 20:], rad[:, :, :, :40])
    assert np.abs(rad[:, :, 10:] - rad[:, :, :50]).mean() > 0.05 * rad.mean()
    assert zarr.open_group(path).attrs["material"]["period"] == 20


def test_low_lights_cast_shadows_in_stored_layers(small_abtf):
    # Texels far darker than the shadow-free Lambertian prediction (stored albedo x cos theta)
    # are in cast shadow: many under grazing light, none under light from near the normal.
    ds = open_radiance(small_abtf)
    rad = ds[RADIANCE].values[0].mean(axis=-1)
    albedo = ds["albedo"].values.mean(axis=-1)
    theta = ds["theta_light"].values
    dark = np.array([np.mean(rad[i] < 0.3 * albedo * np.cos(np.radians(t)))
                     for i, t in enumerate(theta)])
    assert dark[theta == theta.max()].mean() > 0.03
    assert dark[theta == theta.min()].max() == 0.0
    assert dark[theta == theta.max()].mean() > 5 * dark[(theta > 30) & (theta < 60)].mean()


def test_highlights_move_with_the_light_in_stored_layers(small_abtf):
    # Top view, light near the normal: the brightest texels are those facing the light
    # (ground truth: the stored height), and they move when the light turns.
    ds = open_radiance(small_abtf)
    height = ds["height"].values
    theta, phi = ds["theta_light"].values, ds["phi_light"].values
    tops = {}
    for i in np.flatnonzero(theta == theta.min()):
        layer = ds[RADIANCE].values[0, i].sum(axis=-1)
        top = layer > np.percentile(layer, 97)
        assert np.mean(facing(height, phi[i])[top] > 0) > 0.85
        tops[round(phi[i])] = top
    assert np.mean(tops[0] & tops[180]) < 0.25 * np.mean(tops[0])
    assert np.mean(tops[60] & tops[300]) < 0.5 * np.mean(tops[60])  # mirror images in y


def test_existing_output_is_kept_unless_overwrite(tmp_path, btf):
    path = generate_store(tmp_path / "s.zarr", *SMALL)
    before = _arrays(path)[RADIANCE]
    result = btf("generate", path, *SMALL[:-1], "99", "--quiet")
    assert result.code == 1 and "already exists" in result.err
    assert np.array_equal(_arrays(path)[RADIANCE], before)
    assert btf("generate", path, *SMALL[:-1], "99", "--quiet", "--overwrite").code == 0
    assert not np.array_equal(_arrays(path)[RADIANCE], before)


def _flaky_render(monkeypatch, fail_at: int) -> dict:
    import pipeline.stages.generate as gen

    calls = {"n": 0}
    real = gen.render_block

    def flaky(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == fail_at:
            raise RuntimeError("disk on fire")
        return real(*args, **kwargs)

    monkeypatch.setattr(gen, "render_block", flaky)
    return calls


@pytest.mark.parametrize("scheduler", ["synchronous", "threads"])
def test_a_failure_during_rendering_leaves_no_output(tmp_path, monkeypatch, small_tasks,
                                                     scheduler):
    calls = _flaky_render(monkeypatch, fail_at=3)
    params = GenerateParams(out=str(tmp_path / "s.zarr"), material="wood", size=64,
                            sampling="hemi:3", chunk=16, dir_chunk=1)
    with Session(RuntimeOptions(scheduler=scheduler, quiet=True)) as session:
        with pytest.raises(RuntimeError, match="disk on fire"):
            generate(params, session)
    assert calls["n"] >= 3
    assert no_partial_outputs(tmp_path / "s.zarr")


def test_a_failed_overwrite_keeps_the_previous_store(tmp_path, monkeypatch, btf):
    path = generate_store(tmp_path / "s.zarr", *SMALL)
    before = _arrays(path)
    _flaky_render(monkeypatch, fail_at=2)
    with pytest.raises(RuntimeError, match="disk on fire"):
        btf("generate", path, *SMALL[:-1], "12", "--overwrite", "--quiet")
    after = _arrays(path)
    for name in VARIABLES:
        assert np.array_equal(after[name], before[name])
    assert no_partial_outputs(tmp_path / "elsewhere.zarr") and len(list(tmp_path.iterdir())) == 1


@pytest.mark.parametrize(("args", "message"), [
    (("--size", "64"), "--material: is required"),
    (("--material", "wood"), "--size: is required"),
    (("--material", "marble", "--size", "64"), "invalid choice"),
    (("--material", "wood", "--size", "64", "--sampling", "dome"), "unknown sampling"),
    (("--material", "wood", "--size", "4"), "--size: must be between"),
    (("--material", "wood", "--size", "64", "--chunk", "64", "--shard", "100"),
     "--shard: must be 0 or a multiple of --chunk"),
    (("--material", "wood", "--size", "64", "--dir-chunk", "0"), "--dir-chunk: must be at least"),
    (("--material", "wood", "--size", "64", "--seed", str(2**64)), "--seed: must be between"),
    (("--albedo", "photo.png", "--seed", "3"), "--seed: has no effect with --albedo"),
    (("--material", "wood", "--size", "64", "--height", "bumps"),
     "--height: only applies with --albedo"),
    (("--albedo", "photo.png", "--height", "dunes"), "invalid choice"),
    (("--material", "wood", "--size", "64", "--scheduler", "gpu"), "unknown scheduler"),
])
def test_bad_arguments_are_refused_before_anything_is_written(tmp_path, btf, args, message):
    result = btf("generate", tmp_path / "s.zarr", *args)
    assert result.code == 2 and message in result.err
    assert no_partial_outputs(tmp_path / "s.zarr")


@pytest.mark.parametrize("suffix", [".png", ".exr"])
def test_a_photo_becomes_the_albedo_of_a_generated_store(tmp_path, btf, suffix, small_tasks):
    rng = np.random.default_rng(1)
    photo = tmp_path / f"photo{suffix}"
    pixels = rng.integers(20, 235, (36, 44, 3), dtype=np.uint8)  # 3 x 3 task blocks
    if suffix == ".png":
        write_png(photo, pixels)
        expected = ((pixels / 255.0 + 0.055) / 1.055) ** 2.4  # sRGB decoded
    else:
        expected = pixels.astype(np.float32) / 255
        write_exr(photo, expected, ("R", "G", "B"))
    out = tmp_path / "photo.zarr"
    assert btf("generate", out, "--albedo", photo, "--sampling", "abtf:3,2", "--chunk", "16",
               "--quiet").code == 0
    ds = open_radiance(out)
    assert ds[RADIANCE].shape == (1, 6, 36, 44, 3)
    assert np.allclose(ds["albedo"].values, expected, atol=1e-5)
    assert ds.attrs["provenance"]["inputs"][str(photo)].startswith("sha256:")
    assert np.isfinite(ds[RADIANCE].values).all()
    cropped = tmp_path / "crop.zarr"
    assert btf("generate", cropped, "--albedo", photo, "--size", "30", "--sampling", "abtf:3,2",
               "--quiet").code == 0
    assert np.allclose(open_radiance(cropped)["albedo"].values, expected[3:33, 7:37], atol=1e-5)


def test_a_photo_under_bumps_keeps_its_albedo_and_takes_the_seeds_relief(tmp_path, btf):
    photo = tmp_path / "photo.exr"
    pixels = np.random.default_rng(3).uniform(0.05, 0.95, (48, 40, 3)).astype(np.float32)
    write_exr(photo, pixels, ("R", "G", "B"))
    stores = {}
    for seed in (1, 2):
        stores[seed] = tmp_path / f"bumps{seed}.zarr"
        assert btf("generate", stores[seed], "--albedo", photo, "--height", "bumps", "--seed",
                   seed, "--scale", "12", "--sampling", "abtf:3,2", "--quiet").code == 0
    a, b = open_radiance(stores[1]), open_radiance(stores[2])
    assert np.allclose(a["albedo"].values, pixels, atol=1e-6)
    height = a["height"].values
    expected = bump_height(48, 40, seed=1, scale=12.0, relief=bump_relief(12.0))
    assert np.array_equal(height, expected)
    assert 0 <= height.min() and height.max() <= bump_relief(12.0) == pytest.approx(3.6)
    # the relief is the seed's, not the photo's: unrelated to the albedo's lightness
    lightness = pixels @ np.array([0.2126, 0.7152, 0.0722])
    assert abs(np.corrcoef(height.ravel(), lightness.ravel())[0, 1]) < 0.2
    assert not np.array_equal(b["height"].values, height)
    assert a.attrs["material"]["height"] == "bumps" and a.attrs["material"]["seed"] == 1


def test_bumps_are_smooth_span_their_relief_and_do_not_repeat():
    h = bump_height(256, 256, seed=7, scale=20.0, relief=6.0)
    assert h.dtype == np.float32 and 0.0 <= h.min() and h.max() <= 6.0
    assert h.max() - h.min() > 4.0  # domes and hollows, not a flat plate
    assert np.abs(np.diff(h, axis=0)).max() < 1.5 and np.abs(np.diff(h, axis=1)).max() < 1.5
    # no period up to half the field: every shift leaves the field well apart from itself
    for axis in (0, 1):
        for shift in range(8, 128):
            a = np.take(h, np.arange(0, 256 - shift), axis=axis)
            b = np.take(h, np.arange(shift, 256), axis=axis)
            assert np.sqrt(np.mean((a - b) ** 2)) > 0.1 * h.std(), (axis, shift)


def test_a_top_light_cannot_tell_bumps_from_their_flip_and_grazing_lights_can():
    # why one top-lit photo leaves the enlargement's gap on the bumps (issue 57): the relief
    # turned upside down (domes for hollows) shades the same under a top light, texel for
    # texel, and differs under every other light by about as much as the texture varies
    from tasks.materials import image_fields
    from tasks.shading import ShadingModel, render_block

    relief = bump_relief(20.0)
    h = bump_height(96, 96, seed=3, scale=20.0, relief=relief)
    albedo = np.random.default_rng(3).uniform(0.1, 0.9, (96, 96, 3)).astype(np.float32)
    model = ShadingModel(relief=relief)
    theta, phi = np.array([0.0, 45.0, 60.0, 75.0]), np.array([0.0, 90.0, 180.0, 270.0])
    layers = [np.log(1e-4 + render_block(
        image_fields(albedo, relief=relief, height=field), halo=model.halo(0.0, 75.0),
        theta_view=np.zeros(1), phi_view=np.zeros(1), theta_light=theta, phi_light=phi,
        model=model)[0].astype(np.float64)) for field in (h, relief - h)]
    apart = np.sqrt(np.mean((layers[0] - layers[1]) ** 2, axis=(1, 2, 3)))
    spread = layers[0].std(axis=(1, 2, 3))
    assert apart[0] < 1e-4 * spread[0]
    assert np.all(apart[1:] > 0.5 * spread[1:])


def test_a_missing_or_broken_photo_is_named(tmp_path, btf):
    result = btf("generate", tmp_path / "s.zarr", "--albedo", tmp_path / "nope.png")
    assert result.code == 1 and "nope.png: albedo image not found" in result.err
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"not a png at all, really not")
    result = btf("generate", tmp_path / "s.zarr", "--albedo", bad, "--quiet")
    assert result.code == 1 and "bad.png" in result.err
    assert no_partial_outputs(tmp_path / "s.zarr")


def test_a_photo_renders_the_same_in_one_block_or_many(tmp_path, monkeypatch):
    photo = tmp_path / "photo.exr"
    pixels = np.random.default_rng(2).uniform(0.05, 0.95, (40, 52, 3)).astype(np.float32)
    write_exr(photo, pixels, ("R", "G", "B"))
    args = ("--albedo", photo, "--sampling", "hemi:3", "--chunk", "8")
    one = generate_store(tmp_path / "one.zarr", *map(str, args))
    monkeypatch.setattr("pipeline.graphs.blocks.TASK_TEXELS", 16)
    many = generate_store(tmp_path / "many.zarr", *map(str, args))
    a, b = _arrays(one), _arrays(many)
    for name in VARIABLES:
        assert np.array_equal(a[name], b[name]), name


@pytest.mark.slow
def test_btf_bench_scaling_times_every_stage_under_every_configuration():
    import argparse

    from benchmarks import scaling as suite

    result = suite.run(argparse.Namespace(size=64, sampling="abtf:4,2", repeat=1,
                                          stages="generate,compress,enlarge,quilt"))
    seen = {(r["stage"], r["config"]) for r in result["runs"]}
    assert seen == {(s, c) for s in suite.STAGES for c in suite.CONFIGS}
    assert all(r["seconds"] > 0 and r["peak_rss"] > 0 for r in result["runs"])
    text = suite.report(result)
    for stage in suite.STAGES:
        assert f"| {stage} | " in text and f"- {stage}: `btf {stage} " in text


def test_the_shadow_and_view_caches_are_emptied_when_generate_ends(tmp_path, btf):
    """The stages a run config puts after generate, in the same process, do not keep its
    cached shadows (the plan counts them against generate's workers only)."""
    from tasks.shading import SHADOWS, VIEWS

    before, seen = SHADOWS.computed, VIEWS.computed
    result = btf("generate", tmp_path / "g.zarr", "--material", "stone", "--size", "16",
                 "--sampling", "hemi:3", "--scheduler", "threads", "--quiet")
    assert result.code == 0, result.err
    assert SHADOWS.computed > before and VIEWS.computed > seen  # the caches were used ...
    for cache in (SHADOWS, VIEWS):
        assert not cache.entries and cache.size == 0  # ... and are empty again

"""``btf generate --renderer mitsuba``: height-field materials path traced by Mitsuba 3.

Needs Mitsuba 3 and its llvm variant: slow tests, skipped with the reason where either is
missing, unless ``BTF_REQUIRE_MITSUBA=1`` (``.ci/run``) makes that a failure. The parameter
checks run in the default set.
"""

from __future__ import annotations

import numpy as np
import pytest
import zarr

from helpers import (
    generate_store,
    require_mitsuba_llvm,
    side_lights_brighten_the_slopes_facing_them,
)
from pipeline.cli import main
from pipeline.stores.radiance import open_radiance
from tasks.materials import Fields, Material
from tasks.sampling import direction_vectors
from tasks.shading import ShadingModel, normals


@pytest.fixture(scope="module")
def llvm():
    """Mitsuba with a working llvm variant, or a skip naming what is missing."""
    require_mitsuba_llvm()


def _trace(fields, halo, views, lights, **tracer):
    from tasks.pathtrace import PathTracer, render_block

    views, lights = np.asarray(views, float), np.asarray(lights, float)
    return render_block(fields, halo=halo, theta_view=views[:, 0], phi_view=views[:, 1],
                        theta_light=lights[:, 0], phi_light=lights[:, 1],
                        view_index=np.arange(len(views)), light_index=np.arange(len(lights)),
                        origin=(0, 0), tracer=PathTracer(**tracer))


VIEWS = [(0, 0), (40, 120), (55, 300)]
LIGHTS = [(0, 0), (30, 45), (60, 200), (75, 90)]


@pytest.mark.slow
@pytest.mark.parametrize("slope", [(0.0, 0.0), (0.3, 0.0), (0.0, 0.3), (-0.25, 0.2)])
def test_a_diffuse_plane_shows_albedo_times_the_cosine_in_the_stores_frame(llvm, slope):
    """Exact: a Lambertian plane of albedo a under irradiance pi has radiance a max(n.l, 0).

    Tilted planes rise along columns and along rows; their normals are btf's own
    (:func:`tasks.shading.normals`), so a frame error (a flipped row axis, a mirrored light)
    fails here.
    """
    n, halo = 24, 24
    rows, cols = np.mgrid[0 : n + 2 * halo, 0 : n + 2 * halo] - (halo + n // 2)
    height = 30.0 + slope[0] * cols + slope[1] * rows  # within [0, relief] everywhere
    albedo = np.array([0.8, 0.5, 0.2])
    fields = Fields.stack(height, albedo, 0.3, 0.04)
    got = _trace(fields, halo, VIEWS, LIGHTS, relief=60.0, bsdf="diffuse", spp=4)
    normal = np.array([c[halo, halo] for c in normals(height)], float)
    cosine = np.maximum(direction_vectors(*np.array(LIGHTS, float).T) @ normal, 0.0)
    want = np.broadcast_to(cosine[None, :, None, None, None] * albedo, got.shape)
    np.testing.assert_allclose(got, want, rtol=2e-5, atol=2e-6)


@pytest.mark.slow
def test_grazing_light_casts_shadows_and_bounces_fill_them(llvm):
    """Two walls: the first shadows the floor between them, the second's lit face lights it."""
    n, halo = 32, 24
    kept = np.mgrid[0 : n + 2 * halo, 0 : n + 2 * halo][1] - halo  # columns of the kept block
    walls = ((kept >= 8) & (kept < 12)) | ((kept >= 22) & (kept < 26))
    fields = Fields.stack(np.where(walls, 10.0, 0.0), 0.7, 0.3, 0.04)
    light = [(60, 180)]  # from -x: 10 px of wall at 60 degrees shadow 17 px of floor
    direct, bounced = (_trace(fields, halo, [(0, 0)], light, relief=10.0, bsdf="diffuse",
                              spp=16, max_depth=depth)[0, 0, ..., 0] for depth in (2, 4))
    lit, shadow = slice(2, 6), slice(14, 20)  # floor before the first wall, between them
    assert np.allclose(direct[:, lit], 0.7 * 0.5, rtol=1e-4)
    assert direct[:, shadow].max() == 0.0
    assert bounced[:, shadow].mean() > 0.03  # the second wall's lit face (noisy at 16 spp)
    assert (bounced[:, lit] >= direct[:, lit] - 1e-4).all()  # bounces only add light


@pytest.mark.slow
def test_generated_store_follows_the_contract_and_the_frame(llvm, tmp_path):
    path = generate_store(tmp_path / "l.zarr", "--material", "leather", "--size", "40",
                          "--sampling", "abtf:4,2", "--seed", "5", "--renderer", "mitsuba",
                          "--spp", "16", "--bsdf", "diffuse", "--bounces", "0")
    ds = open_radiance(path)
    shading = zarr.open_group(path, mode="r").attrs["shading"]
    assert shading["renderer"].startswith("mitsuba") and shading["spp"] == 16
    assert ds["radiance"].shape == (1, 8, 40, 40, 3)
    h = ds["height"].values
    assert np.array_equal(h, Material("leather", seed=5).fields(0, 0, 40, 40).height)
    side_lights_brighten_the_slopes_facing_them(ds)
    # btf's own shading model sees the same surface
    shaded = generate_store(tmp_path / "s.zarr", "--material", "leather", "--size", "40",
                            "--sampling", "abtf:4,2", "--seed", "5")
    a = ds["radiance"].values.mean(-1).ravel()
    b = open_radiance(shaded)["radiance"].values.mean(-1).ravel()
    assert np.corrcoef(a, b)[0, 1] > 0.9


@pytest.mark.slow
def test_every_scheduler_gives_the_identical_store_and_blocks_leave_no_seams(llvm, tmp_path,
                                                                              monkeypatch):
    from conftest import SMALL_TASKS

    args = ("--material", "stone", "--size", "32", "--sampling", "hemi:3", "--chunk", "8",
            "--shard", "16", "--dir-chunk", "2", "--seed", "3", "--renderer", "mitsuba",
            "--spp", "16")
    whole = generate_store(tmp_path / "w.zarr", *args)  # one spatial block
    monkeypatch.setattr("pipeline.graphs.blocks.TASK_TEXELS", SMALL_TASKS)  # 2 x 2 blocks
    a = generate_store(tmp_path / "a.zarr", *args, "--scheduler", "threads")
    b = generate_store(tmp_path / "b.zarr", *args, "--scheduler", "synchronous")
    rw, ra, rb = (zarr.open_group(p, mode="r")["radiance"][:] for p in (whole, a, b))
    assert np.array_equal(ra, rb)
    assert np.isfinite(ra).all() and ra.max() > 0
    # the blocks' own noise differs from the whole's, but no more at the blocks' borders
    noise = np.abs(ra - rw).mean(axis=(0, 1, 4))
    border = np.r_[noise[15:17].ravel(), noise[:, 15:17].ravel()].mean()
    assert border < 1.5 * noise.mean(), (border, noise.mean())
    assert abs(ra.mean() / rw.mean() - 1) < 0.01


@pytest.mark.parametrize("extra, name", [(("--spp", "16"), "spp"), (("--bsdf", "conductor"),
                                          "bsdf"), (("--bounces", "1"), "bounces")])
def test_path_tracer_options_need_the_mitsuba_renderer(tmp_path, capsys, extra, name):
    code = main(["generate", str(tmp_path / "x.zarr"), "--material", "stone", "--size", "16",
                 *extra])
    assert code != 0
    assert f"--{name}" in capsys.readouterr().err
    assert not (tmp_path / "x.zarr").exists()


def test_the_shading_model_is_the_default_renderer():
    from pipeline.stages.generate import GenerateParams

    assert GenerateParams(out="x.zarr", material="stone", size=16).renderer == "shading"
    assert ShadingModel(relief=1.0).reference == 0.5


def test_spp_that_fills_no_grid_of_strata_is_refused_naming_the_nearest(tmp_path, capsys):
    from tasks.pathtrace import stratified_spp

    assert [stratified_spp(n) for n in (1, 4, 10, 12, 16, 17, 64)] == [1, 4, 12, 12, 16, 20, 64]
    code = main(["generate", str(tmp_path / "x.zarr"), "--material", "stone", "--size", "16",
                 "--renderer", "mitsuba", "--spp", "10"])
    assert code != 0 and "use 12" in capsys.readouterr().err
    assert not (tmp_path / "x.zarr").exists()


@pytest.mark.slow
def test_the_path_traced_store_resumes_after_kill_9_to_the_same_bits(llvm, tmp_path):
    from test_resume import _kill_and_resume

    def args(out):
        return ["generate", out, "--material", "stone", "--size", "128", "--sampling",
                "abtf:6,2", "--chunk", "32", "--seed", "3", "--renderer", "mitsuba", "--spp",
                "16"]

    _kill_and_resume(tmp_path, args, ("radiance", "height", "albedo", "roughness", "specular"),
                     mark="layers of", resumed_says="generate: resuming an interrupted run",
                     seed=2)


@pytest.mark.slow
def test_btf_bench_rendered_runs_end_to_end_and_reports_every_part(llvm, tmp_path, capsys,
                                                                     monkeypatch):
    import json

    from benchmarks.cli import main as bench

    monkeypatch.setenv("BTF_RATES", str(tmp_path / "rates.json"))  # not the user's rates
    out = tmp_path / "r.json"
    assert bench(["rendered", "--materials", "bumps", "--bsdf", "principled", "--size", "64",
                  "--throughput-size", "32", "--throughput-spp", "4", "--spp", "4",
                  "--noise-spp", "1,4", "--noise-size", "16", "--ranks", "2,8", "--rank", "8",
                  "--quilt-seeds", "1", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    for heading in ("Throughput", "Noise of the path tracer", "Compression", "Enlargement",
                    "Gap share over the seeds", "Quilting"):
        assert heading in text, heading
    result = json.loads(out.read_text())
    noise = result["noise"]["rows"]
    assert noise[1]["worst"] < noise[0]["worst"]  # 4 spp are less noisy than 1
    rows = result["benches"]
    assert [r["renderer"] for r in rows] == ["shading", "mitsuba, principled"]
    for r in rows:
        errors = [c["error"] for c in r["compression"]]
        assert errors[1] < errors[0]  # rank 8 is closer than rank 2
        assert r["material"] == "bumps" and set(r["enlarge"]) == {
            "top", "random", "top (--qp-metric plain)", "random (--qp-metric plain)"}
        for e in r["enlarge"].values():
            assert e["oracle"] <= e["error"] and e["oracle"] < e["lookup"]
    assert result["noise"]["material"] == "leather"  # procedural: the first, or leather
    assert "generate_path_samples_per_core_second" in json.loads(
        (tmp_path / "rates.json").read_text())

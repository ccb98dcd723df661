"""btf scene: exactly the directions, region, level and rank asked for, reading only that."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import zarr

from helpers import ROOT, generate_store, no_partial_outputs
from tasks.transform import Transform


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def _block_means(a: np.ndarray, f: int) -> np.ndarray:
    """Means of f x f blocks over the two axes before the last (float64)."""
    *lead, ny, nx, nc = a.shape
    return np.asarray(a, np.float64).reshape(*lead, ny // f, f, nx // f, f, nc).mean(
        axis=(-4, -2))


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    """A small full BTF, its compression, and quilted tile sets of both.

    6 x 6 directions in chunks of 4 lights (the last chunk part full): a tile set stores
    every (tile, view, light) as a chunk of its own, so its quilt and pyramid cost goes with
    the layers (16 x 36 here).
    """
    from pipeline.cli import main

    root = tmp_path_factory.mktemp("scene")
    m = generate_store(root / "m.zarr", "--material", "leather", "--size", "64", "--sampling",
                       "hemi:6", "--chunk", "16", "--dir-chunk", "4", "--seed", "3")
    assert main(["compress", str(m), str(root / "m_svd.zarr"), "--rank", "8", "-q"]) == 0
    assert main(["quilt", str(m), str(root / "q.zarr"), "--corners", "2", "--size", "48",
                 "-q"]) == 0
    assert main(["quilt", str(root / "m_svd.zarr"), str(root / "q_svd.zarr"), "--corners",
                 "2", "--size", "48", "-q"]) == 0
    return root


@pytest.fixture(scope="module")
def with_levels(stores, tmp_path_factory):
    """The small full BTF with two levels of detail (btf pyramid), made once."""
    from pipeline.cli import main

    p = tmp_path_factory.mktemp("levels") / "p.zarr"
    shutil.copytree(stores / "m.zarr", p)
    assert main(["pyramid", str(p), "--levels", "2", "-q"]) == 0
    return p


def _angles(store: Path, view: int, light: int) -> list[float]:
    g = zarr.open_group(store, mode="r")
    return [float(g["theta_light"][light]), float(g["phi_light"][light]),
            float(g["theta_view"][view]), float(g["phi_view"][view])]


def _radiance(path: Path) -> np.ndarray:
    return zarr.open_group(path, mode="r")["radiance"][...]


def test_measured_directions_are_the_layers_and_unmeasured_ones_their_weighted_sums(
        stores, tmp_path, btf):
    m = stores / "m.zarr"
    spec = _write(tmp_path / "s.yaml", f"""source: {m}
directions:
  - {_angles(m, 2, 5)}
  - [33, 40, 20, 100]
region: [8, 40, 16, 64]
""")
    result = btf("scene", spec, tmp_path / "o.zarr")
    assert result.code == 0, result.err
    out = zarr.open_group(tmp_path / "o.zarr", mode="r")
    level0 = _radiance(m)
    assert np.array_equal(out["radiance"][0], level0[2, 5, 8:40, 16:64])
    terms = out.attrs["terms"][1]
    assert len(terms) > 1 and sum(w for *_, w in terms) == pytest.approx(1.0)
    expected = sum(w * level0[v, li, 8:40, 16:64] for v, li, w in terms)
    assert np.allclose(out["radiance"][1], expected, rtol=1e-5, atol=1e-7)
    assert [float(out["theta_light"][1]), float(out["phi_view"][1])] == [33.0, 100.0]
    assert "scene: 2 direction(s)" in btf("inspect", tmp_path / "o.zarr").out


def test_compressed_scene_at_a_rank_equals_reconstruction(stores, tmp_path, btf):
    c = stores / "m_svd.zarr"
    spec = _write(tmp_path / "s.yaml", f"""source: {c}
directions: [{_angles(c, 4, 1)}, {_angles(c, 0, 5)}]
region: [16, 48, 0, 32]
rank: 5
""")
    assert btf("scene", spec, tmp_path / "o.zarr").code == 0
    assert btf("reconstruct", c, tmp_path / "r.zarr", "--rank", "5", "--region",
               "16:48,0:32", "-q").code == 0
    rec = _radiance(tmp_path / "r.zarr")
    got = _radiance(tmp_path / "o.zarr")
    for k, (v, li) in enumerate(((4, 1), (0, 5))):
        assert np.allclose(got[k], rec[v, li], rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("kind", ["radiance", "compressed"])
def test_levels_are_block_means_from_the_pyramid_or_on_the_fly(stores, tmp_path, btf, kind,
                                                               request):
    src = stores / ("m.zarr" if kind == "radiance" else "m_svd.zarr")
    level0 = _radiance(src) if kind == "radiance" else None
    if level0 is None:
        assert btf("reconstruct", src, tmp_path / "r.zarr", "-q").code == 0
        level0 = _radiance(tmp_path / "r.zarr")
    exact = _block_means(level0[:, :, 8:40, 0:64], 4)  # region [10, 37, 3, 64] snapped out
    text = "source: {}\ndirections: all\nregion: [10, 37, 3, 64]\nlevel: 2\n"
    result = btf("scene", _write(tmp_path / "a.yaml", text.format(src)), tmp_path / "fly.zarr")
    assert result.code == 0 and "no pyramid" in result.err and "on the fly" in result.err
    assert "level's texels [2, 10, 0, 16], which cover [8, 40, 0, 64] of level 0" in result.err
    fly = _radiance(tmp_path / "fly.zarr")
    assert fly.shape == exact.shape  # a radiance store of every layer: directions 'all'
    assert zarr.open_group(tmp_path / "fly.zarr").attrs["btf_kind"] == "btf"
    assert np.allclose(fly, exact, rtol=1e-5, atol=1e-7)  # linear means, exact
    if kind == "radiance":  # the module's copy of it with levels (btf pyramid --levels 2)
        with_levels = request.getfixturevalue("with_levels")
    else:
        with_levels = tmp_path / "p.zarr"
        shutil.copytree(src, with_levels)
        assert btf("pyramid", with_levels, "--levels", "2", "-q").code == 0
    result = btf("scene", _write(tmp_path / "b.yaml", text.format(with_levels)),
                 tmp_path / "stored.zarr")
    assert result.code == 0 and "no pyramid" not in result.err
    assert "pyramid/2/" in result.err  # read from the stored level
    stored = _radiance(tmp_path / "stored.zarr")
    if kind == "radiance":
        assert np.allclose(stored, exact, rtol=1e-5, atol=1e-7)
    else:  # the stored level: exp(U S V_2^T) - eps of the pyramid's V_2 (a projection on U)
        from tasks.svd import reconstruct_layers

        g = zarr.open_group(with_levels, mode="r")
        v2 = g["pyramid/2/V"][2:10, 0:16]
        rebuilt = reconstruct_layers(g["U"][...], g["S"][...], v2,
                                     transform=Transform.from_attrs(g.attrs["transform"]))
        assert np.allclose(stored, rebuilt, rtol=1e-5, atol=1e-6)
        rel = np.sqrt(np.mean((stored - exact) ** 2) / np.mean(exact**2))
        assert rel < 0.15  # the projection's own error at rank 8 (measured: 6.8%)


def _count_reads(monkeypatch) -> list[str]:
    """Record the key of every chunk or metadata document zarr reads from local stores."""
    from zarr.storage import LocalStore

    from pipeline import chunk_io

    keys: list[str] = []
    original, direct = LocalStore.get, chunk_io._get

    async def get(self, key, *args, **kwargs):
        keys.append(f"{Path(str(self.root)).name}/{key}")
        return await original(self, key, *args, **kwargs)

    def get_here(store, key):  # chunks read in the task's thread (pipeline.chunk_io)
        keys.append(f"{Path(str(store.root)).name}/{key}")
        return direct(store, key)

    monkeypatch.setattr(LocalStore, "get", get)
    monkeypatch.setattr(chunk_io, "_get", get_here)
    return keys


def _chunk_reads(keys: list[str], variable: str) -> set[str]:
    return {k for k in keys if f"/{variable}/c/" in k}


@pytest.mark.parametrize("size", [64, 96])  # 4 x 4 and 6 x 6 chunks of texels
def test_reads_are_counted_and_do_not_grow_with_the_store(tmp_path, btf, monkeypatch, size):
    """One direction of a 16 x 16 region: the same chunks, whatever the store's size."""
    from pipeline.cli import main

    # 4 x 4 directions: 8 direction chunks of radiance and of U, one of them read
    m = generate_store(tmp_path / "m.zarr", "--material", "wood", "--size", str(size),
                       "--sampling", "hemi:4", "--chunk", "16", "--dir-chunk", "2")
    assert main(["compress", str(m), str(tmp_path / "c.zarr"), "--rank", "4", "-q"]) == 0
    for source, variables in ((m, {"radiance": 1}), (tmp_path / "c.zarr", {"V": 1, "U": 1})):
        spec = _write(tmp_path / "s.yaml", f"source: {source}\ndirections: "
                                           f"[{_angles(source, 1, 3)}]\nregion: [16, 32, 32, 48]\n")
        keys = _count_reads(monkeypatch)
        result = btf("scene", spec, tmp_path / "o.zarr", "--scheduler", "synchronous")
        monkeypatch.undo()
        assert result.code == 0, result.err
        recorded = zarr.open_group(tmp_path / "o.zarr", mode="r").attrs["reads"]
        for variable, count in variables.items():
            read = _chunk_reads(keys, variable)
            assert len(read) == count, (variable, sorted(read))
            assert recorded[variable][0] == count
        if source == m:  # the chunk of view 1, lights 2-3, texels 16-32 x 32-48
            assert _chunk_reads(keys, "radiance") == {"m.zarr/radiance/c/1/1/1/2/0"}
        shutil.rmtree(tmp_path / "o.zarr")


def test_tile_set_scenes_equal_btf_render_and_read_only_visible_tiles(stores, tmp_path, btf,
                                                                      monkeypatch):
    for name in ("q.zarr", "q_svd.zarr"):
        ts = stores / name
        assert btf("render", ts, tmp_path / f"r_{name}", "--light", "4", "--view", "2",
                   "--size", "40,52", "--origin=-9,30", "-q").code == 0
        spec = _write(tmp_path / "s.yaml", f"source: {ts}\ndirections: [{_angles(ts, 2, 4)}]"
                                           "\nsize: [40, 52]\norigin: [-9, 30]\nchunk: 16\n")
        keys = _count_reads(monkeypatch)
        result = btf("scene", spec, tmp_path / f"o_{name}", "--scheduler", "synchronous")
        monkeypatch.undo()
        assert result.code == 0, result.err
        assert np.array_equal(_radiance(tmp_path / f"o_{name}")[0],
                              _radiance(tmp_path / f"r_{name}"))
        # a compressed set's tiles are their prescriptions applied to the sample's V (read
        # whole): only the visible tiles' prescriptions are read
        variable = "prescription_index" if "svd" in name else "radiance"
        read = _chunk_reads(keys, variable)
        recorded = zarr.open_group(tmp_path / f"o_{name}", mode="r").attrs["reads"]
        assert len(read) == recorded[variable][0] < 16  # of 16 tiles (x one layer)
        # a region inside one cell of the lattice: one tile
        small = _write(tmp_path / "t.yaml", f"source: {ts}\ndirections: "
                                            f"[{_angles(ts, 2, 4)}]\nsize: [5, 5]\n")
        keys = _count_reads(monkeypatch)
        assert btf("scene", small, tmp_path / f"t_{name}", "-q").code == 0
        monkeypatch.undo()
        assert len(_chunk_reads(keys, variable)) == 1


@pytest.mark.slow  # 5 s: kept out of the default run (4 min), run by .ci/run
def test_tile_set_levels_come_from_the_tiles_pyramid(stores, tmp_path, btf, monkeypatch):
    """Level 2 of a quilted surface: laid from the tiles' level 2 once ``btf pyramid`` made
    it, equal to the on-the-fly block means (exactly for radiance tiles; within the
    projection's error for eigentextures), reading no level-0 tile."""
    text = ("source: {}\ndirections: [{}, [40, 30, 20, 200]]\nsize: [60, 84]\n"
            "origin: [-12, 36]\nlevel: 2\nchunk: 32\n")
    for name, variable in (("q.zarr", "radiance"), ("q_svd.zarr", "V")):
        ts = stores / name
        fly = btf("scene", _write(tmp_path / "a.yaml", text.format(ts, _angles(ts, 2, 4))),
                  tmp_path / f"fly_{name}")
        assert fly.code == 0 and "on the fly" in fly.err, fly.err
        assert "which cover" not in fly.err  # on whole 4 x 4 blocks: nothing widened
        levels = tmp_path / f"p_{name}"
        shutil.copytree(ts, levels)
        if variable == "V":  # prescribed tiles: no pyramid, the level is block means of 0
            refused = btf("pyramid", levels, "--levels", "2", "-q")
            assert refused.code == 1 and "computed where they are read" in refused.err
            zero = btf("scene", _write(tmp_path / "z.yaml", text.format(
                ts, _angles(ts, 2, 4)).replace("level: 2", "level: 0")), tmp_path / "zero.zarr")
            assert zero.code == 0, zero.err
            full = _radiance(tmp_path / "zero.zarr").astype(np.float64)
            means = full.reshape(2, 15, 4, 21, 4, 3).mean(axis=(2, 4))
            assert np.allclose(_radiance(tmp_path / f"fly_{name}"), means, rtol=1e-5,
                               atol=1e-7)
            continue
        assert btf("pyramid", levels, "--levels", "2", "-q").code == 0
        keys = _count_reads(monkeypatch)
        stored = btf("scene", _write(tmp_path / "b.yaml", text.format(levels,
                                                                      _angles(ts, 2, 4))),
                     tmp_path / f"stored_{name}", "--scheduler", "synchronous")
        monkeypatch.undo()
        assert stored.code == 0 and f"pyramid/2/{variable}" in stored.err, stored.err
        assert "on the fly" not in stored.err
        assert _chunk_reads(keys, f"pyramid/2/{variable}")
        assert not {k for k in keys if k.startswith(f"p_{name}/{variable}/c/")}
        a, b = _radiance(tmp_path / f"fly_{name}"), _radiance(tmp_path / f"stored_{name}")
        assert a.shape == b.shape == (2, 15, 21, 3)
        if variable == "radiance":
            assert np.allclose(a, b, rtol=1e-5, atol=1e-7)
        else:  # a projection on U (tests/test_pyramid.py), here at rank 8
            rel = np.sqrt(np.mean((a - b) ** 2) / np.mean(a**2))
            assert 0 < rel < 0.15, rel
    beyond = btf("scene", _write(tmp_path / "c.yaml", text.format(
        tmp_path / "p_q.zarr", _angles(stores / "q.zarr", 2, 4)).replace("level: 2",
                                                                         "level: 3")),
        tmp_path / "beyond.zarr")
    assert beyond.code == 1 and "level 3 is beyond the pyramid" in beyond.err


@pytest.mark.slow  # 5 s: kept out of the default run (4 min), run by .ci/run
def test_roller_tile_sets_equal_btf_render(tmp_path, btf):
    """Several roller tiles: picked per cell of a sheared lattice (every tile is read)."""
    src = generate_store(tmp_path / "f.zarr", "--material", "fabric", "--size", "96",
                         "--sampling", "hemi:4", "--seed", "2")
    assert btf("roller", src, tmp_path / "ro.zarr", "--tiles", "3", "-q").code == 0
    assert btf("render", tmp_path / "ro.zarr", tmp_path / "r.zarr", "--light", "2", "--view",
               "1", "--size", "70,90", "--origin=5,-20", "-q").code == 0
    spec = _write(tmp_path / "s.yaml", f"source: {tmp_path / 'ro.zarr'}\ndirections: "
                                       f"[{_angles(tmp_path / 'ro.zarr', 1, 2)}]\n"
                                       "size: [70, 90]\norigin: [5, -20]\nchunk: 32\n")
    assert btf("scene", spec, tmp_path / "s.zarr", "-q").code == 0
    assert np.array_equal(_radiance(tmp_path / "s.zarr")[0], _radiance(tmp_path / "r.zarr"))
    refused = btf("pyramid", tmp_path / "ro.zarr", "-q")  # tiles on a sheared lattice
    assert refused.code == 1 and "a roller tile set" in refused.err
    level = btf("scene", _write(tmp_path / "l.yaml", spec.read_text() + "level: 1\n"),
                tmp_path / "l.zarr")
    assert level.code == 0 and "roller tile set has no pyramid" in level.err
    assert "level's texels [2, 38, -10, 35], which cover [4, 76, -20, 70]" in level.err
    # --for-scene: the tiles applied only to the layers the scene reads, the same scene
    only = _write(tmp_path / "only.yaml", spec.read_text().replace("ro.zarr", "only.zarr"))
    made = btf("roller", src, tmp_path / "only.zarr", "--tiles", "3", "--for-scene", only)
    assert made.code == 0 and "only to the 1 of 16 layers" in made.err, made.err
    ro = zarr.open_group(tmp_path / "only.zarr", mode="r")
    assert ro.attrs["computed_for_scene"]["layers"] == [[1, 2]]
    assert np.isnan(ro["radiance"][0, 0, 0, 0, 0, 0])  # another layer: never written
    assert btf("scene", only, tmp_path / "o.zarr", "-q").code == 0
    assert np.array_equal(_radiance(tmp_path / "o.zarr"), _radiance(tmp_path / "s.zarr"))
    other = _write(tmp_path / "other.yaml", only.read_text().replace(
        str(_angles(tmp_path / "ro.zarr", 1, 2)), str(_angles(tmp_path / "ro.zarr", 0, 0))))
    refused = btf("scene", other, tmp_path / "x.zarr")
    assert refused.code == 1 and "was not computed" in refused.err


def test_surface_source_and_image_formats(stores, tmp_path, btf):
    from pipeline.images import read_image

    assert btf("render", stores / "q.zarr", tmp_path / "surf.zarr", "--light", "1", "--size",
               "32,48", "-q").code == 0
    surface = _radiance(tmp_path / "surf.zarr")
    for fmt in ("exr", "png"):
        spec = _write(tmp_path / f"{fmt}.yaml", f"source: {tmp_path / 'surf.zarr'}\n"
                      "directions: [[10, 0, 0, 0], [60, 90, 45, 0]]\nlevel: 1\n"
                      f"format: {fmt}\n")
        assert btf("scene", spec, tmp_path / fmt).code == 0
        again = btf("scene", spec, tmp_path / fmt)  # refused before anything is computed
        assert again.code == 1 and "already exists; pass --overwrite" in again.err
        assert "scene: 2 direction(s)" not in again.err
        files = sorted(p.name for p in (tmp_path / fmt).iterdir())
        assert files == ["manifest.csv", f"tl10_pl0_tv0_pv0.{fmt}",
                         f"tl60_pl90_tv45_pv0.{fmt}"]
    pixels, _ = read_image(tmp_path / "exr" / "tl10_pl0_tv0_pv0.exr")
    # a surface holds one layer: every direction is that layer (here at level 1)
    assert np.allclose(pixels, _block_means(surface, 2), rtol=1e-6)


@pytest.mark.parametrize("text, where", [
    ("source: {m}\ndirections: all\nregoin: [0, 4, 0, 4]\n", ":3: regoin: unknown key "
                                                             "(did you mean 'region'?)"),
    ("source: {m}\ndirections:\n  - [0, 0, 0, 0]\n  - [95, 0, 10, 0]\n",
     ":4: directions[1]: theta_light 95 is below the horizon"),
    ("source: {m}\ndirections: all\nregion: [0, 80, 0, 8]\n",
     ":3: region: [0, 80, 0, 8] reaches beyond the source's 64 x 64 texels"),
    ("source: {m}\ndirections: all\nlevel: 7\n", ":3: level: level 7 would shrink"),
    ("source: {p}\ndirections: all\nlevel: 3\n", ":3: level: level 3 is beyond the pyramid"),
    ("source: {m}\ndirections: all\nrank: 3\n", ":3: rank: applies to compressed sources"),
    ("source: {c}\ndirections: all\nrank: 30\n", ":3: rank: 30 is above the 8 components"),
    ("source: {m}\ndirections: all\nsize: [4, 4]\n", ":3: size: applies to tile sets only"),
    ("source: {q}\ndirections: all\nregion: [0, 4, 0, 4]\n", ":3: region: a tile set covers"),
    ("source: {q}\ndirections: all\n", ":1: size: is required for a tile set"),
    ("source: nowhere.zarr\ndirections: all\n", ":1: source: 'nowhere.zarr' does not exist"),
    ("source: {m}\ndirections: [[0, 0, 0]]\n", ":2: directions[0]: expected [theta_light"),
    ("source: {m}\ndirections: [[0, 0, 0, 0], [0, 360, 0, 0]]\n",
     ":2: directions[1]: repeats directions[0]"),
    ("source: {m}\ndirections: all\ninterpolation: cubic\n", ":3: interpolation: expected one"),
    ("directions: all\n", ":1: source: is required"),
])
def test_bad_specs_name_the_key_and_line_and_write_nothing(stores, with_levels, tmp_path, btf,
                                                           text, where):
    p = with_levels
    spec = _write(tmp_path / "bad.yaml", text.format(m=stores / "m.zarr", p=p,
                                                     c=stores / "m_svd.zarr",
                                                     q=stores / "q.zarr"))
    result = btf("scene", spec, tmp_path / "o.zarr")
    assert result.code == 1
    assert f"{spec}{where}" in result.err, result.err
    assert result.err.count("error") == 1
    assert no_partial_outputs(tmp_path / "o.zarr")


@pytest.mark.slow  # stores of up to 256^2 texels, as the specs' headers make them
def test_example_scenes_run(tmp_path, btf, monkeypatch):
    """Every spec in configs/scenes/ runs on the stores its header says how to make."""
    from pipeline.cli import main
    from pipeline.scene_spec import load

    examples = sorted((ROOT / "configs" / "scenes").glob("*.yaml"))
    assert len(examples) >= 3
    monkeypatch.chdir(tmp_path)
    for example in examples:
        setup = [line[len("# setup: "):] for line in example.read_text().splitlines()
                 if line.startswith("# setup: ")]
        assert setup, f"{example.name} has no '# setup: btf ...' lines"
        for command in setup:
            words = command.split()
            assert words[0] == "btf"
            assert main([*words[1:], "-q"]) == 0, command
        spec = load(example)
        out = tmp_path / (example.stem + (".zarr" if spec.format == "zarr" else ""))
        result = btf("scene", example, out, "-q")
        assert result.code == 0, (example.name, result.err)
        assert out.exists()


def test_a_run_config_scene_restricts_reconstruct_and_quilt_to_what_it_reads(tmp_path, btf,
                                                                             monkeypatch):
    monkeypatch.chdir(tmp_path)
    stages = """stages:
  - generate: {out: m.zarr, material: leather, size: 64, sampling: "hemi:9", chunk: 16,
               dir_chunk: 3, seed: 4}
  - compress: {store: m.zarr, out: c.zarr, rank: 8}
  - reconstruct: {store: c.zarr, out: r.zarr, chunk: 16, dir_chunk: 3}
  - quilt: {store: m.zarr, out: q.zarr, size: [48, 48], corners: 1}
"""
    _write(tmp_path / "r.yaml", stages + """scene:
  out: s.zarr
  source: r.zarr
  directions: [[20, 10, 30, 40], [0, 0, 0, 0]]
  region: [0, 32, 16, 48]
""")
    check = btf("run", "r.yaml", "--check")
    assert check.code == 0, check.err
    assert "--for-scene r.yaml" in check.out
    # counted before anything exists, from the planned shapes and generate's sampling
    planned = re.search(r"reconstruct: restricted to the scene: (\d+) of 432 chunks", check.out)
    assert "compress: all 43 chunks: the SVD needs every layer and texel" in check.out
    assert "generate: all 432 chunks: a measurement" in check.out
    assert btf("run", "r.yaml", "-q").code == 0
    again = btf("run", "r.yaml", "--check")
    counted = re.search(r"reconstruct: restricted to the scene: (\d+) of 432 chunks", again.out)
    r = zarr.open_group("r.zarr", mode="r")
    only = r.attrs["computed_for_scene"]
    assert "computed only for the scene r.yaml: 9 of 81 layers, texels" in btf(
        "inspect", "r.zarr").out
    assert len(only["layers"]) == 9 and only["of_layers"] == 81  # (0, 0) among the 9
    written = np.isfinite(r["radiance"][..., 0, 16, 0])  # (view, light) written at all
    # 64^2 texels are one task block: whole light chunks (3 lights) of the needed layers
    blocks = {(v, li // 3) for v, li in zip(*np.nonzero(written), strict=True)}
    assert int(counted.group(1)) == int(planned.group(1)) == 16 * len(blocks) < 432 // 2
    assert all(written[v, li] for v, li in only["layers"])
    # the scene equals the same scene on a full reconstruction
    assert btf("reconstruct", "c.zarr", "full.zarr", "-q").code == 0
    spec = _write(tmp_path / "direct.yaml", "source: full.zarr\ndirections: [[20, 10, 30, 40], "
                                            "[0, 0, 0, 0]]\nregion: [0, 32, 16, 48]\n")
    assert btf("scene", spec, "direct.zarr", "-q").code == 0
    assert np.array_equal(_radiance(tmp_path / "s.zarr"), _radiance(tmp_path / "direct.zarr"))
    # a scene that needs a layer the restricted store did not compute is refused
    other = _write(tmp_path / "o.yaml", "source: r.zarr\ndirections: [[70, 200, 60, 90]]\n")
    refused = btf("scene", other, "o.zarr")
    assert refused.code == 1 and "was not computed" in refused.err
    other.write_text("source: r.zarr\ndirections: [[0, 0, 0, 0]]\nregion: [0, 64, 0, 64]\n")
    refused = btf("scene", other, "o.zarr")
    assert refused.code == 1 and "was computed only for the texels" in refused.err
    # the whole tile set: r.yaml's quilt stage (no scene read it), kept from the run below
    shutil.copytree("q.zarr", "qfull.zarr")
    assert "computed_for_scene" not in zarr.open_group("qfull.zarr", mode="r").attrs
    # quilting a radiance store for a scene applies the plan to the scene's layers only (no
    # reconstruct stage: read by no scene here, it would be made again whole)
    reconstruct = "  - reconstruct: {store: c.zarr, out: r.zarr, chunk: 16, dir_chunk: 3}\n"
    assert reconstruct in stages
    _write(tmp_path / "q.yaml", stages.replace(reconstruct, "") + """scene:
  out: t.zarr
  source: q.zarr
  directions: [[20, 10, 30, 40]]
  size: [40, 60]
""")
    assert btf("run", "q.yaml", "-q").code == 0
    q = zarr.open_group("q.zarr", mode="r")
    assert len(q.attrs["computed_for_scene"]["layers"]) == 9
    spec = _write(tmp_path / "qd.yaml", "source: qfull.zarr\ndirections: [[20, 10, 30, 40]]\n"
                                        "size: [40, 60]\n")
    assert btf("scene", spec, "qd.zarr", "-q").code == 0
    assert np.array_equal(_radiance(tmp_path / "t.zarr"), _radiance(tmp_path / "qd.zarr"))
    refused = btf("render", "q.zarr", "x.exr", "--light", "8", "--view", "8", "--size", "8")
    assert refused.code == 1 and "was not computed" in refused.err
    # the roller restricts itself the same way (tests its output in test_roller_tile_sets_...)
    _write(tmp_path / "ro.yaml", stages + """  - roller: {store: m.zarr, out: ro.zarr}
scene:
  out: u.zarr
  source: ro.zarr
  directions: [[20, 10, 30, 40]]
  size: [40, 60]
""")
    check = btf("run", "ro.yaml", "--check")
    assert check.code == 0, check.err
    assert re.search(r"roller: restricted to the scene: \d+ of 27 blocks of layers per tile "
                     r"\(9 of 81 layers\)", check.out), check.out


def test_a_run_config_scene_section_is_validated_with_lines(tmp_path, btf):
    cfg = _write(tmp_path / "bad.yaml", f"""stages:
  - inspect: {{store: {stores_hint(tmp_path)}}}
scene:
  out: s.zarr
  source: nowhere.zarr
  directions: all
""")
    result = btf("run", cfg, "--check")
    assert result.code == 1
    assert f"{cfg}:5: scene.source: 'nowhere.zarr' does not exist" in result.err
    cfg.write_text(cfg.read_text().replace("directions: all", "directions: [[0, 0, 100, 0]]")
                   .replace("nowhere.zarr", str(tmp_path / "m.zarr")))
    result = btf("run", cfg, "--check")
    assert result.code == 1
    assert f"{cfg}:6: scene.directions[0]: theta_view 100 is below the horizon" in result.err


def stores_hint(tmp_path: Path) -> Path:
    """A small generated store the config's stage can name."""
    return generate_store(tmp_path / "m.zarr", "--material", "stone", "--size", "16",
                          "--sampling", "abtf:2,1")


def test_a_store_another_stage_reads_is_not_restricted_to_the_scene(tmp_path, btf,
                                                                    monkeypatch):
    monkeypatch.chdir(tmp_path)
    _write(tmp_path / "r.yaml", """stages:
  - generate: {out: m.zarr, material: wood, size: 32, sampling: "hemi:4"}
  - compress: {store: m.zarr, out: c.zarr, rank: 4}
  - reconstruct: {store: c.zarr, out: r.zarr}
  - compress: {store: r.zarr, out: c2.zarr, rank: 4}
scene:
  out: s.zarr
  source: r.zarr
  directions: [[10, 0, 0, 0]]
""")
    check = btf("run", "r.yaml", "--check")
    assert check.code == 0, check.err
    assert "--for-scene" not in check.out
    assert "reconstruct: all 4 chunks: a later stage reads its output too" in check.out
    (tmp_path / "r.yaml").write_text((tmp_path / "r.yaml").read_text().replace(
        "out: s.zarr", "out: s_images"))
    bad = btf("run", "r.yaml", "--check")
    assert bad.code == 1 and "r.yaml:7: scene.out: 's_images' does not suit format zarr" in bad.err


@pytest.mark.parametrize("chunks", [(12, 12, 3, 16), (1, 4, 3, 16), (5, 5, 3, 16)])
def test_u_rows_are_the_rows_asked_for_and_their_chunks_are_counted(chunks):
    from pipeline.graphs.scene import read_u_rows

    rng = np.random.default_rng(0)
    values = rng.standard_normal((12, 12, 3, 16)).astype(np.float32)
    u = zarr.create_array(zarr.storage.MemoryStore(), shape=values.shape, chunks=chunks,
                          dtype="float32")
    u[...] = values
    cv, dl = chunks[:2]
    for layers in ([(0, 1), (5, 7), (11, 3), (5, 6)],  # scattered chunks
                   [(v, li) for v in range(12) for li in range(12)],  # every chunk: one call
                   [(2, 2)]):
        rows, read = read_u_rows(u, layers, 10)
        assert np.array_equal(rows, np.stack([values[v, li, :, :10] for v, li in layers]))
        assert read == len({(v // cv, li // dl) for v, li in layers})


def test_on_the_fly_levels_keep_direction_chunks_of_a_store_chunk():
    """A thin on-the-fly block (chunk / 2^n texels) must not hold the directions of a whole
    output task: its chunks hold as many directions as a scene store chunk does."""
    import dask.array as da
    from scipy.sparse import identity

    from pipeline.graphs.scene import Request, radiance_graph
    from pipeline.stores.scene import directions_per_chunk

    data = da.zeros((1, 64, 4096, 4096, 3), dtype=np.float32, chunks=(1, 1, 512, 512, 3))
    request = Request(layers=[(0, li) for li in range(64)], weights=identity(64, format="csr"),
                      window=(0, 512, 0, 512), level=3, stored_level=False, chunk=256)
    out = radiance_graph(data, request)
    assert out.shape == (64, 512, 512, 3)
    assert out.chunks[1][0] == 32  # 256 level-0 texels a side
    assert max(out.chunks[0]) == directions_per_chunk(64, (256, 256), 3) == 21

"""btf run: configs are validated before anything runs, then run in order."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

CONFIGS = sorted((Path(__file__).resolve().parents[1] / "configs").glob("*.yaml"))
SMALL = ("--set", "generate.size=64")  # every shipped config must work at this size


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    return tmp_path


# In the slow set: terabyte.yaml (at 64^2 texels still 151 x 151 directions, 1.1 GB, 70-85 s
# with its tiles at 120^2 rather than 504^2; its plan is checked in the default set,
# tests/test_plan.py) and cluster.yaml (run on S3 and on a cluster, also in the slow set:
# tests/test_s3.py::test_the_cluster_config_on_s3_...)
SLOW_CONFIGS = ("terabyte.yaml", "cluster.yaml")
SMALLER = {"terabyte.yaml": ("--set", "quilt.size=[120, 120]")}  # 504^2 tiles: 71 s more


@pytest.mark.parametrize("config", [pytest.param(c, marks=pytest.mark.slow)
                                    if c.name in SLOW_CONFIGS else c for c in CONFIGS],
                         ids=[c.name for c in CONFIGS])
def test_every_shipped_config_runs(btf, workdir, config, request):
    if config.name == "cluster.yaml":  # its stores are in object storage: a real S3 server
        from pipeline import storage

        s3 = request.getfixturevalue("s3")
        result = btf("run", config, *SMALL, "--quiet")
        assert result.code == 0, result.err
        assert "report.html" in storage.children(s3.url("cluster"))
        assert not list(workdir.iterdir())  # nothing local: the report is in the bucket too
        return
    if config.name == "demo.yaml":  # its crop region needs the size: test_demo_* runs it
        assert "\n  - report:\n" in config.read_text()
        return
    result = btf("run", config, *SMALL, *SMALLER.get(config.name, ()), "--quiet")
    assert result.code == 0, result.err
    assert list(workdir.rglob("*.zarr")), "a config is expected to make at least one store"


def test_demo_runs_the_mission_writes_its_report_and_skips_what_is_up_to_date(btf, workdir):
    from helpers import small_demo

    demo = small_demo(workdir, 64)
    first = btf("run", demo)
    assert first.code == 0, first.err
    out = workdir / "out" / "demo"
    for name in ("wood.zarr", "sample.zarr", "photo.zarr", "sample_svd.zarr", "enlarged.zarr",
                 "tiles.zarr", "surface.png", "report.html", "view.html"):
        assert (out / name).exists(), name
    assert len(list((out / "scene").glob("*.png"))) == 3
    page = (out / "report.html").read_text()
    for text in ("The run", "Compression: ", "Enlargement: ", "Tile set: ", "Pictures",
                 "btf enlarge out/demo/sample_svd.zarr out/demo/photo.zarr", "Relight it",
                 '<a href="view.html">'):
        assert text in page, text
    again = btf("run", demo)
    assert again.code == 0 and again.err.count("up to date, skipped") == 6, again.err
    # the page still gives what the skipped stages cost when they ran
    assert (out / "report.html").read_text().count("time of the run that made it") == 6


def _write(workdir, text):
    path = workdir / "run.yaml"
    path.write_text(text)
    return path


GOOD_GENERATE = """\
stages:
  - generate:
      out: a.zarr
      material: tiles
      size: 32
      sampling: "abtf:2,2"
"""


@pytest.mark.parametrize(("text", "message"), [
    (GOOD_GENERATE.replace("size: 32", "sise: 32"),
     "run.yaml:5: stages[0].generate.sise: unknown key (did you mean 'size'?)"),
    (GOOD_GENERATE.replace("size: 32", "size: big"),
     "run.yaml:5: stages[0].generate.size: expected an integer, got 'big'"),
    (GOOD_GENERATE.replace("size: 32", "size: '32'"),
     "run.yaml:5: stages[0].generate.size: expected an integer, got '32'"),
    (GOOD_GENERATE.replace("material: tiles", "material: marble"),
     "run.yaml:4: stages[0].generate.material: 'marble' is not one of"),
    (GOOD_GENERATE.replace("      out: a.zarr\n", ""),
     "run.yaml:2: stages[0].generate.out: is required"),
    (GOOD_GENERATE + "  - inspect:\n      store: b.zarr\n",
     "run.yaml:8: stages[1].inspect.store: 'b.zarr' does not exist and no earlier stage makes it"),
    ("stages:\n  - inspect:\n      store: a.zarr\n" + GOOD_GENERATE.split("\n", 1)[1],
     "run.yaml:3: stages[0].inspect.store: 'a.zarr' does not exist"),
    (GOOD_GENERATE + "  - paint:\n      store: a.zarr\n", "run.yaml:7: stages[1]: unknown stage"),
    (GOOD_GENERATE + "colour: blue\n", "run.yaml:7: colour: unknown key"),
    (GOOD_GENERATE + "scheduler: gpu\n", "run.yaml:7: scheduler: unknown scheduler 'gpu'"),
    (GOOD_GENERATE.replace("size: 32", "size: 32\n      size: 64"), "duplicate key 'size'"),
    ("stages: []\n", "run.yaml:1: stages: expected a non-empty list"),
    ("just text\n", "run.yaml:1: config: expected a mapping"),
    ("stages:\n  - generate: [1, 2]\n", "run.yaml:2: stages[0].generate: expected a mapping"),
    ("stages: {\n", "not valid YAML"),
    (GOOD_GENERATE + "  - preview:\n      store: a.zarr\n      out: a.zarr\n",
     "run.yaml:9: stages[1].preview.out: 'a.zarr' is also an input of this stage"),
])
def test_config_errors_name_the_key_and_line_and_nothing_runs(btf, workdir, text, message):
    result = btf("run", _write(workdir, text))
    assert result.code == 1
    assert message in result.err, result.err
    assert not (workdir / "a.zarr").exists()


def test_unsafe_yaml_tags_are_refused(btf, workdir):
    text = "stages:\n  - inspect:\n      store: !!python/object/apply:os.system ['true']\n"
    result = btf("run", _write(workdir, text))
    assert result.code == 1 and "not valid YAML" in result.err


def test_check_prints_the_commands_without_running(btf, workdir):
    result = btf("run", _write(workdir, GOOD_GENERATE), "--check")
    assert result.code == 0
    assert "btf generate a.zarr --material tiles --size 32 --sampling abtf:2,2" in result.out
    assert not (workdir / "a.zarr").exists()


@pytest.mark.parametrize(("override", "message"), [
    ("generate.size", "expected STAGE.KEY=VALUE"), ("paint.size=3", "unknown stage 'paint'"),
    ("export.light=1", "has no 'export' stage"),
])
def test_bad_overrides_are_refused(btf, workdir, override, message):
    result = btf("run", _write(workdir, GOOD_GENERATE), "--set", override)
    assert result.code == 1 and message in result.err


def test_command_line_scheduler_overrides_the_config(btf, workdir):
    path = _write(workdir, GOOD_GENERATE + "scheduler: processes\n")
    result = btf("run", path, "--check", "--scheduler", "synchronous")
    assert "on synchronous" in result.out
    assert "on processes" in btf("run", path, "--check").out


def test_relative_paths_are_relative_to_the_working_directory(btf, workdir):
    sub = workdir / "configs"
    sub.mkdir()
    shutil.copy(_write(workdir, GOOD_GENERATE), sub / "run.yaml")
    assert btf("run", sub / "run.yaml", "--quiet").code == 0
    assert (workdir / "a.zarr").is_dir() and not (sub / "a.zarr").exists()


def test_a_run_never_replaces_a_folder_btf_did_not_write(btf, workdir):
    (workdir / "notes").mkdir()
    (workdir / "notes" / "todo.txt").write_text("keep me")
    text = GOOD_GENERATE + "  - export:\n      store: a.zarr\n      out_dir: notes\n"
    result = btf("run", _write(workdir, text), "--quiet")
    assert result.code == 1 and "refusing to replace a folder that btf did not write" in result.err
    assert (workdir / "notes" / "todo.txt").read_text() == "keep me"


def test_a_changed_input_photo_is_not_up_to_date(btf, workdir):
    from pipeline.images import write_png

    rng = np.random.default_rng(0)
    write_png(workdir / "photo.png", rng.integers(0, 255, (24, 24, 3), dtype=np.uint8))
    text = "stages:\n  - generate:\n      out: p.zarr\n      albedo: photo.png\n"
    path = _write(workdir, text + "      sampling: hemi:2\n")
    assert btf("run", path).code == 0
    assert "up to date" in btf("run", path).err
    write_png(workdir / "photo.png", rng.integers(0, 255, (24, 24, 3), dtype=np.uint8))
    again = btf("run", path)
    assert again.code == 0 and "up to date" not in again.err

"""The command line: help for every option, scheduler choice, quiet mode."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import dask
import pytest

from pipeline.params import key_of
from pipeline.stages import STAGES


@pytest.mark.parametrize("name", [*STAGES, "run"])
def test_every_subcommand_explains_every_option(btf, name):
    result = btf(name, "--help")
    assert result.code == 0
    for flag in ("--scheduler", "--workers", "--quiet"):
        assert flag in result.out
    if name in STAGES:
        for field in dataclasses.fields(STAGES[name].params):
            shown = ((field.metadata["metavar"] or field.name.upper())
                     if field.metadata["positional"] else "--" + key_of(field).replace("_", "-"))
            assert shown in result.out, shown
        assert STAGES[name].description[:40] in " ".join(result.out.split())


def test_top_level_help_lists_the_commands(btf):
    result = btf("--help")
    assert result.code == 0
    for name in [*STAGES, "run"]:
        assert name in result.out


def test_main_returns_the_status_of_help_and_usage_errors(capsys):
    """In-process callers get a status back, as the console script's exit code."""
    from pipeline.cli import main

    assert main(["--help"]) == 0 and "usage: btf" in capsys.readouterr().out
    assert main(["bench", "--help"]) == 0 and "usage: btf bench" in capsys.readouterr().out
    assert main(["generate"]) == 2 and "required: OUT" in capsys.readouterr().err
    assert main(["no-such-command"]) == 2


def test_a_stage_s_command_imports_no_other_stage_and_a_local_run_no_distributed(tmp_path):
    """Start-up: ``btf generate`` imports its own stage's module alone, and computing on a
    local scheduler does not import dask.distributed (dask does, given a scheduler's name).
    Neither it nor ``btf inspect``, ``crop``, ``compress``, ``reconstruct`` or ``export`` (EXR)
    imports xarray or pandas (0.6-0.7 s), which dask.array would import itself
    (pipeline._imports).
    """
    g, c, k, r = (str(tmp_path / f"{name}.zarr") for name in "gckr")
    e = str(tmp_path / "exr")
    code = ("import sys; from pipeline.cli import main; "
            f"status = main(['generate', {g!r}, '--material', 'wood', "
            "'--size', '16', '--sampling', 'abtf:2,1', '--quiet']); "
            "print(status, sorted(m for m in sys.modules if m.startswith('pipeline.stages.')), "
            "'distributed' in sys.modules, 'xarray' in sys.modules); "
            f"print(main(['inspect', {g!r}]) == 0, "
            f"main(['crop', {g!r}, {c!r}, '--region', '1:9,2:7', '--light', '1', '-q']) == 0, "
            f"main(['compress', {g!r}, {k!r}, '--rank', '2', '-q']) == 0, "
            f"main(['reconstruct', {k!r}, {r!r}, '--light', '1', '-q']) == 0, "
            f"main(['export', {k!r}, {e!r}, '--light', '0', '-q']) == 0, "
            "sorted(m for m in ('xarray', 'pandas') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    lines = out.splitlines()
    assert lines[0].split() == ["0", "['pipeline.stages.generate']", "False", "False"], out
    assert lines[-1] == "True True True True True []", out


def test_dask_array_imported_before_xarray_still_tells_a_data_array():
    """With xarray imported after dask.array, ``from_array`` of a DataArray of a dask array
    gives that dask array, as with dask's own import of xarray."""
    code = ("import sys, pipeline, numpy as np, dask.array as da; "
            "da.from_array(np.ones(3)); before = 'xarray' in sys.modules; "
            "import xarray as xr; x = xr.DataArray(da.ones((4, 4), chunks=2)); "
            "print(before, da.from_array(x) is x.data, "
            "type(da.from_array(xr.DataArray(np.ones(3)))).__name__)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert out.split() == ["False", "True", "Array"], out


def test_dask_array_s_sparse_and_fftpack_imports_wait_for_their_first_use():
    """``dask.array`` imported after ``pipeline`` imports neither ``scipy.sparse`` nor
    ``scipy.fftpack`` (0.3-0.4 s); once ``scipy.sparse`` is imported, dask handles the same
    chunk types as without ``pipeline``, and ``fft_wrap`` still warns of fftpack's functions.
    """
    probe = ("import dask.array as da, scipy.sparse, scipy.fftpack, warnings; "
             "from dask.array.chunk_types import _HANDLED_CHUNK_TYPES as kinds, "
             "is_valid_chunk_type; "
             "print(sorted(k.__name__ for k in kinds), "
             "is_valid_chunk_type(scipy.sparse.csr_matrix), "
             "is_valid_chunk_type(scipy.sparse.csr_array)); "
             "warnings.simplefilter('error'); "
             "exec('try: da.fft.fft_wrap(scipy.fftpack.fft)\\n"
             "except FutureWarning: print(\\'warned\\')')")
    first = ("import sys, pipeline, dask.array; "
             "print(sorted(m for m in ('scipy.sparse', 'scipy.fftpack', 'xarray') "
             "if m in sys.modules)); ")
    deferred, plain = (subprocess.run([sys.executable, "-c", code], capture_output=True,
                                      text=True, check=True).stdout.splitlines()
                       for code in (first + probe, probe))
    assert deferred[0] == "[]", deferred
    assert deferred[1:] == plain and "True True" in plain[0] and plain[1] == "warned", plain


def test_a_module_dask_imports_in_turn_still_gets_scipy_sparse(tmp_path):
    """Only dask's own optional imports wait: a package ``dask.array.chunk_types`` imports
    that imports ``scipy.sparse`` itself (pydata's ``sparse`` before 0.16) gets it, and its
    arrays stay a chunk type."""
    (tmp_path / "sparse").mkdir()
    (tmp_path / "sparse" / "__init__.py").write_text(
        "import scipy.sparse\nclass SparseArray:\n    pass\n")
    code = ("import pipeline, dask.array; "
            "from dask.array.chunk_types import _HANDLED_CHUNK_TYPES as kinds; "
            "print(sorted(k.__name__ for k in kinds))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, env={**os.environ, "PYTHONPATH": os.pathsep.join(
                             [str(tmp_path), os.environ.get("PYTHONPATH", "")])}).stdout
    assert out.split("\n")[0] == str(sorted(["ndarray", "MaskedArray", "SparseArray",
                                               "spmatrix", "sparray"])), out


@pytest.mark.slow  # 6 s (3 processes): kept out of the default run (4 min), run by .ci/run
def test_a_rechunk_on_a_local_scheduler_does_not_import_distributed(tmp_path):
    """dask's rechunk looks for a default client by importing distributed (0.17 s); a session
    tells it the method it would choose ("tasks"). ``btf scene`` rechunks the layers it reads.
    """
    g, spec = tmp_path / "g.zarr", tmp_path / "scene.yaml"
    spec.write_text(f"source: {g}\ndirections:\n  - [0, 0, 0, 0]\n  - [45, 30, 0, 0]\n")
    code = ("import sys; from pipeline.cli import main; "
            f"print(main(['generate', {str(g)!r}, '--material', 'wood', '--size', '24', "
            "'--sampling', 'abtf:4,1', '--chunk', '8', '--quiet']), "
            f"main(['scene', {str(spec)!r}, {str(tmp_path / 's.zarr')!r}, '--quiet']), "
            "'distributed' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert out.split() == ["0", "0", "False"], out


def test_console_script_is_installed():
    btf = Path(sys.executable).parent / "btf"
    out = subprocess.run([btf, "--version"], capture_output=True, text=True, check=True)
    assert out.stdout.startswith("btf ")
    usage = subprocess.run([btf, "generate", "x.zarr"], capture_output=True, text=True)
    assert usage.returncode == 2 and "--material: is required" in usage.stderr


def test_bad_scheduler_and_workers_are_usage_errors(btf, tmp_path):
    assert btf("inspect", tmp_path, "--scheduler", "tcp://").code == 2
    assert btf("inspect", tmp_path, "--workers", "0").code == 2


def test_progress_is_shown_unless_quiet(btf, tmp_path):
    args = ("generate", tmp_path / "a.zarr", "--material", "wood", "--size", "64",
            "--sampling", "abtf:16,4", "--chunk", "16", "--dir-chunk", "1")
    with dask.config.set({"btf.progress-after": 0}):
        loud = btf(*args, "--scheduler", "synchronous", "--workers", "1")
    assert loud.code == 0 and "generate: 1 x 64 layers" in loud.err
    assert "100% Completed" in loud.err
    quiet = btf(*args[:1], tmp_path / "b.zarr", *args[2:], "--quiet")
    assert quiet.code == 0 and quiet.err == "" and quiet.out == ""


def test_an_unreachable_cluster_is_a_clear_error(btf, tmp_path, monkeypatch):
    monkeypatch.setattr("pipeline.session.CONNECT_TIMEOUT", "1s")
    result = btf("generate", tmp_path / "a.zarr", "--material", "wood", "--size", "16",
                 "--scheduler", "tcp://127.0.0.1:9", "--quiet")
    assert result.code == 1 and "cannot reach the dask scheduler at tcp://127.0.0.1:9" in result.err
    assert not (tmp_path / "a.zarr").exists()

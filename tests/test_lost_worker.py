"""A worker lost in the middle of a run: the run finishes, with the bits of a synchronous run.

A real ``dask scheduler`` and two ``dask worker`` processes (docker-compose.yml's commands,
without a nanny so that SIGKILL really loses the worker) on loopback; one is killed once the
stage has written its first chunks. The scheduler reruns the lost worker's tasks on the other;
tasks write whole chunks and are pure functions of their inputs and the seed, so the output is
the same. Slow (a cluster per test): run by CI with ``-m slow``.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import zarr

from helpers import dask_cluster, generate_store

BIN = Path(sys.executable).parent
pytestmark = [pytest.mark.slow, pytest.mark.distributed]


@pytest.fixture
def two_workers(tmp_path):
    """``(address, [worker processes])`` of a fresh cluster: two workers without nannies, so
    that killing one loses it."""
    with dask_cluster(tmp_path, workers=2, processes=1, no_nanny=True) as cluster:
        yield cluster


def _chunks(out: Path) -> int:
    """Chunk files written so far in OUT's partial sibling (-1 before it exists; it may vanish:
    it is renamed)."""
    try:
        partial = [p for p in out.parent.glob(f".{out.stem}.*")
                   if "partial" in p.name or ".resume-" in p.name]
        return sum(1 for p in partial for _ in p.rglob("c/*")) if partial else -1
    except OSError:
        return 0


def _run_and_kill(args: list, out: Path, workers) -> subprocess.CompletedProcess:
    """Run ``btf args`` on the cluster; SIGKILL a worker once OUT's partial has 4 chunks, or
    half a second after it appeared (a stage that writes its output in its last pass)."""
    proc = subprocess.Popen([BIN / "btf", *map(str, args), "--quiet"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    killed = False
    deadline = time.monotonic() + 300
    try:
        started = None
        while proc.poll() is None and time.monotonic() < deadline:
            chunks = _chunks(out)
            if started is None and chunks >= 0:
                started = time.monotonic()
            if not killed and started is not None and (
                    chunks >= 4 or time.monotonic() - started > 0.5):
                os.kill(workers[0].pid, signal.SIGKILL)
                killed = True
            time.sleep(0.05)
        out_text, err_text = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert killed, "the run ended before a worker could be killed: make it larger"
    assert workers[0].wait(timeout=10) == -signal.SIGKILL
    return subprocess.CompletedProcess(proc.args, proc.returncode, out_text, err_text)


GENERATE = ("--material", "wood", "--size", "192", "--sampling", "abtf:12,4", "--chunk", "32",
            "--dir-chunk", "8", "--seed", "5")


def test_generate_survives_a_lost_worker(tmp_path, two_workers):
    address, workers = two_workers
    out = tmp_path / "cluster.zarr"
    run = _run_and_kill(["generate", out, *GENERATE, "--scheduler", address], out, workers)
    assert run.returncode == 0, run.stderr
    local = generate_store(tmp_path / "local.zarr", *GENERATE, "--scheduler", "synchronous")
    a, b = zarr.open_group(out, mode="r"), zarr.open_group(local, mode="r")
    for name in ("radiance", "height", "albedo"):
        assert np.array_equal(a[name][:], b[name][:]), name


def _same_as_synchronous(tmp_path, workers, address, stage, src, options, names):
    """Run ``btf stage src OUT options`` on the cluster losing a worker, and synchronously."""
    from pipeline.cli import main

    out = tmp_path / f"cluster_{stage}.zarr"
    run = _run_and_kill([stage, src, out, *options, "--scheduler", address], out, workers)
    assert run.returncode == 0, run.stderr
    local = tmp_path / f"local_{stage}.zarr"
    assert main([stage, str(src), str(local), *options, "--scheduler", "synchronous",
                 "--quiet"]) == 0
    a, b = zarr.open_group(out, mode="r"), zarr.open_group(local, mode="r")
    for name in names:
        assert np.array_equal(a[name][:], b[name][:]), name


@pytest.mark.parametrize("mode", [(), ("--passes", "1", "--oversample", "17")])
def test_compress_survives_a_lost_worker(tmp_path, two_workers, mode):
    address, workers = two_workers
    src = generate_store(tmp_path / "src.zarr", *GENERATE)
    _same_as_synchronous(tmp_path, workers, address, "compress", src, ["--rank", "16", *mode],
                         ("U", "S", "V"))


def test_quilt_application_survives_a_lost_worker(tmp_path, two_workers):
    address, workers = two_workers
    src = generate_store(tmp_path / "src.zarr", *GENERATE)
    _same_as_synchronous(tmp_path, workers, address, "quilt", src,
                         ["--block", "32", "--overlap", "8", "--size", "480,480"],
                         ("radiance",))


@pytest.mark.parametrize("progress", [False, True], ids=["quiet", "progress"])
def test_a_run_whose_last_worker_is_lost_stops_with_a_message(tmp_path, progress):
    """No worker left: the run stops after btf.no-workers-timeout (here 3 s) instead of
    waiting for ever, says why, and leaves no output; with a progress bar too."""
    out = tmp_path / "g.zarr"
    env = {**os.environ, "DASK_BTF__NO_WORKERS_TIMEOUT": "3",
           **({"DASK_BTF__PROGRESS_AFTER": "0"} if progress else {})}
    with dask_cluster(tmp_path, workers=1, processes=1, no_nanny=True) as (address, workers):
        proc = subprocess.Popen([BIN / "btf", "generate", out, *GENERATE, "--scheduler",
                                 address, *([] if progress else ["--quiet"])],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                env=env)
        try:
            deadline = time.monotonic() + 120
            while _chunks(out) < 4 and proc.poll() is None and time.monotonic() < deadline:
                time.sleep(0.05)
            assert proc.poll() is None, "the run ended before its worker could be killed"
            os.kill(workers[0].pid, signal.SIGKILL)
            lost = time.monotonic()
            _, err = proc.communicate(timeout=120)
            waited = time.monotonic() - lost
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
    assert proc.returncode == 1, err
    assert f"the dask cluster at {address} has had no worker for 3 s" in err, err
    assert "Traceback" not in err and waited < 30, (waited, err)
    assert not out.exists()

"""Shared fixtures: an in-process CLI runner and small generated stores."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import dask
import pytest
import scipy.linalg  # noqa: F401  (loads scipy's own BLAS, to be limited below)
from threadpoolctl import threadpool_limits

from helpers import generate_store
from pipeline.cli import main

# One BLAS thread in each test process: two pytest workers on two cores, each with OpenBLAS
# threads of its own, spin against each other (scipy's eigh measured 100x slower with both
# busy). btf pins its tasks to one BLAS thread itself (session.limit_blas); this is for the
# work the tests' own process does outside tasks (planning, references). Processes the tests
# start keep btf's own settings.
threadpool_limits(limits=1, user_api="blas")

# dask.distributed's clusters in tests poll less often: an idle LocalCluster of two worker
# processes took 7.4 s of CPU in 30 s (its event loops' 20 ms ticks, a stack profiler every
# 10 ms, the memory monitor every 100 ms, psutil every 500 ms), against 0.5 s with these.
# A session's cluster stays up once a test has started it, so the three test workers' clusters
# had cost a fifth of the run's CPU. Set in the environment too, for the clusters and the
# `btf` commands the tests start as processes.
QUIET_CLUSTERS = {
    "distributed.admin.tick.interval": "1s",
    "distributed.admin.system-monitor.interval": "5s",
    "distributed.worker.memory.monitor-interval": "1s",
    "distributed.worker.profile.enabled": False,
}
for _key, _value in QUIET_CLUSTERS.items():
    os.environ.setdefault("DASK_" + _key.upper().replace(".", "__").replace("-", "_"),
                          str(_value))
dask.config.set(QUIET_CLUSTERS)


@dataclass
class Result:
    code: int
    out: str
    err: str


@pytest.fixture
def btf(capsys):
    """Run ``btf ARGS...`` in-process; return exit code, stdout and stderr."""

    def run(*args) -> Result:
        try:
            code = main([str(a) for a in args])
        except SystemExit as exc:  # argparse usage errors and --help
            code = exc.code if isinstance(exc.code, int) else 1
        captured = capsys.readouterr()
        return Result(code, captured.out, captured.err)

    return run


SMALL_TASKS = 16  # texels per side of a task block in tests: small stores, many blocks


@pytest.fixture
def small_tasks(monkeypatch):
    """Task blocks of 16 texels, so that small test stores still span many blocks."""
    monkeypatch.setattr("pipeline.graphs.blocks.TASK_TEXELS", SMALL_TASKS)


@pytest.fixture(scope="session")
def small_abtf(tmp_path_factory) -> Path:
    """A 48 x 48 wood ABTF, 6 rotations x 3 elevations, in shards, many task blocks."""
    path = tmp_path_factory.mktemp("stores") / "wood.zarr"
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr("pipeline.graphs.blocks.TASK_TEXELS", SMALL_TASKS)
        return generate_store(path, "--material", "wood", "--size", "48", "--sampling",
                              "abtf:6,3", "--chunk", "8", "--shard", "16", "--dir-chunk", "4",
                              "--seed", "3")


@pytest.fixture(scope="session")
def small_btf(tmp_path_factory) -> Path:
    """A 32 x 32 fabric BTF with 3 views x 3 lights (oblique views: parallax)."""
    path = tmp_path_factory.mktemp("stores") / "fabric.zarr"
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr("pipeline.graphs.blocks.TASK_TEXELS", SMALL_TASKS)
        return generate_store(path, "--material", "fabric", "--size", "32", "--sampling",
                              "hemi:3", "--chunk", "8", "--dir-chunk", "2")


@pytest.fixture(scope="session")
def samples(tmp_path_factory) -> dict[str, Path]:
    """72 x 72 samples to quilt (fabric, stone, tiles), 4 x 2 ABTF lights, chunks of 32."""
    folder = tmp_path_factory.mktemp("quilt")
    return {m: generate_store(folder / f"{m}.zarr", "--material", m, "--size", "72",
                              "--sampling", "abtf:4,2", "--seed", "2", "--chunk", "32")
            for m in ("fabric", "stone", "tiles")}


@pytest.fixture(scope="session")
def local_cluster():
    """A dask.distributed LocalCluster of two single-threaded worker processes (its address)."""
    from distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=":0") as cluster:  # any free port
        yield cluster.scheduler_address


@pytest.fixture(scope="session")
def s3_server(tmp_path_factory):
    """A SeaweedFS S3 server on loopback with a bucket (benchmarks/s3server.py), for the session."""
    from benchmarks.s3server import start

    server = start(tmp_path_factory.mktemp("s3"))
    yield server
    server.stop()


@pytest.fixture
def s3(s3_server, monkeypatch):
    """The S3 server's environment set for the test (as a user's AWS set-up would be)."""
    for key, value in s3_server.environment.items():
        monkeypatch.setenv(key, value)
    return s3_server

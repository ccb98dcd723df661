"""The same commands as docker-compose.yml, as local processes on loopback.

A ``dask scheduler`` and a ``dask worker`` (two single-threaded processes, started in another
directory than the runner, as on a cluster) serve ``btf run`` started as a separate process.
"""

from __future__ import annotations

import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import zarr

from helpers import generate_store

BIN = Path(sys.executable).parent
DEMO = Path(__file__).resolve().parents[1] / "configs" / "demo.yaml"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_for_workers(address: str, n: int, timeout: float = 60) -> None:
    from distributed import Client

    with Client(address, timeout="20s") as client:
        client.wait_for_workers(n, timeout=timeout)


@pytest.fixture
def cluster(tmp_path):
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    elsewhere = tmp_path / "worker-home"
    elsewhere.mkdir()
    logs = (tmp_path / "scheduler.log").open("w"), (tmp_path / "worker.log").open("w")
    procs = [subprocess.Popen([BIN / "dask", "scheduler", "--host", "127.0.0.1", "--port",
                               str(port), "--no-dashboard"], stdout=logs[0], stderr=logs[0])]
    try:
        deadline = time.monotonic() + 30
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)
        procs.append(subprocess.Popen(
            [BIN / "dask", "worker", address, "--nworkers", "2", "--nthreads", "1",
             "--no-dashboard"], cwd=elsewhere, stdout=logs[1], stderr=logs[1]))
        _wait_for_workers(address, 2)
        yield address
    finally:
        for proc in reversed(procs):
            proc.terminate()
        for proc in reversed(procs):
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        for log in logs:
            log.close()


@pytest.mark.distributed
def test_btf_run_on_a_dask_cluster_of_separate_processes(tmp_path, cluster):
    run = subprocess.run([BIN / "btf", "run", DEMO, "--scheduler", cluster, "--set",
                          "generate.size=40", "--quiet"], cwd=tmp_path, capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    out = tmp_path / "out" / "demo"
    assert (out / "contact_sheet.png").is_file() and len(list((out / "layers").glob("*.png")))
    # the cluster's store is the one a local synchronous run makes
    local = generate_store(tmp_path / "local.zarr", "--material", "wood", "--size", "40",
                           "--sampling", "abtf:12,6", "--seed", "7", "--scheduler",
                           "synchronous")
    a = zarr.open_group(out / "wood.zarr", mode="r")
    b = zarr.open_group(local, mode="r")
    for name in ("radiance", "height", "albedo"):
        assert np.array_equal(a[name][:], b[name][:]), name


@pytest.mark.distributed
def test_quilting_on_the_cluster_gives_the_bits_of_a_local_run(tmp_path, cluster):
    src = generate_store(tmp_path / "s.zarr", "--material", "fabric", "--size", "48",
                         "--sampling", "abtf:4,2", "--seed", "3")
    compressed = tmp_path / "c.zarr"
    done = subprocess.run([BIN / "btf", "compress", src, compressed, "--rank", "4", "--quiet"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    for store, values in ((src, "radiance"), (compressed, "V")):
        outs = []
        # the cluster has two threads, the local run three: other task groupings, same bits
        for scheduler in ((cluster,), ("threads", "--workers", "3")):
            out = tmp_path / f"{Path(store).stem}-{len(outs)}.zarr"
            done = subprocess.run(
                [BIN / "btf", "quilt", store, out, "--block", "16", "--overlap", "4",
                 "--candidates", "4", "--corners", "2", "--size", "24,24", "--seed", "5",
                 "--scheduler", *scheduler, "--quiet"], capture_output=True, text=True,
                timeout=300)
            assert done.returncode == 0, done.stderr
            outs.append(zarr.open_group(out, mode="r"))
        for name in (values, "prescription_index", "prescription_weight"):
            assert np.array_equal(outs[0][name][:], outs[1][name][:]), (store, name)

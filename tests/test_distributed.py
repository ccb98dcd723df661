"""The same commands as docker-compose.yml, as local processes on loopback.

A ``dask scheduler`` and a ``dask worker`` (two single-threaded processes, started in another
directory than the runner, as on a cluster) serve ``btf run`` started as a separate process.
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
import yaml
import zarr

from helpers import (
    btf_process,
    compose_command,
    compose_services,
    dask_cluster,
    generate_store,
    no_partial_outputs,
    small_demo,
)

BIN = Path(sys.executable).parent


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """One cluster for the module's tests (stopping one takes ~8 s): docker-compose.yml's
    worker replicas as processes (at most 2: CI has 2 cores), one thread each."""
    replicas = min(2, compose_services()["worker"]["deploy"]["replicas"])
    with dask_cluster(tmp_path_factory.mktemp("cluster"), processes=replicas) as (address, _):
        yield address


PROGRESS = {"DASK_BTF__PROGRESS_AFTER": "0"}  # a progress bar on every compute


def _btf(*args, **kwargs) -> subprocess.CompletedProcess:
    """``btf ARGS`` as a process, with a progress bar on every compute unless --quiet."""
    return btf_process(*args, env=PROGRESS, **kwargs)


def _shows_progress(stderr: str) -> bool:
    return "% Completed" in stderr and "Traceback" not in stderr


# In the slow set, with the other runs of btf on clusters of separate processes: over TLS
# (tests/test_tls.py), with cluster.yaml on S3 (tests/test_s3.py), and progress on a cluster
# in the next test. The default set runs the demo locally (tests/test_config.py).
@pytest.mark.slow
@pytest.mark.distributed
@pytest.mark.parametrize("quiet", [False, True], ids=["progress", "quiet"])
def test_btf_run_on_a_dask_cluster_of_separate_processes(tmp_path, cluster, quiet):
    # docker-compose.yml's runner command with the demo config, scaled down (local stores,
    # which this host's workers share; its own config, on S3, runs in tests/test_s3.py)
    demo = small_demo(tmp_path, 64)
    runner = compose_command("runner", words={"/app/configs/cluster.yaml": str(demo)},
                             values={"--scheduler": cluster})
    assert runner[0] == "btf"
    run = _btf(*runner[1:], *(["--quiet"] if quiet else []), cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    if quiet:
        assert run.stderr == ""
    else:  # the stages' messages and a bar per compute, as on the local schedulers
        stages = len(yaml.safe_load(demo.read_text())["stages"])
        assert f"[1/{stages}] generate" in run.stderr, run.stderr
        assert f"[{stages}/{stages}] report" in run.stderr and _shows_progress(run.stderr)
    out = tmp_path / "out" / "demo"
    assert (out / "report.html").is_file() and len(list((out / "scene").glob("*.png"))) == 3
    # the cluster's store is the one a local synchronous run makes
    local = generate_store(tmp_path / "local.zarr", "--material", "wood", "--size", "64",
                           "--sampling", "abtf:12,4", "--seed", "7", "--scheduler",
                           "synchronous")
    a = zarr.open_group(out / "wood.zarr", mode="r")
    b = zarr.open_group(local, mode="r")
    for name in ("radiance", "height", "albedo"):
        assert np.array_equal(a[name][:], b[name][:]), name


@pytest.mark.slow
@pytest.mark.distributed
def test_quilting_on_the_cluster_gives_the_bits_of_a_local_run(tmp_path, cluster):
    src = generate_store(tmp_path / "s.zarr", "--material", "fabric", "--size", "48",
                         "--sampling", "abtf:4,2", "--seed", "3")
    compressed = tmp_path / "c.zarr"
    done = btf_process("compress", src, compressed, "--rank", "4", "--quiet")
    assert done.returncode == 0, done.stderr
    for store, values in ((src, "radiance"), (compressed, "V")):
        outs = []
        # the cluster has two threads, the local run three: other task groupings, same bits
        for scheduler in ((cluster,), ("threads", "--workers", "3")):
            out = tmp_path / f"{Path(store).stem}-{len(outs)}.zarr"
            # tiles of two steps on a 48^2 sample: a test of the bits, not of the seams
            done = btf_process("quilt", store, out, "--block", "16", "--overlap", "4",
                               "--candidates", "4", "--corners", "2", "--size", "24,24",
                               "--seed", "5", "--max-seam", "10", "--scheduler", *scheduler,
                               "--quiet")
            assert done.returncode == 0, done.stderr
            outs.append(zarr.open_group(out, mode="r"))
        for name in (values, "prescription_index", "prescription_weight"):
            assert np.array_equal(outs[0][name][:], outs[1][name][:]), (store, name)


@pytest.mark.slow  # 12 s (a cluster): kept out of the default run (4 min), run by .ci/run
@pytest.mark.distributed
def test_a_subcommand_on_the_cluster_shows_progress_and_reports_a_failing_task(tmp_path,
                                                                               cluster):
    src = generate_store(tmp_path / "s.zarr", "--material", "wood", "--size", "64",
                         "--sampling", "abtf:8,2", "--seed", "3")
    done = _btf("compress", src, tmp_path / "c.zarr", "--rank", "4", "--scheduler", cluster)
    assert done.returncode == 0 and _shows_progress(done.stderr), done.stderr
    assert "compress: pass 3/3 (projection" in done.stderr
    # a chunk whose bytes changed fails its task on a worker: one clear error naming the
    # chunk (its checksum), no output
    chunk = next(p for p in sorted((src / "radiance" / "c").rglob("*")) if p.is_file())
    chunk.write_bytes(b"not a blosc frame")
    failed = _btf("compress", src, tmp_path / "bad.zarr", "--rank", "4", "--scheduler", cluster)
    assert failed.returncode == 1, failed.stderr
    assert "btf compress: error:" in failed.stderr
    assert "variable 'radiance', chunk (0, 0, 0, 0, 0)" in failed.stderr
    assert "fails its checksum" in failed.stderr
    assert "Traceback" not in failed.stderr and no_partial_outputs(tmp_path / "bad.zarr")


def _idle(address: str) -> bool:
    from distributed import Client

    with Client(address, timeout="20s") as client:
        busy = client.run(lambda dask_worker: len(dask_worker.state.executing))
    return not any(busy.values())


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.mark.slow
@pytest.mark.distributed
def test_ctrl_c_on_a_cluster_run_stops_cleanly(tmp_path, cluster):
    src = generate_store(tmp_path / "s.zarr", "--material", "wood", "--size", "256",
                         "--sampling", "abtf:12,4", "--seed", "3")
    out = tmp_path / "c.zarr"
    # ten passes (a second or more): the interrupt lands while they run on the workers. A
    # shell starting CI in the background ignores SIGINT in what it starts; the child would
    # inherit that and never see the interrupt, so its default action is restored.
    with subprocess.Popen([BIN / "btf", "compress", src, out, "--rank", "8", "--power-iters",
                           "9", "--scheduler", cluster], stderr=subprocess.PIPE, text=True,
                          env={**os.environ, **PROGRESS}, preexec_fn=_default_sigint) as proc:
        seen = ""
        while "pass 1/10" not in seen:  # interrupt once the first pass runs on the workers
            line = proc.stderr.readline()
            assert line, seen
            seen += line
        time.sleep(0.2)
        proc.send_signal(signal.SIGINT)
        seen += proc.stderr.read()
        assert proc.wait(timeout=120) == 130, seen
    assert "btf compress: interrupted" in seen and "Traceback" not in seen, seen
    assert no_partial_outputs(out)
    assert _idle(cluster)  # the running tasks were waited for: nothing writes any more
    again = _btf("compress", src, out, "--rank", "8", "--scheduler", cluster, "--quiet")
    assert again.returncode == 0 and again.stderr == "", again.stderr


@pytest.mark.distributed
def test_shared_values_are_graph_tasks_a_lost_worker_can_recompute(local_cluster):
    """Values every task reads travel as one graph task, not scattered data: the scheduler can
    run it again when the worker holding it is lost (tests/test_lost_worker.py kills one)."""
    import dask
    from dask.delayed import Delayed

    from pipeline.session import RuntimeOptions, Session

    with Session(RuntimeOptions(scheduler=local_cluster, quiet=True)) as session:
        shared = session.share(np.arange(5))
        assert isinstance(shared, Delayed)
        total = dask.delayed(np.sum)(shared)
        assert session.compute(total) == (10,)


class _FlakyScheduler:
    """A client whose scheduler fails to send a worker plugin ``failures`` times, as when a
    worker is killed while the plugin is being sent to it."""

    def __init__(self, failures: int):
        self.failures, self.calls = failures, 0

    def register_plugin(self, plugin, name):
        from distributed.comm.core import CommClosedError

        self.calls += 1
        if self.calls <= self.failures:
            raise CommClosedError("in <TCP (closed) ConnectionPool.register_worker_plugin "
                                  "local=tcp://127.0.0.1:1 remote=tcp://127.0.0.1:2>: "
                                  "Stream is closed")


@pytest.mark.parametrize("failures", [0, 2, 6])
def test_a_worker_lost_while_the_blas_plugin_is_sent_is_ridden_out(monkeypatch, capsys,
                                                                    failures):
    """The plugin is sent again while the scheduler drops the lost worker (a kill -9 of a
    worker at that moment stopped a whole btf run), once a session; if the scheduler never
    takes it, one clear message."""
    from pipeline import session as session_module
    from pipeline.errors import BTFError
    from pipeline.session import RuntimeOptions, Session

    monkeypatch.setattr(session_module, "PLUGIN_WAITS", (0.01,) * 5)
    monkeypatch.setattr(session_module, "steady_memory", lambda: None)
    session = Session(RuntimeOptions(scheduler="tcp://127.0.0.1:2"))
    session.client = client = _FlakyScheduler(failures)
    if failures > 5:
        with pytest.raises(BTFError, match=r"tcp://127.0.0.1:2: the workers did not take btf's "
                                           r"worker plugin after 6 tries \(CommClosedError"):
            with session.blas_pinned_in_tasks():
                pass
        assert client.calls == 6
        return
    for _ in range(3):  # a stage after another
        with session.blas_pinned_in_tasks():
            pass
    assert client.calls == failures + 1
    assert capsys.readouterr().err.count("trying again in 0.01 s") == failures

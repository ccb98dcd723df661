"""Stores in object storage: every stage on a real S3 server, the commit protocol, bad input.

The server is SeaweedFS (benchmarks/s3server.py) on loopback; the environment holds its endpoint
and credentials as a user's AWS set-up would (the ``s3`` fixture).
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import dask
import numpy as np
import pytest
import zarr

from helpers import Killed, btf_process, dask_cluster, killed_before_unit
from pipeline import storage

BIN = Path(sys.executable).parent
GEN = ("--material", "wood", "--size", "48", "--sampling", "abtf:4,2", "--chunk", "16",
       "--dir-chunk", "4")


def _arrays(store) -> dict[str, np.ndarray]:
    """Every array of a store, by path (reads through btf's own opener)."""
    group = zarr.open_group(storage.store(storage.parse(store)), mode="r",
                            use_consolidated=False)
    return {name: array[...] for name, array in group.arrays()}


def _same(a, b) -> None:
    left, right = _arrays(a), _arrays(b)
    assert left.keys() == right.keys()
    for name in left:
        assert np.array_equal(left[name], right[name], equal_nan=True), name


def test_a_url_names_a_store_or_is_refused_and_never_becomes_a_folder(tmp_path, btf,
                                                                       monkeypatch):
    monkeypatch.chdir(tmp_path)
    for url, message in (("gs://bucket/x.zarr", "unsupported store URL scheme 'gs'"),
                         ("s3:/bucket/x.zarr", "s3://BUCKET/KEY"),
                         ("s3://bucket", "s3://BUCKET/KEY"),
                         ("https://host/x.zarr", "unsupported store URL scheme 'https'")):
        result = btf("generate", url, *GEN, "--quiet")
        assert result.code == 2 and message in result.err, (url, result.err)
    result = btf("run", _config(tmp_path, "gs://b/x.zarr"), "--quiet")
    assert result.code == 1 and "stages[0].generate.out" in result.err
    assert list(tmp_path.iterdir()) == [tmp_path / "run.yaml"]  # no folder named s3: or gs:
    assert storage.parse(f"file://{tmp_path}/x.zarr") == str(tmp_path / "x.zarr")


def _config(folder: Path, out: str) -> Path:
    path = folder / "run.yaml"
    path.write_text(f"stages:\n  - generate: {{out: '{out}', material: wood, size: 32, "
                    "sampling: 'abtf:4,2'}\n")
    return path


@pytest.mark.slow  # 25 s: the slow set (.ci/run) keeps it; the default run stays in 4 minutes
def test_every_stage_on_s3_gives_the_bits_of_a_local_run(tmp_path, btf, s3):
    """generate, ingest, crop, compress, reconstruct, quilt, roller, enlarge, scene, inspect:
    reading and writing S3 only, the same stores as on a local disk."""
    local, remote = tmp_path / "local", "s3://btf/every"
    local.mkdir()
    steps = [
        ("generate", "{d}/wood.zarr", *GEN),
        ("export", "{d}/wood.zarr", str(tmp_path / "layers"), "--light", "0,1,2"),
        ("ingest", str(tmp_path / "layers"), "{d}/again.zarr"),
        ("crop", "{d}/wood.zarr", "{d}/sample.zarr", "--region", "8:40,8:40"),
        ("crop", "{d}/wood.zarr", "{d}/photo.zarr", "--light", "0"),
        ("compress", "{d}/sample.zarr", "{d}/sample_svd.zarr", "--rank", "4"),
        ("compress", "{d}/wood.zarr", "{d}/wood_svd.zarr", "--rank", "4", "--verify"),
        ("reconstruct", "{d}/wood_svd.zarr", "{d}/part.zarr", "--light", "1,3"),
        ("quilt", "{d}/wood.zarr", "{d}/tiles.zarr", "--block", "16", "--overlap", "4",
         "--size", "24,24", "--max-seam", "10"),
        ("enlarge", "{d}/sample_svd.zarr", "{d}/photo.zarr", "{d}/big.zarr", "--levels", "1",
         "--iterations", "1", "--no-statistics", "--sample-origin", "8,8"),
        ("pyramid", "{d}/wood.zarr", "--levels", "1"),
    ]
    for step in steps:
        for where in (str(local), remote):
            if step[0] == "export" and where == remote:
                continue  # the layer folder is local; ingest reads it into both
            args = [a.format(d=where) for a in step]
            result = btf(*args, "--quiet", "--scheduler", "synchronous")
            assert result.code == 0, (args, result.err)
    for name in ("wood", "again", "sample", "photo", "sample_svd", "wood_svd", "part", "tiles",
                 "big"):
        _same(local / f"{name}.zarr", f"{remote}/{name}.zarr")
    scene = tmp_path / "scene.yaml"
    for where in (str(local), remote):
        scene.write_text(f"source: {where}/wood_svd.zarr\ndirections: [[30, 40, 0, 0]]\n"
                         "region: [0, 32, 8, 40]\nlevel: 1\nformat: zarr\n")
        assert btf("scene", scene, f"{where}/scene.zarr", "--quiet").code == 0
    _same(local / "scene.zarr", f"{remote}/scene.zarr")
    inspected = btf("inspect", f"{remote}/wood_svd.zarr", "--json")
    assert inspected.code == 0 and json.loads(inspected.out)["kind"] == "compressed"


def test_plain_zarr_and_xarray_open_an_s3_output_with_no_private_code(tmp_path, btf, s3):
    url = s3.url("plain/wood.zarr")
    assert btf("generate", url, *GEN, "--quiet").code == 0
    import xarray as xr

    group = zarr.open_group(url, mode="r")  # fsspec's s3fs, configured by the environment
    assert group.attrs["btf_kind"] == "abtf" and group["radiance"].shape[:2] == (1, 8)
    ds = xr.open_zarr(url)
    assert ds["radiance"].dims == ("view", "light", "y", "x", "channel")
    assert not [k for k in storage.list_below(url) if ".btf" in k]  # no markers left


def _start(args, env=None):
    return subprocess.Popen([BIN / "btf", *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env={**os.environ, **(env or {})})


def _held_lock(url: str, **fields) -> str:
    """Write the lock object of output ``url`` as a run with ``fields`` would have left it."""
    from pipeline import locks

    target = storage.join(storage.parent(url), f".{storage.name(url)}.lock")
    body = {"owner": f"{socket.gethostname()}:{os.getpid()}:test", "expires": time.time() + 600,
            "boot": locks._boot_id(), "started": locks._started(os.getpid()), **fields}
    storage.write(target, json.dumps(body).encode())
    return target


def _gone_pid() -> int:
    child = subprocess.Popen(["true"])
    child.wait()
    return child.pid  # reaped: no process has it (until the system reuses it)


@pytest.mark.parametrize("holder", ["this process", "another machine", "a process gone",
                                    "a reused process id", "an earlier boot"])
def test_a_lock_whose_holder_is_gone_is_taken_at_once_and_a_live_one_is_not(btf, s3, holder):
    url = s3.url(f"locked-{holder.replace(' ', '-')}/wood.zarr")
    fields = {"this process": {},
              "another machine": {"owner": "elsewhere.example:1:test"},
              "a process gone": {"owner": f"{socket.gethostname()}:{_gone_pid()}:test"},
              "a reused process id": {"started": 1.0},  # this pid, but started in 1970
              "an earlier boot": {"boot": "not-this-boot"}}[holder]
    target = _held_lock(url, **fields)
    done = btf("generate", url, *GEN, "--quiet")
    if holder in ("this process", "another machine"):  # alive, or unknowable: the lease
        assert done.code == 1, done.err
        assert "another btf run is writing this output" in done.err and "s more" in done.err
        assert storage.read(target) is not None and not storage.exists(url)
    else:
        assert done.code == 0, done.err
        assert storage.read(target) is None  # released at the end, as its own
        assert zarr.open_group(url, mode="r")["radiance"].shape[:2] == (1, 8)


@pytest.mark.slow  # kill -9 and resume on a local disk: tests/test_resume.py, also slow
def test_a_killed_run_leaves_nothing_that_opens_and_resumes_to_the_same_bits(tmp_path, s3):
    url, whole = s3.url("killed/wood.zarr"), s3.url("killed/whole.zarr")
    args = ["generate", url, "--material", "wood", "--size", "96", "--sampling", "abtf:6,4",
            "--chunk", "16", "--dir-chunk", "4", "--scheduler", "synchronous", "--quiet"]
    env = {"BTF_LOCK_LEASE": "8"}
    proc = _start(args, env)
    deadline = time.monotonic() + 120
    while not any(".btf-done/" in k and "_created" not in k for k in storage.list_below(url)):
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        time.sleep(0.2)
    proc.send_signal(signal.SIGKILL)
    proc.communicate()  # and its pipes closed
    with pytest.raises(FileNotFoundError):  # nothing half-written opens at OUT
        zarr.open_group(storage.store(url), mode="r")
    # the lock names this machine and a process that is gone: taken over within its lease
    again = btf_process(*args[:-1], env=env)
    assert again.returncode == 0, again.stderr
    assert "kept" in again.stderr or "already" in again.stderr, again.stderr
    done = btf_process("generate", whole, *args[2:])
    assert done.returncode == 0, done.stderr
    _same(url, whole)


# slow (7-9 s): its local twin, test_resume_units.py's kept block whose chunk changed, is in
# the default set
@pytest.mark.slow
def test_a_resume_starts_over_when_a_chunk_the_killed_run_wrote_fails_its_checksum(
        btf, s3, monkeypatch, capsys):
    """Quilting resumes in place on S3; a chunk object of the killed run with a changed byte
    is not kept: the rerun starts over and gives the bits of an uninterrupted run."""
    from pipeline.cli import main

    sample, ref, out = (s3.url(f"distrust/{n}.zarr") for n in ("stone", "ref", "out"))
    assert btf("generate", sample, "--material", "stone", "--size", "64", "--sampling",
               "hemi:3", "--chunk", "32", "--dir-chunk", "2", "--quiet").code == 0
    args = ["--block", "16", "--overlap", "4", "--candidates", "4", "--seed", "3",
            "--scheduler", "synchronous"]
    assert btf("quilt", sample, ref, *args, "--quiet").code == 0
    real_remove = storage.remove
    with monkeypatch.context() as m, pytest.raises(Killed):  # killed: nothing cleaned up
        killed_before_unit(m, 2, "write-")
        m.setattr(storage, "remove", lambda at: None if at == out else real_remove(at))
        main(["quilt", sample, out, *args, "--quiet"])
    chunk = storage.join(out, next(k for k in sorted(storage.list_below(out))
                                   if "radiance/c/" in k))
    data = bytearray(storage.read(chunk))
    data[len(data) // 2] ^= 0x10
    storage.write(chunk, bytes(data))
    capsys.readouterr()
    assert main(["quilt", sample, out, *args]) == 0
    said = capsys.readouterr().err
    assert "quilt: resuming: " in said and "radiance chunk (" in said, said
    assert "of the killed run fails its checksum: starting over" in said, said
    _same(out, ref)


def test_a_lost_chunk_write_fails_the_commit_and_a_lost_object_fails_its_reader(btf, s3,
                                                                               monkeypatch):
    """A chunk PUT acknowledged and never stored is found before the commit (nothing is left,
    the rerun gives the bits); an object deleted from a committed store is an error naming it,
    not NaN (pipeline.completeness)."""
    from zarr.storage import ObjectStore

    url, ref = s3.url("lost/wood.zarr"), s3.url("lost/ref.zarr")
    assert btf("generate", ref, *GEN, "--quiet").code == 0
    put, dropped = ObjectStore.set, []

    async def lose_one(self, key, value):
        if storage.chunk_key(key) and key.startswith("radiance/") and not dropped:
            dropped.append(key)
            return None
        return await put(self, key, value)

    with monkeypatch.context() as m:
        m.setattr(ObjectStore, "set", lose_one)
        lost = btf("generate", url, *GEN, "--quiet")
    assert lost.code == 1 and dropped and dropped[0] in lost.err, lost.err
    assert "1 chunk object(s) are missing once the stage finished" in lost.err
    assert not storage.any_below(url) and not storage.exists(storage.join(
        storage.parent(url), ".wood.zarr.record"))
    assert btf("generate", url, *GEN, "--quiet").code == 0
    _same(url, ref)
    storage.remove(storage.join(url, dropped[0]))
    cropped = btf("crop", url, s3.url("lost/crop.zarr"), "--region", "0:48,0:48")
    assert cropped.code == 1, cropped.err
    assert f"{url}: array 'radiance' has no object for chunk " in cropped.err, cropped.err
    assert not storage.any_below(s3.url("lost/crop.zarr"))


@pytest.mark.slow  # 5 s: kept out of the default run (4 min), run by .ci/run
def test_overwrite_keeps_the_old_output_until_the_new_one_is_complete(tmp_path, btf, s3,
                                                                       monkeypatch):
    url = s3.url("over/wood.zarr")
    assert btf("generate", url, *GEN, "--seed", "1", "--quiet").code == 0
    before = _arrays(url)

    def fail(*args, **kwargs):
        raise RuntimeError("killed in the middle")

    monkeypatch.setattr("pipeline.atomic.consolidate", fail)
    with pytest.raises(RuntimeError, match="killed in the middle"):
        btf("generate", url, *GEN, "--seed", "2", "--overwrite", "--quiet")
    after = _arrays(url)
    assert all(np.array_equal(before[k], after[k], equal_nan=True) for k in before)
    monkeypatch.undo()
    for key, value in s3.environment.items():
        monkeypatch.setenv(key, value)
    assert btf("generate", url, *GEN, "--seed", "2", "--overwrite", "--quiet").code == 0
    assert not np.array_equal(_arrays(url)["radiance"], before["radiance"])
    assert not [c for c in storage.children(s3.url("over")) if ".resume-" in c
                and storage.any_below(s3.url(f"over/{c}"))]


@pytest.mark.slow  # 5 s: kept out of the default run (4 min), run by .ci/run
def test_a_swap_cut_short_is_finished_by_the_next_run(btf, s3, monkeypatch):
    url = s3.url("swap/wood.zarr")
    assert btf("generate", url, *GEN, "--seed", "1", "--quiet").code == 0
    real = storage.copy_tree

    def cut(source, target, **order):
        raise KeyboardInterrupt  # killed between deleting the old output and copying the new

    monkeypatch.setattr(storage, "copy_tree", cut)
    from pipeline.cli import main

    assert main(["generate", url, *GEN, "--seed", "2", "--overwrite", "--quiet"]) != 0
    monkeypatch.setattr(storage, "copy_tree", real)
    assert btf("inspect", url).code == 0  # any command on it finishes the swap first
    assert btf("generate", s3.url("swap/two.zarr"), *GEN, "--seed", "2", "--quiet").code == 0
    _same(url, s3.url("swap/two.zarr"))


@pytest.mark.slow  # 4 s: kept out of the default run (4 min), run by .ci/run
def test_a_write_landing_after_a_failed_run_s_cleanup_is_removed_by_the_next_run(btf, s3,
                                                                                 monkeypatch):
    """A failed run's cleanup lists and removes its partial output; a write still in flight
    (a retry that got through once the server was back) can land after it. The record that
    marks the prefix as btf's stays while anything is left, so the next run removes the rest
    rather than refusing a prefix it takes for someone else's."""
    import pipeline.stages.generate as gen

    url = s3.url("late/wood.zarr")
    real_remove = storage.remove

    def remove_then_late_write(location):
        real_remove(location)
        if location == url:
            storage.write(storage.join(url, "radiance/c/9/9/9/9/9"), b"late")

    def failing(*args, **kwargs):
        raise RuntimeError("the object store went away")

    monkeypatch.setattr(storage, "remove", remove_then_late_write)
    monkeypatch.setattr(gen, "render_block", failing)
    from pipeline.cli import main

    with pytest.raises(RuntimeError, match="went away"):
        main(["generate", url, *GEN, "--quiet"])
    monkeypatch.undo()
    for key, value in s3.environment.items():
        monkeypatch.setenv(key, value)
    assert storage.any_below(url)  # the late write is there, and so is the record
    assert storage.read(storage.join(storage.parent(url), ".wood.zarr.record")) is not None
    again = btf("generate", url, *GEN, "--quiet")
    assert again.code == 0, again.err
    assert btf("generate", s3.url("late/two.zarr"), *GEN, "--quiet").code == 0
    _same(url, s3.url("late/two.zarr"))


def test_an_object_store_error_inside_zarr_is_one_message_with_the_object_s_url(tmp_path, btf,
                                                                                monkeypatch):
    import obstore.exceptions as oe

    import pipeline.stages.generate as gen

    monkeypatch.setenv("AWS_ENDPOINT_URL", "http://127.0.0.1:9")
    text = ("Generic S3 error: Error performing PUT http://127.0.0.1:9/btf/x.zarr/radiance/c/0/1"
            " in 30.9s, after 100 retries, max_retries: 100, retry_timeout: 60s  - HTTP error: "
            "error sending request\n\nDebug source:\nGeneric {...}")

    def down(*args, **kwargs):
        raise oe.GenericError(text)

    monkeypatch.setattr(gen, "render_block", down)
    result = btf("generate", tmp_path / "x.zarr", *GEN, "-q")
    assert result.code == 1 and not list(tmp_path.iterdir())
    assert result.err == ("btf generate: error: s3://btf/x.zarr/radiance/c/0/1: cannot reach "
                          "the object store at http://127.0.0.1:9\n"), result.err
    assert storage.explain_request(RuntimeError(text)) is None  # only obstore's errors


# the 10 s, in the slow set (.ci/run)
@pytest.mark.parametrize("seconds", [10])
@pytest.mark.slow
def test_a_run_rides_out_an_outage_of_the_object_store(tmp_path, btf, s3, monkeypatch, seconds):
    """Every connection reset, and every new one, for some seconds in the middle of the
    writes: the run waits it out (obstore's retries) and writes the same store as without the
    outage."""
    from urllib.parse import urlparse

    from benchmarks.faultproxy import FlakyProxy

    server = urlparse(s3.endpoint)
    url = s3.url(f"flaky{seconds}/wood.zarr")
    with FlakyProxy((server.hostname, server.port), after_requests=12,
                    seconds=seconds) as proxy:
        monkeypatch.setenv("AWS_ENDPOINT_URL", proxy.endpoint)
        start = time.monotonic()
        result = btf("generate", url, *GEN, "--quiet")
        took = time.monotonic() - start
        assert result.code == 0, result.err
        assert len(proxy.outages) == 1 and proxy.reset > 0  # the outage happened, mid-run
        assert took >= seconds, took
    monkeypatch.setenv("AWS_ENDPOINT_URL", s3.endpoint)
    assert btf("generate", tmp_path / "wood.zarr", *GEN, "--quiet").code == 0
    _same(tmp_path / "wood.zarr", url)


@pytest.mark.parametrize("case", ["unreachable", "bucket", "credentials", "permission"])
def test_bad_object_storage_stops_with_the_url_and_the_cause(btf, s3, monkeypatch, case):
    from benchmarks.s3server import READER_KEY, READER_SECRET

    url = s3.url(f"bad/{case}.zarr")
    if case == "unreachable":
        monkeypatch.setenv("AWS_ENDPOINT_URL", "http://127.0.0.1:1")
        cause = "cannot reach the object store at http://127.0.0.1:1"
    elif case == "bucket":
        url = "s3://no-such-bucket/x.zarr"
        cause = "the bucket 'no-such-bucket' does not exist"
    elif case == "credentials":
        monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "not-the-secret")
        cause = "the credentials were refused"
    else:
        monkeypatch.setenv("AWS_ACCESS_KEY_ID", READER_KEY)
        monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", READER_SECRET)
        cause = "permission denied"
    # one retry where nothing answers: the defaults retry for about 30 s
    retries = {"btf.object-store.max-retries": 1} if case == "unreachable" else {}
    with dask.config.set(retries):
        result = btf("generate", url, *GEN, "--quiet")
    assert result.code == 1 and f"{url}: {cause}" in result.err, result.err
    assert result.err.count("\n") == 1  # one message
    monkeypatch.undo()
    for key, value in s3.environment.items():
        monkeypatch.setenv(key, value)
    if case != "bucket":
        assert not storage.any_below(url) and not storage.any_below(s3.url("bad/.x"))


@pytest.fixture
def s3_cluster(tmp_path, s3):
    """A dask scheduler and two single-threaded workers whose folders share nothing: each
    worker process starts in a folder of its own and reaches the stores through S3 only."""
    with dask_cluster(tmp_path, workers=2, processes=1,
                      env={**os.environ, **s3.environment}) as (address, _):
        yield address


# slow: 18 s; test_every_stage_on_s3_gives_the_bits_of_a_local_run (also slow) covers every
# stage on S3, this one adds configs/cluster.yaml on a cluster of shared-nothing workers
@pytest.mark.slow
@pytest.mark.distributed
def test_the_cluster_config_on_s3_gives_the_bits_of_a_local_run(tmp_path, btf, s3, s3_cluster):
    config = Path(__file__).resolve().parents[1] / "configs" / "cluster.yaml"
    runner = tmp_path / "runner"
    runner.mkdir()
    done = btf_process("run", config, "--scheduler", s3_cluster, "--set", "generate.size=64",
                       "--quiet", cwd=runner, env=s3.environment, timeout=600)
    assert done.returncode == 0, done.stderr
    assert list(runner.iterdir()) == []  # the runner wrote nothing locally either
    page = storage.read(s3.url("cluster/report.html")).decode()
    assert "Compression: s3://btf/cluster/wood_svd.zarr" in page and "Tile set: " in page
    local = tmp_path / "local"
    for args in (("generate", local / "wood.zarr", "--material", "wood", "--size", "64",
                  "--sampling", "abtf:12,4"),
                 ("compress", local / "wood.zarr", local / "wood_svd.zarr", "--rank", "16"),
                 ("quilt", local / "wood.zarr", local / "tiles.zarr")):
        assert btf(*args, "--scheduler", "synchronous", "--quiet").code == 0
    for name in ("wood", "wood_svd", "tiles"):
        _same(local / f"{name}.zarr", f"s3://btf/cluster/{name}.zarr")


@pytest.mark.slow
def test_btf_bench_objectstore_measures_both_locations_and_both_store_classes():
    import argparse

    from benchmarks import objectstore as suite

    result = suite.run(argparse.Namespace(size=64, sampling="abtf:4,2", rank=4, repeat=1))
    assert [r["layout"] for r in result["rows"]] == list(suite.LAYOUTS)
    for row in result["rows"]:
        assert row["s3_bytes"] == pytest.approx(row["local_bytes"], rel=0.05)
        for key in ("local_generate", "s3_generate", "local_compress", "s3_compress"):
            assert row[key]["seconds"] > 0 and row[key]["peak_rss"] > 0
    shards, chunks = result["rows"][2], result["rows"][0]
    assert shards["s3_objects"] <= chunks["s3_objects"]
    assert {c["class"] for c in result["classes"]} == {"obstore", "fsspec"}
    text = suite.report(result)
    assert "| chunks 128 in 2x2 shards | compress |" in text and "| obstore |" in text


@pytest.mark.slow
def test_btf_bench_writes_s3_rows_stand_beside_zarr_writing_to_the_same_server():
    import argparse

    from benchmarks import writes as suite

    result = suite.run(argparse.Namespace(texels=16, components=2, dir_chunks="64",
                                          stages="reconstruct,crop", repeat=1, s3=True,
                                          image_size=128))
    rows = {r["stage"]: r for r in result["rows"]}
    assert {"reconstruct (S3)", "crop (S3)"} <= rows.keys()
    for name in ("reconstruct (S3)", "crop (S3)"):
        assert rows[name]["bytes"] == rows["reconstruct"]["bytes"] and rows[name]["stored"] is None
        assert rows[name]["floor_rate"] > 0 and rows[name]["seconds"] > 0
    assert "| reconstruct (S3) |" in suite.report(result)


def test_a_server_that_exits_at_once_is_started_again_then_named_with_its_log(tmp_path,
                                                                              monkeypatch):
    # a port found free may be taken before the server binds it: it exits, and is started
    # again on other ports; one that never starts is reported with its log's end and status
    import benchmarks.s3server as s3server

    script = tmp_path / "weed"
    script.write_text("#!/bin/sh\necho 'bind: address already in use' >&2\nexit 7\n")
    script.chmod(0o755)
    monkeypatch.setattr(s3server, "weed_binary", lambda: str(script))
    starts = []
    real = s3server._start
    monkeypatch.setattr(s3server, "_start", lambda *a: starts.append(1) or real(*a))
    with pytest.raises(s3server.ServerDidNotStart, match=r"(?s)exit status 7.*address already"):
        s3server.start(tmp_path / "s3")
    assert len(starts) == 3


@pytest.mark.parametrize("opened", ["no", "made",
                                    pytest.param("unpickled", marks=pytest.mark.slow)])
def test_a_process_that_opened_object_storage_lets_foreign_threads_leave_python_at_exit(
        tmp_path, monkeypatch, opened):
    # obstore answers from tokio's threads, which call into Python; one still in such a call
    # when the interpreter finalizes is ended by pthread_exit, which aborts a Rust thread
    # (SIGABRT after the work was done). A thread not started by threading stands in for it:
    # it is inside a Python call (a sleep) when the main thread exits. "unpickled": the store
    # reached the process as a task's argument does (a worker of the processes scheduler)
    import pickle

    monkeypatch.setenv("AWS_REGION", "us-east-1")
    pickled = tmp_path / "store.pickle"
    pickled.write_bytes(pickle.dumps(storage.store("s3://bucket/a.zarr")))
    out = tmp_path / "left python"
    script = ("import _thread, pickle, sys, time\n"
              "from pathlib import Path\n"
              "from pipeline import storage\n"
              f"if {opened!r} == 'made': storage.store('s3://bucket/a.zarr')\n"
              f"if {opened!r} == 'unpickled': pickle.loads(Path({str(pickled)!r}).read_bytes())\n"
              "started = _thread.allocate_lock()\n"
              "started.acquire()\n"
              "def late():\n"
              "    started.release()\n"
              "    time.sleep(2)\n"
              f"    Path({str(out)!r}).write_text('yes')\n"
              "_thread.start_new_thread(late, ())\n"
              "started.acquire()\n")
    subprocess.run([sys.executable, "-c", script], check=True, timeout=60)
    assert out.exists() == (opened != "no")

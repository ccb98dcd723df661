"""Resuming, deterministically: a run that dies after N blocks, then the same command again.

The crash is simulated in-process (the N+1-th block write fails and the partial output is kept,
as a ``kill -9`` keeps it); tests/test_resume.py kills real processes at random moments. The
rerun must write exactly the blocks the crashed run had not finished and give the bits of an
uninterrupted run.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import zarr

import pipeline.graphs.blocks as blocks
from helpers import SLOW_CLUSTER, SLOW_PROCESSES, Killed, killed_before_unit
from pipeline.cli import main
from pipeline.resume import CREATED, DONE, Progress


class Crash(Exception):
    pass


def _writes(monkeypatch, fail_after: int | None = None) -> list:
    """Count block writes (and fail the one after ``fail_after``, keeping the partial output)."""
    original, written = blocks._write_block, []

    def write(block, target, region):
        if fail_after is not None and len(written) >= fail_after:
            raise Crash("killed")
        original(block, target, region)
        written.append(region)

    monkeypatch.setattr(blocks, "_write_block", write)
    if fail_after is not None:
        monkeypatch.setattr("pipeline.atomic._remove", lambda path: None)
    return written


def _arrays(path: Path, names) -> dict:
    g = zarr.open_group(path, mode="r")
    return {n: g[n][...] for n in names}


def _crash_then_resume(tmp_path, monkeypatch, capsys, args, names, crash_after=3):
    ref, out = tmp_path / "ref.zarr", tmp_path / "out.zarr"
    with monkeypatch.context() as m:
        total = _writes(m)
        assert main([*args(ref), "--quiet"]) == 0
    with monkeypatch.context() as m, pytest.raises(Crash):
        _writes(m, fail_after=crash_after)
        main([*args(out), "--quiet"])
    (partial,) = tmp_path.glob(".out.resume-*")
    markers = [n for n in Progress(partial)._names()  # files, and the lines of logs
               if n != CREATED and not n.startswith("image~")]  # ingest's images
    assert len(markers) == crash_after and not out.exists()
    capsys.readouterr()
    with monkeypatch.context() as m:
        rerun = _writes(m)
        assert main(args(out)) == 0
    assert len(rerun) == len(total) - crash_after  # finished blocks are not written again
    assert "resuming" in capsys.readouterr().err
    expected, got = _arrays(ref, names), _arrays(out, names)
    for n in names:
        assert np.array_equal(expected[n], got[n]), n
    assert not (out / DONE).exists() and not list(tmp_path.glob(".out.resume-*"))


GENERATE = ["--material", "stone", "--size", "40", "--sampling", "hemi:3", "--chunk", "8",
            "--dir-chunk", "2", "--seed", "11", "--scheduler", "synchronous"]


def test_generate_resumes_with_the_blocks_left(tmp_path, monkeypatch, capsys, small_tasks):
    _crash_then_resume(tmp_path, monkeypatch, capsys,
                       lambda out: ["generate", str(out), *GENERATE],
                       ("radiance", "height", "albedo"))


@pytest.mark.slow  # 8.5 s: generate's resume above keeps the path in the default run
def test_crop_and_reconstruct_resume_with_the_blocks_left(tmp_path, monkeypatch, capsys,
                                                          small_abtf, small_tasks):
    _crash_then_resume(tmp_path, monkeypatch, capsys,
                       lambda out: ["crop", str(small_abtf), str(out), "--region",
                                    "4:44,0:40", "--scheduler", "synchronous"],
                       ("radiance", "albedo"))
    compressed = tmp_path / "c.zarr"
    assert main(["compress", str(small_abtf), str(compressed), "--rank", "4", "--quiet"]) == 0
    (tmp_path / "r").mkdir()
    _crash_then_resume(tmp_path / "r", monkeypatch, capsys,
                       lambda out: ["reconstruct", str(compressed), str(out), "--chunk", "8",
                                    "--scheduler", "synchronous"], ("radiance",))


@pytest.mark.slow  # 9 s: kept out of the default run (4 min), run by .ci/run
def test_ingest_resumes_with_the_images_and_blocks_left(tmp_path, monkeypatch, capsys,
                                                        small_abtf, small_tasks):
    layers = tmp_path / "layers"
    assert main(["export", str(small_abtf), str(layers), "--quiet"]) == 0
    (tmp_path / "i").mkdir()
    _crash_then_resume(tmp_path / "i", monkeypatch, capsys,
                       lambda out: ["ingest", str(layers), str(out), "--chunk", "8",
                                    "--scheduler", "synchronous"], ("radiance",))


def test_ingest_of_whole_images_resumes_with_the_blocks_left(tmp_path, monkeypatch, capsys,
                                                             small_abtf):
    """Images that fit a task block (48^2 here) are read and written by one task per block
    (pipeline.graphs.blocks.store_blocks): a block whose write failed is not marked done."""
    layers = tmp_path / "layers"
    assert main(["export", str(small_abtf), str(layers), "--quiet"]) == 0
    (tmp_path / "i").mkdir()
    _crash_then_resume(tmp_path / "i", monkeypatch, capsys,
                       lambda out: ["ingest", str(layers), str(out), "--chunk", "8",
                                    "--dir-chunk", "2", "--scheduler", "synchronous"],
                       ("radiance",))


@pytest.mark.slow  # 13 s: kept out of the default run (4 min), run by .ci/run
def test_a_staged_image_whose_chunk_changed_is_staged_again(tmp_path, monkeypatch, capsys,
                                                            small_abtf, small_tasks):
    """Ingest stages images too large for a task block, then copies them in blocks; a staged
    image of the killed run whose chunk fails its checksum is not trusted: the rerun stages
    every image again and gives the bits of an uninterrupted run."""
    layers = tmp_path / "layers"
    assert main(["export", str(small_abtf), str(layers), "--quiet"]) == 0
    args = ["ingest", str(layers), None, "--chunk", "8", "--scheduler", "synchronous"]
    ref, out = tmp_path / "ref.zarr", tmp_path / "out.zarr"
    assert main([*args[:2], str(ref), *args[3:], "--quiet"]) == 0
    with monkeypatch.context() as m, pytest.raises(Crash):
        _writes(m, fail_after=2)
        main([*args[:2], str(out), *args[3:], "--quiet"])
    (partial,) = tmp_path.glob(".out.resume-*")
    staged = sorted(c for c in partial.glob("_*/c/**/*") if c.is_file())
    assert staged  # every image was staged before the crash
    data = bytearray(staged[-1].read_bytes())
    data[len(data) // 2] ^= 0x10
    staged[-1].write_bytes(bytes(data))
    capsys.readouterr()
    assert main([*args[:2], str(out), *args[3:]]) == 0
    assert "fails its checksum: every unit is done again" in capsys.readouterr().err
    assert np.array_equal(_arrays(ref, ["radiance"])["radiance"],
                          _arrays(out, ["radiance"])["radiance"])


def _killed_after_three_blocks(tmp_path, monkeypatch) -> tuple[Path, list, list]:
    """The reference generate, and the partial output of one stopped at its fourth block.

    Returns the partial output, the blocks it wrote (``(array, region)``) and a list that the
    blocks written after it are added to.
    """
    ref, out = tmp_path / "ref.zarr", tmp_path / "out.zarr"
    assert main(["generate", str(ref), *GENERATE, "--quiet"]) == 0
    original, written, crash = blocks._write_block, [], [True]

    def write(block, target, region):
        if crash[0] and len(written) >= 3:
            raise Crash("killed")
        original(block, target, region)
        written.append((target.path, tuple((r.start, r.stop) for r in region)))

    monkeypatch.setattr(blocks, "_write_block", write)
    with monkeypatch.context() as m, pytest.raises(Crash):
        m.setattr("pipeline.atomic._remove", lambda path: None)
        main(["generate", str(out), *GENERATE, "--quiet"])
    (partial,) = tmp_path.glob(".out.resume-*")
    kept, crash[0] = list(written), False
    written.clear()
    return partial, kept, written


def _flip_a_byte(tmp_path, partial, name, region) -> None:
    chunks = zarr.open_array(tmp_path / "ref.zarr" / name).chunks
    chunk = partial / name / "c" / "/".join(str(a // c) for (a, _), c in zip(region, chunks,
                                                                            strict=True))
    data = bytearray(chunk.read_bytes())
    data[len(data) // 2] ^= 0x01
    chunk.write_bytes(bytes(data))


def test_blocks_a_killed_process_wrote_on_this_machine_are_kept_unread(tmp_path, monkeypatch,
                                                                       small_tasks):
    """A process killed since the machine last started lost nothing it wrote: its blocks are
    kept without reading them back."""
    _, kept, written = _killed_after_three_blocks(tmp_path, monkeypatch)

    def intact(target, region):
        raise AssertionError(f"{target.path} {region} read back")

    monkeypatch.setattr(blocks, "_intact", intact)
    assert main(["generate", str(tmp_path / "out.zarr"), *GENERATE, "--quiet"]) == 0
    assert written and not set(kept) & set(written)
    names = ("radiance", "height", "albedo")
    expected, got = _arrays(tmp_path / "ref.zarr", names), _arrays(tmp_path / "out.zarr", names)
    for n in names:
        assert np.array_equal(expected[n], got[n]), n


@pytest.mark.parametrize("scheduler", ["synchronous", "threads", SLOW_PROCESSES,
                                       SLOW_CLUSTER])
def test_a_kept_block_whose_chunk_changed_is_written_again(tmp_path, monkeypatch, small_tasks,
                                                           scheduler, request):
    """After the machine started again, a marker whose data did not survive (bit rot, a
    crash) is not trusted: the task that checks the kept block makes it again, on any
    scheduler."""
    from pipeline import resume

    rerun = ["--scheduler", request.getfixturevalue("local_cluster")
             if scheduler == "cluster" else scheduler]
    ref, out = tmp_path / "ref.zarr", tmp_path / "out.zarr"
    partial, kept, written = _killed_after_three_blocks(tmp_path, monkeypatch)
    name, region = kept[0]
    _flip_a_byte(tmp_path, partial, name, region)
    monkeypatch.setattr(resume, "_boot", lambda: "a-later-boot")
    assert main(["generate", str(out), *GENERATE, *rerun, "--quiet"]) == 0
    if scheduler in ("synchronous", "threads"):  # other processes' writes are not seen here
        assert (name, region) in written  # the damaged block, written again
        assert not set(kept[1:]) & set(written)  # the intact ones kept
    names = ("radiance", "height", "albedo")
    expected, got = _arrays(ref, names), _arrays(out, names)
    for n in names:
        assert np.array_equal(expected[n], got[n]), n


def test_the_fault_campaign_says_what_differs_in_a_run_that_is_not_identical():
    """A faulted run's outputs against the reference: the arrays that differ, how many values,
    how many of them read as NaN (a missing chunk), and the box that holds them."""
    from benchmarks.faults import differences, same

    ref = {"m.zarr/radiance": np.arange(24, dtype="float32").reshape(2, 3, 4),
           "m.zarr/light": np.arange(3), "s.zarr/x": np.zeros(2, "float32")}
    run = {k: v.copy() for k, v in ref.items()}
    assert same(run, ref) and differences(run, ref) == []
    run["m.zarr/radiance"][1, 1:3, 2:4] = np.nan
    run["m.zarr/radiance"][1, 2, 3] = -1.0
    run["m.zarr/light"] = np.arange(4)
    del run["s.zarr/x"]
    run["t.zarr/y"] = np.ones(1)
    assert not same(run, ref)
    assert differences(run, ref) == [
        "s.zarr/x: only in the reference", "t.zarr/y: only in the faulted run",
        "m.zarr/light: int64(4,) against int64(3,)",
        "m.zarr/radiance[2, 3, 4]: 4 value(s) differ, 3 of them NaN in the faulted run, "
        "within [1:2, 1:3, 2:4]"]


def test_a_resumed_tile_set_whose_kept_chunk_changed_is_written_again(tmp_path, monkeypatch,
                                                                     capsys):
    """Quilting resumes with the groups of writes left; but if a chunk the killed run wrote
    fails its checksum (a machine crash, bit rot), it starts over, so the tile set still has
    the bits of an uninterrupted run."""
    sample = tmp_path / "stone.zarr"
    assert main(["generate", str(sample), "--material", "stone", "--size", "64", "--sampling",
                 "hemi:3", "--chunk", "32", "--dir-chunk", "2", "--quiet"]) == 0
    args = ["quilt", str(sample), "--block", "16", "--overlap", "4", "--candidates",
            "4", "--seed", "3", "--scheduler", "synchronous", "--quiet"]
    ref, out = tmp_path / "ref.zarr", tmp_path / "out.zarr"
    assert main([*args[:2], str(ref), *args[2:]]) == 0
    with monkeypatch.context() as m, pytest.raises(Killed):
        killed_before_unit(m, 2, "write-")
        m.setattr("pipeline.atomic._remove", lambda path: None)
        main([*args[:2], str(out), *args[2:]])
    (partial,) = tmp_path.glob(".out.resume-*")
    assert len([p for p in (partial / DONE).iterdir() if p.name != CREATED]) == 2
    ref_group = zarr.open_group(ref, mode="r")
    arrays = {p: a for p, a in ref_group.members(max_depth=None) if isinstance(a, zarr.Array)}
    # a chunk of the radiance a kept group wrote, one byte flipped
    name = next(p for p in arrays if p.endswith("radiance"))
    chunk = next(c for c in sorted((partial / name / "c").rglob("*")) if c.is_file())
    # and one the skeleton wrote (a coordinate): starting over makes it again too
    for damaged in (chunk, next((partial / "theta_light" / "c").rglob("*"))):
        data = bytearray(damaged.read_bytes())
        data[len(data) // 2] ^= 0x10
        damaged.write_bytes(bytes(data))
    capsys.readouterr()
    assert main([*args[:2], str(out), *args[2:-1]]) == 0
    said = capsys.readouterr().err
    assert f"quilt: resuming: {name} chunk (" in said, said  # the first, by path
    assert "(and 1 more) of the killed run fails its checksum: starting over" in said, said
    got = zarr.open_group(out, mode="r")
    for p, a in arrays.items():
        assert np.array_equal(a[...], got[p][...], equal_nan=a.dtype.kind == "f"), p


def test_a_resumed_quilt_keeps_the_plan_the_killed_run_stored(tmp_path, monkeypatch, capsys):
    """A quilt killed while it applies its plan resumes without planning again (the plan is
    read back from the partial output) and gives the bits of an uninterrupted run."""
    sample = tmp_path / "stone.zarr"
    assert main(["generate", str(sample), "--material", "stone", "--size", "64", "--sampling",
                 "hemi:3", "--chunk", "32", "--dir-chunk", "2", "--quiet"]) == 0
    args = ["--block", "16", "--overlap", "4", "--corners", "2", "--seed", "3",
            "--scheduler", "synchronous"]
    ref, out = tmp_path / "ref.zarr", tmp_path / "out.zarr"
    assert main(["quilt", str(sample), str(ref), *args, "--quiet"]) == 0
    with monkeypatch.context() as m, pytest.raises(Killed):
        killed_before_unit(m, 1, "write-")
        m.setattr("pipeline.atomic._remove", lambda path: None)
        main(["quilt", str(sample), str(out), *args, "--quiet"])
    capsys.readouterr()
    with monkeypatch.context() as m:
        def no_planning(*a, **k):
            raise AssertionError("planned again")

        m.setattr("pipeline.stages.quilt.plan_first", no_planning)
        m.setattr("pipeline.stages.quilt.compute_reference", no_planning)
        assert main(["quilt", str(sample), str(out), *args]) == 0
    said = capsys.readouterr().err
    assert "quilt: resuming: the plan the killed run stored is kept" in said, said
    a, b = zarr.open_group(ref, mode="r"), zarr.open_group(out, mode="r")
    arrays = [p for p, x in a.members(max_depth=None) if isinstance(x, zarr.Array)]
    assert "radiance" in arrays and "prescription_index" in arrays
    for p in arrays:
        assert np.array_equal(a[p][...], b[p][...], equal_nan=a[p].dtype.kind == "f"), p
    keep = {"provenance", "btf_every_chunk"}
    assert {k: v for k, v in a.attrs.items() if k not in keep} == \
        {k: v for k, v in b.attrs.items() if k not in keep}


@pytest.mark.slow
def test_btf_bench_writes_puts_every_stage_beside_zarrs_floor(tmp_path, capsys):
    import json

    from benchmarks.cli import main as bench

    out = tmp_path / "w.json"
    assert bench(["writes", "--texels", "16", "--components", "2", "--dir-chunks", "64",
                  "--repeat", "1", "--image-size", "128", "--json", str(out)]) == 0
    assert "vs floor" in capsys.readouterr().out
    result = json.loads(out.read_text())
    assert [r["stage"] for r in result["rows"]] == ["reconstruct", "ingest --radiance", "crop",
                                                    "generate", "ingest", "quilt",
                                                    "quilt apply", "roller apply", "render"]
    sizes = {"ingest": 192 * 128 * 128 * 3 * 4, "quilt": 48 * 240 * 240 * 3 * 4,
             "quilt apply": 48 * 240 * 240 * 3 * 4, "roller apply": 4 * 48 * 128 * 128 * 3 * 4,
             "render": 2048 * 2048 * 3 * 4}
    for r in result["rows"]:
        assert r["bytes"] == sizes.get(r["stage"], 151 * 151 * 16 * 16 * 3 * 4)
        assert r["floor_rate"] > 0 and r["rate"] == pytest.approx(r["bytes"] / r["seconds"])
        # the floor's process holds its writes
        assert r["floor_process_seconds"] > r["bytes"] / r["floor_rate"]


def test_stored_checksums_are_checked_without_decoding_and_catch_a_flipped_bit(tmp_path):
    from helpers import generate_store

    store = generate_store(tmp_path / "s.zarr", "--material", "stone", "--size", "32",
                           "--sampling", "abtf:4,1", "--chunk", "16", "--dir-chunk", "2")
    from pipeline.stores.groups import writable

    radiance = zarr.open_group(store, mode="r+")["radiance"]
    whole = tuple(slice(0, n) for n in radiance.shape)
    assert blocks._stored_sums_match(radiance, whole) is True
    # as a resumed stage opens its partial output: inside btf's store wrapper
    assert blocks._stored_sums_match(writable(str(store))["radiance"], whole) is True
    chunk = store / "radiance" / radiance.metadata.encode_chunk_key((0, 1, 1, 0, 0))
    data = bytearray(chunk.read_bytes())
    data[len(data) // 3] ^= 0x10
    chunk.write_bytes(bytes(data))
    assert blocks._stored_sums_match(radiance, whole) is False
    other = (slice(0, 1), slice(0, 2), slice(0, 16), slice(0, 16), slice(0, 3))
    assert blocks._stored_sums_match(radiance, other) is True  # that chunk is not in it
    assert not blocks._intact(radiance, whole)
    chunk.unlink()  # a chunk never written
    assert blocks._stored_sums_match(radiance, whole) is False
    sharded = generate_store(tmp_path / "h.zarr", "--material", "stone", "--size", "32",
                             "--sampling", "abtf:4,1", "--chunk", "8", "--shard", "16")
    array = zarr.open_group(sharded, mode="r")["radiance"]
    assert blocks._stored_sums_match(array, whole) is None  # read back instead
    assert blocks._intact(array, whole)


def test_blocks_are_marked_done_by_whole_lines_of_each_process_log(tmp_path):
    """A store's blocks are marked in a log per process, not a file each: every whole line
    of every log counts, a last line a kill cut short does not; the results of other units
    stay files."""
    import os
    import socket

    from pipeline import resume

    progress = Progress(tmp_path / "partial")
    progress.mark_created()
    for name in ("radiance/0.0", "radiance/0.1"):
        assert resume.mark_done(7, progress.marker(name), logged=True) == 7
    resume.mark_done({"pass": 1}, progress.marker("pass-1"))  # a result kept: a file
    folder = tmp_path / "partial" / DONE
    logs = sorted(p.name for p in folder.iterdir() if p.name.endswith(".log"))
    assert len(logs) == 1 and logs[0].startswith(".done-")
    assert sorted(p.name for p in folder.iterdir() if not p.name.endswith(".log")) == \
        [CREATED, "pass-1"]
    # another process's log (a killed run's, with this pid in a container, or another
    # host's), its last line cut short by a kill: this process's lines never follow it
    (folder / f".done-{socket.gethostname()}-{os.getpid()}-0.log").write_bytes(
        b"radiance~1.0\nradiance~1.")
    names = ["radiance/0.0", "radiance/0.1", "radiance/1.0", "radiance/1.1", "pass-1"]
    assert progress.finished(names) == ["radiance/0.0", "radiance/0.1", "radiance/1.0",
                                        "pass-1"]
    (folder / "pass-2.partial").write_bytes(b"a running total: no finished unit")
    assert progress.count() == 4
    assert progress.done("radiance/1.0") and not progress.done("radiance/1.1")
    assert progress.memo("pass-1", lambda: None) == ({"pass": 1}, True)
    resume.mark_done(None, progress.marker("radiance/1.1"), logged=True)
    assert (folder / logs[0]).read_bytes() == b"radiance~0.0\nradiance~0.1\nradiance~1.1\n"
    assert progress.finished(names) == names

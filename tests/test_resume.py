"""kill -9 in the middle of a long stage, then the same command again: it resumes.

Each stage runs once uninterrupted (the reference, timed), then several times killed with
SIGKILL at seeded random moments within its run time and rerun to completion. The rerun must
give the reference's bits, leave no partial output behind, say that it resumed whenever the
killed run had finished units of work, and leave the chunk files of those units as they were
(they are not written again). Slow (every stage several times): run by CI with ``-m slow``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import zarr

from benchmarks.harness import run_until
from helpers import btf_process, generate_store
from pipeline.resume import CREATED, DONE, Progress

BIN = Path(sys.executable).parent
pytestmark = pytest.mark.slow
KILLS = 2  # random kill points per stage (new ones every run: CI adds them up)


def _btf(args: list, log: Path, *, mark: str, kill_at: float | None = None, kill_when=None
         ) -> tuple[bool, float, float]:
    return run_until([BIN / "btf", *args], log, mark=mark, kill_at=kill_at, kill_when=kill_when)


def _partial(out: Path) -> Path | None:
    found = list(out.parent.glob(f".{out.stem}.resume-*"))
    assert len(found) <= 1, found
    return found[0] if found else None


def _files(root: Path) -> dict[str, int]:
    """Data files under ``root`` (no metadata, no markers) and their modification times."""
    return {str(p.relative_to(root)): p.stat().st_mtime_ns for p in root.rglob("*")
            if p.is_file() and p.name != "zarr.json" and DONE not in p.parts}


def _finished_units(out: Path) -> list[str]:
    """The units marked done in the partial output of ``out`` (none if there is no partial):
    marker files and the lines of the processes' logs."""
    partial = _partial(out)
    if partial is None or not (partial / DONE).is_dir():
        return []
    return sorted(Progress(partial)._names() - {CREATED})


def _same(a: Path, b: Path, arrays: tuple[str, ...]) -> None:
    ga, gb = zarr.open_group(a, mode="r"), zarr.open_group(b, mode="r")
    for name in arrays:
        assert np.array_equal(ga[name][...], gb[name][...]), name


def _kill_and_resume(tmp_path: Path, args, arrays: tuple[str, ...], *, mark: str,
                     resumed_says: str, seed: int) -> None:
    """Kill at seeded random moments of the work after ``mark``, rerun, compare.

    If no random kill landed after a unit of work was finished (a loaded machine shifts the
    moments), one more run is killed as soon as its first unit is marked done, so the resume
    path is always exercised.
    """
    ref = tmp_path / "ref.zarr"
    _, seen, end = _btf(args(ref), tmp_path / "ref.log", mark=mark)
    work = end - seen
    rng = np.random.default_rng(seed)
    moments = sorted(rng.uniform(0.2, 0.9, KILLS) * work)
    resumed = 0
    for i in range(KILLS + 1):
        out = tmp_path / f"run{i}.zarr"
        if i < KILLS:
            kill = {"kill_at": moments[i]}
        elif not resumed:
            kill = {"kill_when": lambda out=out: bool(_finished_units(out))}
        else:
            break
        _btf(args(out), tmp_path / f"killed{i}.log", mark=mark, **kill)
        if out.exists():  # killed after the output was in place (or not killed at all)
            _same(ref, out, arrays)
            continue
        done = _finished_units(out)
        before = _files(_partial(out)) if done else {}
        log = tmp_path / f"rerun{i}.log"
        _btf(args(out), log, mark=mark)
        _same(ref, out, arrays)
        assert _partial(out) is None  # the partial output became the output
        if done:
            resumed += 1
            assert resumed_says in log.read_text(), log.read_text()
            after = _files(out)
            kept = [f for f, t in before.items() if after.get(f) == t]
            assert kept, "the finished units' files were written again"
    assert resumed, "no kill landed after a unit of work was done"


def test_generate_resumes_after_kill_9(tmp_path):
    def args(out):
        return ["generate", out, "--material", "wood", "--size", "384", "--sampling",
                "abtf:12,4", "--chunk", "64", "--seed", "3"]

    _kill_and_resume(tmp_path, args, ("radiance", "height", "albedo", "roughness", "specular"),
                     mark="layers of", resumed_says="generate: resuming an interrupted run",
                     seed=1)


@pytest.fixture(scope="module")
def wood384(tmp_path_factory) -> Path:
    """The generate test's store, made once for the three compress tests (never written)."""
    return generate_store(tmp_path_factory.mktemp("wood384") / "s.zarr", "--material", "wood",
                          "--size", "384", "--sampling", "abtf:12,4", "--chunk", "64",
                          "--seed", "3")


@pytest.mark.parametrize("sketch", ["texels", "rows", "one pass"])
def test_compress_resumes_after_kill_9(tmp_path, sketch, wood384):
    src = wood384
    # one pass: the sketch (its scratch kept in the partial output), V from it, verification
    mode = (["--passes", "1", "--oversample", "17"] if sketch == "one pass"
            else ["--power-iters", "4", "--sketch", sketch])

    def args(out):
        return ["compress", src, out, "--rank", "16", *mode, "--verify"]

    _kill_and_resume(tmp_path, args, ("U", "S", "V"), mark="pass 1/",
                     resumed_says="kept from the interrupted run", seed=2)


def test_quilt_resumes_after_kill_9(tmp_path):
    src = generate_store(tmp_path / "s.zarr", "--material", "wood", "--size", "256",
                         "--sampling", "abtf:12,4", "--chunk", "64", "--dir-chunk", "4",
                         "--seed", "3")

    def args(out):
        return ["quilt", src, out, "--block", "32", "--overlap", "8", "--size", "240,240"]

    _kill_and_resume(tmp_path, args, ("radiance",), mark="applying", resumed_says="resuming:",
                     seed=3)


def test_tiled_enlargement_resumes_after_kill_9(tmp_path):
    from pipeline.cli import main

    m = generate_store(tmp_path / "M.zarr", "--material", "wood", "--size", "256",
                       "--sampling", "abtf:12,4", "--seed", "1")
    top = int(np.argmin(zarr.open_group(m)["theta_light"][...]))
    for a in (["crop", m, tmp_path / "S.zarr", "--region", "64:192,64:192"],
              ["compress", tmp_path / "S.zarr", tmp_path / "S_svd.zarr", "--rank", "16"],
              ["crop", m, tmp_path / "C.zarr", "--light", str(top)]):
        assert main([str(v) for v in a] + ["--quiet"]) == 0, a

    def args(out):
        return ["enlarge", tmp_path / "S_svd.zarr", tmp_path / "C.zarr", out, "--tile", "64"]

    _kill_and_resume(tmp_path, args, ("U", "S", "V"), mark="level 1/",
                     resumed_says="finished by the interrupted run", seed=4)


@pytest.mark.distributed
def test_btf_bench_faults_finishes_a_run_after_each_kind_of_fault(tmp_path):
    """The fault campaign's small form (``btf bench faults``, one run per mode): kill -9 of
    the client, of a cluster worker, a restart of the S3 server, kill -9 of a cluster's
    client; each run is finished by its reruns with the bits of an undisturbed local run."""
    out = tmp_path / "faults.json"
    seed = np.random.SeedSequence().entropy % 2**32  # new fault moments every run: say which
    done = btf_process("bench", "faults", "--runs", "1", "--seed", str(seed), "--json", out,
                       timeout=900)
    assert done.returncode == 0, (seed, done.stderr)
    result = json.loads(out.read_text())
    assert [m["mode"] for m in result["modes"]] == ["client", "worker", "s3", "cluster-client"]
    for m in result["modes"]:
        assert m["undisturbed_identical"], (seed, m["mode"])
        (row,) = m["runs"]
        assert row["done"] and row["identical"], (seed, m["mode"], row)
    assert "| client | 1 | " in done.stdout and "| cluster-client | 1 | " in done.stdout

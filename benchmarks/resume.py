"""Resuming after ``kill -9``: how long the rerun takes against the work left.

Each stage runs once uninterrupted; then, for every fraction f, it is killed (SIGKILL) once a
fraction f of its work has passed (work: from the stage's first log line of real work to its
end; before it come start-up, reading the inputs and planning, which a rerun does again) and
rerun to completion. A rerun that resumes well takes about start-up plus (1 - f) of the work.
The resumed output is compared with the uninterrupted one, bit for bit.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.harness import btf_executable, generate_store, git_revision, machine, run_until

SUITE = "resume"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of the suite."""
    parser.add_argument("--fractions", default="0.25,0.5,0.75",
                        help="fractions of the work after which the run is killed")
    parser.add_argument("--size", type=int, default=1024,
                        help="texels per side of the generated and compressed store")
    parser.add_argument("--kills", type=int, default=1,
                        help="kills and reruns per fraction, and uninterrupted runs per stage "
                             "(their median is the reference); the table gives each rerun and "
                             "the median and worst (default 1)")
    parser.add_argument("--stages",
                        default="generate,compress,quilt,enlarge,reconstruct,crop,ingest",
                        help="resumable stages to kill and rerun (default: every one)")


def _stages(tmp: Path, size: int) -> dict:
    """``(arguments for an output, log mark of the work, arrays to compare)`` per stage."""
    btf = btf_executable()
    src = tmp / "src.zarr"
    small = tmp / "small.zarr"
    return {
        # the case (issue 56: 768 chunks, 8.7 s on 2 cores)
        "generate": (lambda out: [btf, "generate", out, "--material", "wood", "--size", size,
                                  "--sampling", "abtf:24,8", "--chunk", "128", "--seed", "3"],
                     "layers of", ("radiance",)),
        "compress": (lambda out: [btf, "compress", src, out, "--rank", "32", "--sketch", "rows"],
                     "pass 1/", ("U", "S", "V")),
        "quilt": (lambda out: [btf, "quilt", small, out, "--block", "32", "--overlap", "8",
                               "--size", "960,960"], "applying", ("radiance",)),
        "enlarge": (lambda out: [btf, "enlarge", tmp / "S_svd.zarr", tmp / "C.zarr", out,
                                 "--tile", "128"], "level 1/", ("U", "S", "V")),
        "reconstruct": (lambda out: [btf, "reconstruct", tmp / "wide_svd.zarr", out],
                        "layers of", ("radiance",)),
        "crop": (lambda out: [btf, "crop", tmp / "wide.zarr", out, "--region",
                              f"{size // 8}:{size - size // 8},{size // 8}:{size - size // 8}"],
                 "layers of", ("radiance",)),
        "ingest": (lambda out: [btf, "ingest", tmp / "exr", out], "layers of", ("radiance",)),
    }


def _inputs(tmp: Path, size: int, stages: set[str]) -> None:
    import zarr

    from pipeline.cli import main

    if stages & {"compress"}:
        generate_store(tmp / "src.zarr", "wood", size, "abtf:12,4")
    # the stages that copy or expand radiance: 4x the layers, so that their work outlasts
    # their start-up (abtf:12,4's 48 layers of 1024^2 reconstruct in 3 s)
    if stages & {"reconstruct", "crop"}:
        generate_store(tmp / "wide.zarr", "wood", size, "abtf:24,8")
    if stages & {"reconstruct"}:
        assert main([str(v) for v in ["compress", tmp / "wide.zarr", tmp / "wide_svd.zarr",
                                      "--rank", "32", "--quiet"]]) == 0
    if stages & {"ingest"}:  # a folder of EXR layers (exact float32) and its manifest
        layers = generate_store(tmp / "layers.zarr", "wood", size // 2, "abtf:24,8")
        assert main([str(v) for v in ["export", layers, tmp / "exr", "--quiet"]]) == 0
    if stages & {"quilt"}:  # light chunks of 4: 48 blocks of layers to write
        subprocess.run([btf_executable(), "generate", tmp / "small.zarr", "--material", "wood",
                        "--size", "256", "--sampling", "abtf:24,8", "--dir-chunk", "4",
                        "--quiet"], check=True)
    if stages & {"enlarge"}:
        m = generate_store(tmp / "M.zarr", "wood", 512, "abtf:12,4")
        top = int(np.argmin(zarr.open_group(m)["theta_light"][...]))
        for a in (["crop", m, tmp / "S.zarr", "--region", "192:320,192:320"],
                  ["compress", tmp / "S.zarr", tmp / "S_svd.zarr", "--rank", "32"],
                  ["crop", m, tmp / "C.zarr", "--light", str(top)]):
            assert main([str(v) for v in a] + ["--quiet"]) == 0, a


def _same(a: Path, b: Path, arrays) -> bool:
    import zarr

    ga, gb = zarr.open_group(a, mode="r"), zarr.open_group(b, mode="r")
    return all(np.array_equal(ga[n][...], gb[n][...]) for n in arrays)


def run(args: argparse.Namespace) -> dict:
    """All measurements of the suite, in one run."""
    fractions = [float(f) for f in args.fractions.split(",") if f]
    wanted = [s for s in args.stages.split(",") if s]
    result = {"suite": SUITE, "stages": {}, "machine": machine(), "git": git_revision()}
    with tempfile.TemporaryDirectory(prefix="btf-bench-resume-") as tmp:
        tmp = Path(tmp)
        _inputs(tmp, args.size, set(wanted))
        stages = _stages(tmp, args.size)
        for name in wanted:
            argv, mark, arrays = stages[name]
            whole = []
            for k in range(max(1, args.kills)):
                ref = tmp / f"{name}-ref{'' if k == 0 else k}.zarr"
                whole.append(run_until(argv(ref), tmp / "log", mark=mark)[1:])
                if k:
                    shutil.rmtree(ref)
            seen, total = (float(np.median([w[i] for w in whole])) for i in (0, 1))
            rows = []
            for f, k in ((f, k) for f in fractions for k in range(max(1, args.kills))):
                out = tmp / f"{name}-{f}-{k}.zarr"
                killed, _, _ = run_until(argv(out), tmp / "log", mark=mark,
                                         kill_at=f * (total - seen))
                if out.exists():  # it finished (moved its output into place) before the kill
                    rows.append({"fraction": f, "killed": False,
                                 "identical": _same(tmp / f"{name}-ref.zarr", out, arrays)})
                    shutil.rmtree(out)
                    continue
                _, _, rerun = run_until(argv(out), tmp / "log", mark=mark)
                rows.append({"fraction": f, "killed": killed, "rerun_seconds": rerun,
                             "identical": _same(tmp / f"{name}-ref.zarr", out, arrays),
                             "resumed": "resum" in (tmp / "log").read_text()
                             or "kept from" in (tmp / "log").read_text()
                             or "finished by the interrupted" in (tmp / "log").read_text()})
                if out.exists():
                    shutil.rmtree(out)
            result["stages"][name] = {"seconds": total, "before_work": seen, "runs": rows,
                                      "uninterrupted_runs": [w[1] for w in whole]}
    return result


def report(result: dict) -> str:
    """Markdown table of a result."""
    lines = ["| stage | uninterrupted s | before the work s | killed after | rerun s | "
             "rerun / uninterrupted | (before + work left) / uninterrupted | resumed | "
             "identical |", "|---|---|---|---|---|---|---|---|---|"]
    for name, stage in result["stages"].items():
        total, before = stage["seconds"], stage["before_work"]
        for r in stage["runs"]:
            if not r["killed"]:
                lines.append(f"| {name} | {total:.1f} | {before:.1f} | {r['fraction']:.0%} of "
                             "the work | (finished before the kill) | | | | "
                             f"{'yes' if r['identical'] else 'NO'} |")
                continue
            expected = (before + (1 - r["fraction"]) * (total - before)) / total
            lines.append(f"| {name} | {total:.1f} | {before:.1f} | {r['fraction']:.0%} of the "
                         f"work | {r['rerun_seconds']:.1f} | {r['rerun_seconds'] / total:.2f} | "
                         f"{expected:.2f} | {'yes' if r['resumed'] else 'no'} | "
                         f"{'yes' if r['identical'] else 'NO'} |")
    summary = []
    for name, stage in result["stages"].items():
        for f in sorted({r["fraction"] for r in stage["runs"]}):
            ratios = [r["rerun_seconds"] / stage["seconds"] for r in stage["runs"]
                      if r["fraction"] == f and r["killed"]]
            if len(ratios) > 1:
                summary.append(f"- {name}, killed after {f:.0%}: rerun / uninterrupted median "
                               f"{np.median(ratios):.2f}, worst {max(ratios):.2f} over "
                               f"{len(ratios)} kills (uninterrupted: median of "
                               f"{len(stage['uninterrupted_runs'])} runs, "
                               + ", ".join(f"{t:.1f}" for t in stage["uninterrupted_runs"])
                               + " s)")
    return "\n".join(lines + (["", *summary] if summary else []))

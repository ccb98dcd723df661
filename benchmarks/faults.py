"""Faults survived, counted: btf run under kill -9 of the client, of a worker, and a restart of
the object store, each at a random moment, then the same command again until it is done.

The campaign's config covers generate, crop, compress in both modes (three passes and
``--passes 1``), enlarge, quilt (a corner tile set) and scene. For every mode an undisturbed
run gives the mode's reference time and the time of each stage; then each of ``--runs`` runs
gets one fault at a moment drawn uniformly over that time (``--seed``), and the same
``btf run`` command is started again until it exits 0, at most ``--reruns`` times.

- *identical*: every array of every output equals the undisturbed local run's, bit for bit;
- *needed a human*: not finished within ``--reruns`` reruns, or outputs that differ;
- *time lost*: the run's time with its reruns minus the mode's undisturbed time, set against
  the undisturbed time of the stage the fault hit (the goal: no more than that stage's time).

Modes:

- ``client``: SIGKILL of ``btf run`` (threads scheduler, outputs on the local disk);
- ``worker``: SIGKILL of one of the two single-threaded ``dask worker --no-nanny`` processes
  of a local cluster (loopback); a new worker takes its place before the next run;
- ``s3``: outputs in a SeaweedFS bucket on loopback (:mod:`benchmarks.s3server`), whose
  server is stopped (SIGTERM) at the moment and started again on the same ports and data
  ``--down`` seconds later;
- ``cluster-client``: SIGKILL of ``btf run`` while it drives the local cluster of ``worker``
  (outputs on the local disk): its workers live on, and the tasks they were running may still
  write into the partial output while the rerun starts.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from benchmarks.harness import btf_executable, git_revision, machine, stop_processes

SUITE = "faults"
MODES = ("client", "worker", "s3", "cluster-client")
STORES = ("m.zarr", "sample.zarr", "photo.zarr", "sample_svd.zarr", "m_svd.zarr",
          "enlarged.zarr", "tiles.zarr", "scene.zarr")
STAGE_LINE = re.compile(r"^\[(\d+)/(\d+)\] (\w+)", re.M)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of the suite."""
    parser.add_argument("--runs", type=int, default=20, help="faulted runs per mode (default 20)")
    parser.add_argument("--modes", default=",".join(MODES),
                        help=f"comma-separated, of {', '.join(MODES)} (default: all)")
    parser.add_argument("--size", type=int, default=64,
                        help="texels per side of the generated store (default 64)")
    parser.add_argument("--reruns", type=int, default=3,
                        help="reruns after a fault before the run counts as needing a human "
                             "(default 3)")
    parser.add_argument("--down", type=float, default=5.0,
                        help="seconds the object store stays down in mode s3 (default 5)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the fault moments")
    parser.add_argument("--work", metavar="DIR", help="keep every run's config, log and (local) "
                        "outputs in DIR, which must not exist (default: a temporary folder, "
                        "removed at the end)")


def config_text(root: str, scene: Path, size: int) -> str:
    """The campaign's ``btf run`` config, its outputs under ``root`` (a folder or a URL)."""
    q = size // 4
    return f"""stages:
  - generate: {{out: {root}/m.zarr, material: wood, size: {size}, sampling: "abtf:8,3",
               seed: 7}}
  - crop: {{store: {root}/m.zarr, out: {root}/sample.zarr, region: "{q}:{3 * q},{q}:{3 * q}"}}
  - crop: {{store: {root}/m.zarr, out: {root}/photo.zarr, light: [0]}}
  - compress: {{store: {root}/sample.zarr, out: {root}/sample_svd.zarr, rank: 8}}
  - compress: {{store: {root}/m.zarr, out: {root}/m_svd.zarr, rank: 8, passes: 1}}
  - enlarge: {{sample: {root}/sample_svd.zarr, constraints: {root}/photo.zarr,
              out: {root}/enlarged.zarr}}
  - quilt: {{store: {root}/m.zarr, out: {root}/tiles.zarr, corners: 2}}
  - scene: {{scene: {scene}, out: {root}/scene.zarr}}
"""


def scene_text(root: str) -> str:
    """The campaign's scene: two lights on the enlarged store, one between measured ones."""
    return (f"source: {root}/enlarged.zarr\ndirections:\n  - [0, 0, 0, 0]\n"
            "  - [45, 30, 0, 0]\n")


@dataclass
class Attempt:
    """One start of ``btf run``: its exit status (-9: killed) and time; stage start times."""

    code: int
    seconds: float
    fired: bool = False
    stages: list[tuple[str, float]] = field(default_factory=list)


def attempt(argv: list, log: Path, env: dict, *, fault_at: float | None = None,
            fault=None) -> Attempt:
    """Run ``argv`` once; ``fault(proc)`` at ``fault_at`` seconds if it still runs then."""
    start = time.perf_counter()
    stages: list[tuple[str, float]] = []
    fired, partial = False, ""  # partial: the log's last line, still being written
    with log.open("w") as err, log.open() as follow:
        proc = subprocess.Popen([str(a) for a in argv], stdout=subprocess.DEVNULL, stderr=err,
                                env=env)
        while True:
            ended = proc.poll() is not None
            now = time.perf_counter() - start
            lines, _, partial = (partial + follow.read()).rpartition("\n")
            stages += [(m.group(3), now) for m in STAGE_LINE.finditer(lines)]
            if ended:
                break
            if fault_at is not None and not fired and now >= fault_at:
                fault(proc)
                fired = True
            time.sleep(0.02)
    return Attempt(proc.returncode, time.perf_counter() - start, fired, stages)


def arrays(root: str) -> dict[str, np.ndarray]:
    """Every array of every output store under ``root``, by store and path."""
    import zarr

    from pipeline import storage

    out = {}
    for name in STORES:
        url = f"{root}/{name}"
        group = zarr.open_group(storage.store(storage.parse(url)), mode="r",
                                use_consolidated=False)
        for path, array in group.members(max_depth=None):
            if isinstance(array, zarr.Array):
                out[f"{name}/{path}"] = array[...]
    return out


def _outputs(root: str) -> tuple[dict[str, np.ndarray], str | None]:
    """:func:`arrays`, or the error that stopped reading them (a missing or damaged chunk)."""
    from pipeline.errors import BTFError

    try:
        return arrays(root), None
    except BTFError as exc:
        return {}, str(exc)


def same(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> bool:
    """Whether two outputs hold the same arrays, bit for bit (NaN equal to NaN)."""
    return a.keys() == b.keys() and all(_equal(a[k], b[k]) for k in a)


def _equal(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == b.dtype and np.array_equal(a, b, equal_nan=a.dtype.kind == "f")


def differences(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> list[str]:
    """What differs between outputs ``a`` (a faulted run's) and ``b`` (the reference).

    A line per array: how many values differ, how many of those read as NaN in ``a`` where
    ``b`` has a number (what a float array's missing chunk reads as), and the box that holds
    them (index ranges, ends exclusive), to set against the array's chunks.
    """
    lines = [f"{k}: only in the {'faulted run' if k in a else 'reference'}"
             for k in sorted(a.keys() ^ b.keys())]
    for k in sorted(a.keys() & b.keys()):
        x, y = a[k], b[k]
        if _equal(x, y):
            continue
        if x.shape != y.shape or x.dtype != y.dtype:
            lines.append(f"{k}: {x.dtype}{x.shape} against {y.dtype}{y.shape}")
            continue
        floats = x.dtype.kind == "f"
        differ = ~((x == y) | (np.isnan(x) & np.isnan(y))) if floats else x != y
        fill = int((np.isnan(x) & ~np.isnan(y)).sum()) if floats else 0
        where = np.argwhere(differ)
        box = ", ".join(f"{lo}:{hi + 1}" for lo, hi in zip(where.min(0), where.max(0), strict=True))
        lines.append(f"{k}{list(x.shape)}: {len(where)} value(s) differ, {fill} of them NaN in "
                     f"the faulted run, within [{box}]")
    return lines


class Cluster:
    """A dask scheduler and single-threaded ``dask worker --no-nanny`` processes on loopback.

    Without a nanny, a worker killed with SIGKILL is lost for good, as a machine is.
    """

    def __init__(self, folder: Path, workers: int = 2):
        from benchmarks.s3server import free_ports

        self.folder, self.count = folder, workers
        self.bin = Path(sys.executable).parent
        port = free_ports(1)[0]
        self.address = f"tcp://127.0.0.1:{port}"
        self.log = (folder / "cluster.log").open("a")
        self.env = {**os.environ, "PYTHONFAULTHANDLER": "1"}
        self.scheduler = subprocess.Popen(
            [self.bin / "dask", "scheduler", "--host", "127.0.0.1", "--port", str(port),
             "--dashboard-address", "127.0.0.1:0"], stdout=self.log, stderr=self.log,
            env=self.env)
        self.started = 0  # workers started, each in a folder of its own
        self.workers = [self._worker() for _ in range(workers)]
        try:
            self.wait()
        except BaseException:
            self.close()
            raise

    def _worker(self) -> subprocess.Popen:
        home = self.folder / f"worker-{self.started}"
        home.mkdir()
        self.started += 1
        return subprocess.Popen([self.bin / "dask", "worker", self.address, "--nthreads", "1",
                                 "--no-nanny"], cwd=home, stdout=self.log, stderr=self.log,
                                env=self.env)

    def wait(self) -> None:
        """Until every worker has joined the scheduler (60 s at most)."""
        from distributed import Client

        deadline = time.monotonic() + 60
        while True:
            try:
                with Client(self.address, timeout="10s", set_as_default=False) as client:
                    client.wait_for_workers(self.count, timeout=60)
                return
            except OSError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.5)

    def kill_one(self, proc=None) -> None:
        """SIGKILL the first worker (a fault: ``proc``, the run, is left alone)."""
        os.kill(self.workers[0].pid, signal.SIGKILL)

    def replace(self) -> None:
        """A new worker in place of a killed one."""
        if self.workers[0].poll() is not None:
            self.workers[0] = self._worker()
            self.wait()

    def close(self) -> None:
        """Stop the workers, then the scheduler (Ctrl-C, then SIGKILL if they linger)."""
        stop_processes(self.workers, [self.scheduler])
        self.log.close()


def _restart_later(server, down: float, took: list) -> threading.Thread:
    """Stop the S3 server now and start it again ``down`` seconds later (in a thread).

    Appends to ``took`` the seconds from the stop to the server answering again.
    """
    start = time.perf_counter()
    server.halt()

    def resume():
        time.sleep(down)
        server.resume()
        took.append(time.perf_counter() - start)

    thread = threading.Thread(target=resume, daemon=True)
    thread.start()
    return thread


@dataclass
class _Setting:
    """Where one mode's runs write and what they run on."""

    mode: str
    folder: Path
    size: int
    env: dict
    server: object = None  # benchmarks.s3server.S3Server (mode s3)
    cluster: Cluster | None = None  # mode worker

    def root(self, name: str) -> str:
        """Where run ``name`` writes its outputs."""
        return self.server.url(name) if self.server else str(self.folder / name)

    def command(self, name: str) -> list:
        """The ``btf run`` command of run ``name`` (its config and scene written first)."""
        spec = self.folder / f"{name}.scene.yaml"
        spec.write_text(scene_text(self.root(name)))
        config = self.folder / f"{name}.yaml"
        config.write_text(config_text(self.root(name), spec, self.size))
        extra = ["--scheduler", self.cluster.address] if self.cluster else []
        return [btf_executable(), "run", config, *extra]

    def fault(self, down: float, restarts: list, outage: list):
        """The mode's fault, a function of the run's process."""
        if self.mode in ("client", "cluster-client"):
            return lambda proc: proc.send_signal(signal.SIGKILL)
        if self.mode == "worker":
            return self.cluster.kill_one
        return lambda proc: restarts.append(_restart_later(self.server, down, outage))


def _undisturbed(setting: _Setting) -> Attempt:
    """A warm-up run (the workers' imports, the page cache), then the timed undisturbed one."""
    for name in ("warm-up", "undisturbed"):
        run = attempt(setting.command(name), setting.folder / f"{name}.log", setting.env)
        if run.code != 0:
            raise RuntimeError(f"{setting.mode}: the {name} run failed:\n"
                               f"{(setting.folder / f'{name}.log').read_text()[-3000:]}")
    return run


def _faulted(setting: _Setting, i: int, moment: float, args, reference: dict) -> dict:
    """Run ``i``: one fault at ``moment`` seconds, then reruns until it is done."""
    name = f"run{i}"
    argv = setting.command(name)
    restarts: list[threading.Thread] = []
    outage: list[float] = []
    first = attempt(argv, setting.folder / f"{name}.log", setting.env, fault_at=moment,
                    fault=setting.fault(args.down, restarts, outage))
    for thread in restarts:
        thread.join()
    if setting.cluster is not None:
        setting.cluster.replace()
    tries = [first]
    while tries[-1].code != 0 and len(tries) <= args.reruns:
        tries.append(attempt(argv, setting.folder / f"{name}.rerun{len(tries)}.log",
                             setting.env))
    done = tries[-1].code == 0
    found, unreadable = _outputs(setting.root(name)) if done else ({}, None)
    identical = done and unreadable is None and same(found, reference)
    diagnosis = []
    if unreadable is not None:  # a missing chunk or a failed checksum of a finished output
        diagnosis = [f"the outputs do not read: {unreadable}"]
    elif done and not identical:  # what differs, and whether a second read sees the same
        diagnosis = differences(found, reference)
        diagnosis.append("a second read gives the same arrays" if same(
            arrays(setting.root(name)), found) else "a second read gives other arrays")
    return {"run": i, "moment": moment, "fired": first.fired,
            "codes": [t.code for t in tries], "reruns": len(tries) - 1, "done": done,
            "identical": identical, "differences": diagnosis,
            "seconds": sum(t.seconds for t in tries), "attempts": [t.seconds for t in tries],
            "outage": outage[0] if outage else None}


def _mode(mode: str, args, work: Path, reference: dict | None, rng) -> dict:
    """The undisturbed run and ``args.runs`` faulted runs of one mode."""
    from benchmarks import s3server

    setting = _Setting(mode, work / mode, args.size, dict(os.environ))
    setting.folder.mkdir()
    saved = dict(os.environ)
    try:
        if mode == "s3":
            setting.server = s3server.start(setting.folder / "s3")
            setting.env.update(setting.server.environment)
            os.environ.update(setting.server.environment)  # to read the outputs here
        if mode in ("worker", "cluster-client"):
            setting.cluster = Cluster(setting.folder)
        undisturbed = _undisturbed(setting)
        bits = arrays(setting.root("undisturbed"))
        reference = reference or bits
        total = undisturbed.seconds
        starts = [t for _, t in undisturbed.stages] + [total]
        stages = [(n, starts[k + 1] - t) for k, (n, t) in enumerate(undisturbed.stages)]
        rows = []
        for i in range(args.runs):
            moment = float(rng.uniform(0.05, 0.9) * total)
            row = _faulted(setting, i, moment, args, reference)
            hit = max((k for k, (_, t) in enumerate(undisturbed.stages) if t <= moment),
                      default=0)
            lost = row["seconds"] - total
            row.update(stage=stages[hit][0], stage_seconds=stages[hit][1], lost=lost,
                       lost_beyond_outage=lost - (row["outage"] or 0.0))
            rows.append(row)
            print(f"faults {mode} run {i}: fault at {moment:.1f} s in {row['stage']} ("
                  + ("injected" if row["fired"] else "not injected: the run had ended")
                  + f"), exit codes {row['codes']}, "
                  + ("identical" if row["identical"] else "NOT IDENTICAL")
                  + f", {row['lost']:+.1f} s"
                  + (f" (server down {row['outage']:.1f} s)" if row["outage"] else "")
                  + "".join(f"\n  {line}" for line in row["differences"]),
                  file=sys.stderr, flush=True)
        return {"mode": mode, "undisturbed_seconds": total, "stages": stages,
                "start_up": undisturbed.stages[0][1] if undisturbed.stages else 0.0,
                "undisturbed_identical": same(bits, reference), "runs": rows,
                "reference": reference}
    finally:
        if setting.cluster is not None:
            setting.cluster.close()
        if setting.server is not None:
            if args.work:
                shutil.copy(setting.server.folder / "weed.log", setting.folder / "weed.log")
            setting.server.stop()
        os.environ.clear()
        os.environ.update(saved)


def run(args) -> dict:
    """Every mode of the campaign (see the module)."""
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    unknown = sorted(set(modes) - set(MODES))
    if unknown:
        raise SystemExit(f"btf bench faults: unknown mode(s) {', '.join(unknown)}; "
                         f"choose from {', '.join(MODES)}")
    rng = np.random.default_rng(args.seed)
    out, reference = [], None
    with tempfile.TemporaryDirectory(prefix="btf-faults-") as tmp:
        work = Path(args.work) if args.work else Path(tmp)
        work.mkdir(parents=True, exist_ok=not args.work)
        for mode in modes:
            result = _mode(mode, args, work, reference, rng)
            reference = result.pop("reference")
            out.append(result)
    return {"suite": SUITE, "revision": git_revision(), "machine": machine(),
            "size": args.size, "reruns": args.reruns, "down": args.down, "seed": args.seed,
            "modes": out}


def report(result: dict) -> str:
    """Markdown: one row per mode, then the undisturbed stage times."""
    lines = [f"Fault campaign: `btf run` of benchmarks/faults.py's config at {result['size']}^2 "
             f"texels, one fault per run at a random moment (seed {result['seed']}), then "
             f"reruns of the same command (at most {result['reruns']}).", "",
             "| mode | runs | faults injected | finished | identical | needed a human | "
             "reruns 0 / 1 / 2+ | time lost: median / worst (s) | beyond the server's "
             "outage: median / worst (s) | worst lost beyond the outage / its stage's time | "
             "undisturbed run (s): all / its start-up |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for m in result["modes"]:
        rows = m["runs"]
        if not rows:
            continue
        lost = [r["lost"] for r in rows]
        beyond = [r["lost_beyond_outage"] for r in rows]
        worst = max(rows, key=lambda r: r["lost_beyond_outage"])
        reruns = [r["reruns"] for r in rows]
        human = sum(not (r["done"] and r["identical"]) for r in rows)
        ratio = worst["lost_beyond_outage"] / max(worst["stage_seconds"], 1e-9)
        lines.append(
            f"| {m['mode']} | {len(rows)} | {sum(r['fired'] for r in rows)} | "
            f"{sum(r['done'] for r in rows)} | {sum(r['identical'] for r in rows)} | {human} | "
            f"{reruns.count(0)} / {reruns.count(1)} / {sum(n >= 2 for n in reruns)} | "
            f"{np.median(lost):.1f} / {max(lost):.1f} | "
            f"{np.median(beyond):.1f} / {max(beyond):.1f} | {ratio:.2f} ({worst['stage']}, "
            f"{worst['stage_seconds']:.1f} s) | {m['undisturbed_seconds']:.1f} / "
            f"{m['start_up']:.1f}"
            f"{'' if m['undisturbed_identical'] else ' (NOT identical to the local run)'} |")
    lines += ["", "Undisturbed stage times (s): " + "; ".join(
        f"{m['mode']}: " + ", ".join(f"{n} {s:.1f}" for n, s in m["stages"])
        for m in result["modes"])]
    return "\n".join(lines)

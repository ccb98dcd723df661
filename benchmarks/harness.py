"""Measuring commands: wall time and peak resident memory of a fresh process."""

from __future__ import annotations

import json
import platform
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class Measurement:
    """Wall time (s) and peak resident set (bytes) of one command."""

    seconds: float
    peak_rss: int


def measure(argv: list[str]) -> Measurement:
    """Run ``argv`` in a fresh wrapper process; its peak RSS is the command's alone.

    ``ru_maxrss`` of waited-for children is the largest single process, so for the
    ``processes`` scheduler this is the largest worker, not the sum of the process tree.
    """
    code = ("import resource, subprocess, sys, time, json\n"
            "t = time.perf_counter()\n"
            "subprocess.run(sys.argv[1:], check=True)\n"
            "t = time.perf_counter() - t\n"
            "rss = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024\n"
            "print(json.dumps({'seconds': t, 'peak_rss': rss}), file=sys.stderr)\n")
    done = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"benchmark command failed: {' '.join(argv)}\n{done.stderr}")
    return Measurement(**json.loads(done.stderr.strip().splitlines()[-1]))


def best_of(repeat: int, argv: list[str]) -> Measurement:
    """The fastest of ``repeat`` runs (with the peak memory of that run)."""
    return min((measure(argv) for _ in range(max(1, repeat))), key=lambda m: m.seconds)


def fastest(repeat: int, fn) -> tuple[float, object]:
    """The shortest wall time of ``repeat`` calls of ``fn`` in this process, and its result."""
    best, result = float("inf"), None
    for _ in range(max(1, repeat)):
        start = time.perf_counter()
        result = fn()
        best = min(best, time.perf_counter() - start)
    return best, result


def in_threads(threads: int, fn, parts) -> None:
    """``fn(part)`` for every part, on ``threads`` threads (1: in this thread)."""
    if threads == 1:
        for p in parts:
            fn(p)
        return
    with ThreadPoolExecutor(threads) as pool:
        list(pool.map(fn, parts))


def parse_sizes(text: str, suite: str) -> list[int]:
    """The sample sizes of a ``--sizes`` option (``"256,512"``); at least one."""
    values = [int(s) for s in text.split(",") if s.strip()]
    if not values:
        raise SystemExit(f"btf bench {suite}: --sizes needs at least one size")
    return values


def chosen_stages(text: str, known: tuple[str, ...], suite: str) -> list[str]:
    """The comma-separated stages of ``text``; an unknown one stops the suite, naming it."""
    stages = [s for s in text.split(",") if s]
    unknown = sorted(set(stages) - set(known))
    if unknown:
        raise SystemExit(f"btf bench {suite}: unknown stage(s) {', '.join(unknown)}; choose "
                         f"from {', '.join(known)}")
    return stages


def btf_executable() -> str:
    """The ``btf`` console script of the running environment."""
    return str(Path(sys.executable).parent / "btf")


def generate_store(path: Path, material: str, size: int, sampling: str) -> Path:
    """Generate a store with ``btf generate`` (quietly, replacing what is there)."""
    subprocess.run([btf_executable(), "generate", str(path), "--material", material, "--size",
                    str(size), "--sampling", sampling, "--quiet", "--overwrite"], check=True)
    return path


def git_revision() -> str:
    """Short hash of the checked-out commit (empty outside a git checkout)."""
    return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                          text=True).stdout.strip()


# Debian's chromium headless with WebGL2 on the CPU (SwiftShader): the viewer's tests and bench
BROWSER_FLAGS = ["--headless=new", "--no-sandbox", "--use-angle=swiftshader",
                 "--enable-unsafe-swiftshader"]


def machine() -> dict:
    """What the figures were measured on."""
    import os

    return {"python": platform.python_version(), "cpus": os.cpu_count(),
            "platform": platform.platform(), "when": time.strftime("%Y-%m-%d %H:%M")}


def to_json(result: dict) -> str:
    """JSON of a result."""
    return json.dumps(result, indent=2, default=str)


def run_until(argv: list, log: Path, *, mark: str, kill_at: float | None = None,
              kill_when=None) -> tuple[bool, float, float]:
    """Run ``argv`` (stderr to ``log``), timing from when ``mark`` shows in its log.

    With ``kill_at``, SIGKILL it that many seconds after ``mark`` showed; with ``kill_when``
    (a function of nothing), SIGKILL it as soon as that returns true. Returns whether it was
    killed (False: it finished first), when ``mark`` showed and when it ended (seconds from
    the start). A run that fails raises ``RuntimeError`` with its log.
    """
    import signal

    start = time.perf_counter()
    seen = None
    with Path(log).open("w") as err:
        proc = subprocess.Popen([str(a) for a in argv], stdout=subprocess.DEVNULL, stderr=err)
        while proc.poll() is None:
            now = time.perf_counter() - start
            if seen is None and mark in Path(log).read_text():
                seen = now
            if (seen is not None and kill_at is not None and now >= seen + kill_at) \
                    or (kill_when is not None and kill_when()):
                proc.send_signal(signal.SIGKILL)
                proc.wait()
                return True, seen, time.perf_counter() - start
            time.sleep(0.01)
    end = time.perf_counter() - start
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(map(str, argv))} failed:\n{Path(log).read_text()}")
    return False, end if seen is None else seen, end


def stop_processes(*groups: list[subprocess.Popen], timeout: float = 20) -> None:
    """Stop each group of processes in turn, as Ctrl-C does, and kill any that linger.

    A cluster's workers first, then the scheduler they say goodbye to: 0.3 s (SIGTERM: 8 s).
    """
    import signal

    for group in groups:
        for proc in group:
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        for proc in group:
            try:
                proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def store_bytes(store: Path) -> int:
    """Bytes a store's files take on disk."""
    return sum(f.stat().st_size for f in Path(store).rglob("*") if f.is_file())


def drop_page_cache() -> bool:
    """Write dirty pages and drop the page cache (Linux, as root); whether it was dropped."""
    subprocess.run(["sync"], check=False)
    try:
        Path("/proc/sys/vm/drop_caches").write_text("3\n")
    except OSError:
        return False
    return True

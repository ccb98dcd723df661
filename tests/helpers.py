"""Helpers shared by the tests (importable as ``helpers``)."""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from benchmarks.harness import stop_processes
from pipeline.cli import main

# The processes scheduler (a fresh interpreter per worker) and a local cluster, seconds each to
# start, as slow parameters: threads and synchronous stand for them in the default set, and
# .ci/run runs them (the slow set).
SLOW_PROCESSES = pytest.param("processes", marks=pytest.mark.slow)
SLOW_CLUSTER = pytest.param("cluster", marks=[pytest.mark.slow, pytest.mark.distributed])


# float16's rounding of a value, relative: a store of 8-bit or half-float measurements holds
# float16 (each value within this of the float32 decode, and encoding back to its code)
HALF_ROUNDING = 2.0**-11


def stored_dtype(path: Path) -> str:
    """The type a radiance store keeps its layers in."""
    import zarr

    return str(zarr.open_group(path, mode="r")["radiance"].dtype)


def side_lights_brighten_the_slopes_facing_them(ds, bound: float = 0.5) -> None:
    """In a generated store's first view, each lowest light (the sides) brightens the slopes
    facing it (correlation above ``bound``) and darkens those facing away (below -bound)."""
    import numpy as np

    h = ds["height"].values
    theta = ds["theta_light"].values
    for i in np.flatnonzero(theta == theta.max()):
        phi = float(ds["phi_light"].values[i])
        lum = ds["radiance"].values[0, i].mean(axis=-1).ravel()
        towards = np.corrcoef(lum, facing(h, phi).ravel())[0, 1]
        away = np.corrcoef(lum, facing(h, phi + 180).ravel())[0, 1]
        assert towards > bound and away < -bound, (phi, towards, away)


def facing(height, phi: float):
    """How far each texel's surface faces azimuth ``phi`` (degrees): its slope down towards it.

    In the store's frame (docs/formats.md, "The frame"): x along columns, y towards row 0, so
    ``dh/dy`` is minus the gradient along rows. Positive where the surface tilts towards phi.
    """
    import numpy as np

    grow, gx = np.gradient(np.asarray(height, np.float64))
    p = np.radians(phi)
    return -(gx * np.cos(p) - grow * np.sin(p))


def generate_store(path: Path, *args: str) -> Path:
    code = main(["generate", str(path), "--quiet", *args])
    assert code == 0
    return path


def quilt(src: Path, out: Path, *args: str):
    """``btf quilt SRC OUT ARGS --quiet`` in this process; the tile set, opened."""
    import zarr

    assert main(["quilt", str(src), str(out), "--quiet", *map(str, args)]) == 0
    return zarr.open_group(out, mode="r")


def btf_process(*args, env: dict | None = None, cwd: Path | None = None,
                timeout: float = 300) -> subprocess.CompletedProcess:
    """``btf ARGS`` as a separate process (output captured as text), with ``env`` added to
    this process's environment: the one way the tests run btf as a user's shell would."""
    import os

    return subprocess.run([Path(sys.executable).parent / "btf", *map(str, args)],
                          capture_output=True, text=True, env={**os.environ, **(env or {})},
                          cwd=cwd, timeout=timeout)


class Killed(Exception):
    """A run stopped in the middle, in-process (see :func:`killed_before_unit`)."""


def killed_before_unit(monkeypatch, unit: int, marker: str = "") -> None:
    """Make a run raise :class:`Killed` where it would mark its unit number ``unit`` (from 0;
    only units whose marker's name holds ``marker`` count) done, as a ``kill -9`` would stop it
    there. Its partial output stays only if the caller also stops the cleanup.
    """
    import pipeline.resume as resume

    original, kept = resume._keep, []

    def keep(result, at, **how):
        if marker in at:
            if len(kept) == unit:
                raise Killed("killed")
            kept.append(at)
        return original(result, at, **how)

    monkeypatch.setattr(resume, "_keep", keep)


def chromium() -> str:
    """Debian's chromium; skips the test where there is none, fails if BTF_REQUIRE_BROWSER."""
    found = shutil.which("chromium") or shutil.which("chromium-browser")
    if found is None:
        if os.environ.get("BTF_REQUIRE_BROWSER"):
            pytest.fail("BTF_REQUIRE_BROWSER is set but there is no chromium (.ci/run installs "
                        "it)")
        pytest.skip("no chromium here (Debian's package; .ci/run installs it)")
    return found


def free_port() -> int:
    """A free TCP port on loopback, for a test's server (one helper for every test)."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def no_partial_outputs(path: Path) -> bool:
    """Neither the output nor any hidden partial sibling of it exists."""
    stem = path.name.split(".")[0]
    leftovers = [p for p in path.parent.glob(f".{stem}*")
                 if "partial" in p.name or ".resume-" in p.name]
    return not path.exists() and not leftovers


ROOT = Path(__file__).resolve().parents[1]


def compose_command(service: str, *, values: dict[str, str] | None = None,
                    words: dict[str, str] | None = None) -> list[str]:
    """The command of a ``docker-compose.yml`` service, with some option values replaced.

    The cluster tests run these commands (the same programs, subcommands and options) with
    local hosts, ports and sizes, so the compose file cannot drift from what the tests run.
    ``values`` maps an option to its new value; ``words`` maps other words (addresses, config
    paths) to new ones. Every key must occur in the command.
    """
    import shlex

    import yaml

    spec = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    command = shlex.split(spec["services"][service]["command"])
    values, words = dict(values or {}), dict(words or {})
    missing = [k for k in values if k not in command] + [k for k in words if k not in command]
    assert not missing, f"docker-compose.yml's {service} command has no {missing}"
    out, applied = [], set()
    for i, word in enumerate(command):
        if i and command[i - 1] in values:
            out.append(values[command[i - 1]])
            applied.add(command[i - 1])
        else:
            out.append(words.get(word, word))
    assert applied == set(values), f"{service}: options without a value: {set(values) - applied}"
    return out


def compose_services() -> dict:
    """The services of ``docker-compose.yml``."""
    import yaml

    return yaml.safe_load((ROOT / "docker-compose.yml").read_text())["services"]


REPO = Path(__file__).resolve().parents[1]


def small_demo(folder: Path, size: int = 128, *, mitsuba: bool = False) -> Path:
    """configs/demo.yaml scaled down to a ``size^2`` ground truth, written into ``folder``.

    The sample stays the central half and the surface twice the size; the scene spec goes
    to ``folder/configs/demo/`` where the config finds it when run from ``folder``. Without
    ``mitsuba`` the Mitsuba render and its place in the report are left out (the default
    tests do not need Mitsuba 3 or LLVM 16).
    """
    import yaml

    text = (REPO / "configs" / "demo.yaml").read_text()
    for old, new in (("size: 256", f"size: {size}"),
                     ('"64:192,64:192"', f'"{size // 4}:{3 * size // 4},{size // 4}:'
                                         f'{3 * size // 4}"'),
                     ("size: [512, 512]", f"size: [{2 * size}, {2 * size}]")):
        assert old in text, old
        text = text.replace(old, new)
    if not mitsuba:
        config = yaml.safe_load(text)
        config["stages"] = [s for s in config["stages"] if "mitsuba" not in s]
        for stage in config["stages"]:
            stage.get("report", {}).pop("mitsuba", None)
        text = yaml.safe_dump(config, sort_keys=False)
    scenes = folder / "configs" / "demo"
    scenes.mkdir(parents=True, exist_ok=True)
    (scenes / "scene.yaml").write_text((REPO / "configs" / "demo" / "scene.yaml").read_text())
    path = folder / "demo.yaml"
    path.write_text(text)
    return path


@contextlib.contextmanager
def dask_cluster(folder: Path, *, workers: int = 1, processes: int = 2, protocol: str = "tcp",
                 tls: tuple[str, ...] = (), security=None, env: dict | None = None,
                 no_nanny: bool = False) -> Iterator[tuple[str, list[subprocess.Popen]]]:
    """A dask scheduler and ``workers`` ``dask worker`` commands as local processes: the
    address and the worker commands' processes. Every cluster test starts its cluster here.

    The commands are docker-compose.yml's, on loopback: the scheduler on a free port (its
    dashboard on any), each worker command with ``processes`` single-threaded processes and
    its own folder under ``folder`` (as on separate machines). ``protocol`` and ``tls`` (the
    dask options for certificates) make a TLS cluster; ``security`` is the client's, to wait
    for the workers. Everything started is stopped at the end (as by Ctrl-C, then killed if
    it lingers).
    """
    import socket

    from distributed import Client

    port = free_port()
    address = f"{protocol}://127.0.0.1:{port}"
    # a process that crashes in C code prints its Python stacks to the log, which is shown
    # below (with a failing test's output) when one did
    env = {**os.environ, "PYTHONFAULTHANDLER": "1", **(env or {})}
    bin_ = Path(sys.executable).parent
    log = (folder / "cluster.log").open("w")
    scheduler = compose_command("scheduler", values={
        "--host": "127.0.0.1", "--port": str(port), "--dashboard-address": "127.0.0.1:0"})
    if protocol != "tcp":
        scheduler += ["--protocol", protocol]
    procs = [subprocess.Popen([bin_ / scheduler[0], *scheduler[1:], *tls], stdout=log,
                              stderr=log, env=env)]
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
        worker = compose_command("worker", words={"tcp://scheduler:8786": address},
                                 values={"--nworkers": str(processes), "--nthreads": "1"})
        extra = [*tls, *(["--no-nanny"] if no_nanny else [])]
        started = []
        for i in range(workers):
            home = folder / f"worker-{i}"
            home.mkdir(exist_ok=True)
            started.append(subprocess.Popen([bin_ / worker[0], *worker[1:], *extra], cwd=home,
                                            stdout=log, stderr=log, env=env))
        procs += started
        deadline = time.monotonic() + 60
        while True:
            try:
                with Client(address, security=security, timeout="10s",
                            set_as_default=False) as client:  # the tests choose their own
                    client.wait_for_workers(workers * processes, timeout=60)
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.5)
        yield address, started
    finally:
        stop_processes(procs[1:], procs[:1])  # workers, then the scheduler
        log.close()
        text = (folder / "cluster.log").read_text(errors="replace")
        if "Fatal Python error" in text:
            print(f"a cluster process crashed; {folder / 'cluster.log'}:\n{text}",
                  file=sys.stderr)


def require_mitsuba_llvm():
    """Mitsuba 3 with a working llvm variant (set), or a skip naming what is missing.

    ``BTF_REQUIRE_MITSUBA=1`` (``.ci/run``) makes a missing one a failure instead.
    """
    import os

    import pytest

    from pipeline import mitsuba_plugin

    required = os.environ.get("BTF_REQUIRE_MITSUBA") == "1"
    try:
        import mitsuba  # noqa: F401
    except ImportError:
        if required:
            raise
        pytest.skip("Mitsuba 3 is not installed (pip install 'btf-pipeline[mitsuba]')")
    if not mitsuba_plugin.llvm_works(mitsuba_plugin.llvm_library()):
        if required:
            raise RuntimeError("Mitsuba's llvm variant does not run: LLVM 16 or later needed")
        pytest.skip("Mitsuba's llvm variant needs LLVM 16 or later (apt-get install libllvm19)")
    mitsuba_plugin.variant("llvm_ad_rgb")

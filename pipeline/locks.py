"""One writer per output: a lock next to it, on a local disk or in object storage.

Locally the lock is a file held with :func:`fcntl.flock`: the system releases it when the
holder dies, however it dies. An object store has no such thing. There the lock is an object
``.NAME.lock`` created with a conditional write (``If-None-Match: *``: the store refuses it
when it exists), holding who took it and until when; the holder renews it every third of
its lease with a conditional write on the version it wrote (``If-Match``), so a run killed
with ``kill -9`` leaves a lock that expires one lease later, and a rerun then takes it over
(again with ``If-Match`` on the version it read, so two reruns cannot both). A second run
finding a lock that has not expired stops at once, naming the lock and when it expires.
The lease is ``BTF_LOCK_LEASE`` seconds (30 by default).

A lock taken on this machine is known dead at once, lease or not, when its holder is gone
(:func:`holder_gone`): the machine booted since (its boot id changed), no process has the
holder's id, or the process with that id started at another time (the id was reused). Locks
of live processes and of other machines keep the lease rule.

A store without conditional writes (older MinIO and SeaweedFS releases) answers a conditional
write like a plain one: btf then reads the lock back and goes on only if it holds its own
owner tag, which catches two runs that do not start in the same instant, not all races; the
docs/cluster-and-storage.md says so.
"""

from __future__ import annotations

import json
import os
import socket
import threading
import time
import uuid

from pipeline import storage
from pipeline.errors import BTFError


def lease() -> float:
    """Seconds a lock object stays valid without being renewed."""
    return float(os.environ.get("BTF_LOCK_LEASE", "30"))


def _boot_id() -> str | None:
    """The id of the machine's current boot (Linux), or None where the system has none."""
    try:
        with open("/proc/sys/kernel/random/boot_id") as f:
            return f.read().strip()
    except OSError:
        return None


def _started(pid: int) -> float | None:
    """When process ``pid`` started (seconds since the epoch), or None if there is none."""
    import psutil

    try:
        return psutil.Process(pid).create_time()
    except (psutil.NoSuchProcess, psutil.ZombieProcess):
        return None
    except psutil.Error:  # exists but not ours to inspect: alive
        return float("nan")


def holder_gone(body: dict) -> bool:
    """Whether a lock's holder (its ``owner``, ``boot`` and ``started``) is gone for sure.

    Only a holder on this machine can be known gone; any doubt (another machine, a lock
    written without those fields, a process that may not be inspected) says it is not.
    """
    host, _, rest = str(body.get("owner", "")).partition(":")
    pid = rest.partition(":")[0]
    if host != socket.gethostname() or not pid.isdigit():
        return False
    boot = _boot_id()
    if body.get("boot") and boot and body["boot"] != boot:
        return True  # the machine restarted: every process of that boot is gone
    started = _started(int(pid))
    if started is None:
        return True
    recorded = body.get("started")
    return recorded is not None and abs(started - recorded) > 1.0  # the pid was reused


def _update(meta) -> dict:
    """An obstore ``UpdateVersion`` for an object's entity tag and version (when it has one)."""
    return {k: meta[k] for k in ("e_tag", "version") if meta.get(k) is not None}


class ObjectLock:
    """The lock object of one output (see the module); a context manager."""

    def __init__(self, url: str, shown: str):
        self.url, self.shown = url, shown
        self.owner = f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:8]}"
        self.version = None
        self._stop = threading.Event()
        self._thread = None
        self.lost = False

    def _body(self) -> bytes:
        return json.dumps({"owner": self.owner, "expires": time.time() + lease(),
                           "boot": _boot_id(), "started": _started(os.getpid())}).encode()

    def _put(self, mode):
        """One conditional write of the lock, retried while the server does not answer.

        obstore does not retry a conditional write whose request may have reached the server
        (it is not idempotent), so this does, within the retry settings' count and time
        (:func:`pipeline.storage.retry_settings`). A retry that meets its own earlier write
        (the answer was lost on the way back) finds the lock holding this run's owner tag.
        """
        import obstore
        import obstore.exceptions as oe

        bucket, key = storage._bucket(self.url)
        retries, timeout = storage.retry_settings()
        deadline = time.monotonic() + timeout
        wait, retried = 0.1, 0
        while True:
            with storage._guard(self.shown):  # conditions lost pass through it
                try:
                    return obstore.put(bucket, key, self._body(), mode=mode)
                except (oe.AlreadyExistsError, oe.PreconditionError):
                    if not retried:
                        raise
                    held = obstore.get(bucket, key)
                    if json.loads(bytes(held.bytes())).get("owner") != self.owner:
                        raise
                    return held.meta
                except (oe.BaseError, OSError) as exc:
                    if (not storage.unreachable(exc) or retried >= retries
                            or time.monotonic() + wait > deadline):
                        raise
            time.sleep(wait)
            wait, retried = min(2 * wait, 5.0), retried + 1

    def __enter__(self) -> ObjectLock:
        import obstore
        import obstore.exceptions as oe

        try:
            self.version = self._put("create")
        except oe.AlreadyExistsError:
            bucket, key = storage._bucket(self.url)
            with storage._guard(self.shown):
                try:
                    held = obstore.get(bucket, key)
                except FileNotFoundError:  # released meanwhile: try once more
                    return self.__enter__()
                meta, body = held.meta, json.loads(bytes(held.bytes()))
            left = body.get("expires", 0) - time.time()
            if left > 0 and not holder_gone(body):
                raise BTFError(f"{self.shown}: another btf run is writing this output ("
                               f"{body.get('owner', '?')} holds {self.url}, for {left:.0f} s "
                               "more unless it renews it); wait for it to end") from None
            try:
                self.version = self._put(_update(meta))
            except (oe.PreconditionError, oe.AlreadyExistsError):
                raise BTFError(f"{self.shown}: another btf run took over the dead lock "
                               f"{self.url} at the same moment; wait for it to end") from None
        held = json.loads(storage.read(self.url) or b"{}")
        if held.get("owner") != self.owner:  # a store that ignored the condition
            raise BTFError(f"{self.shown}: another btf run is writing this output (it holds "
                           f"{self.url}); wait for it to end")
        self._thread = threading.Thread(target=self._renew, name="btf-lock", daemon=True)
        self._thread.start()
        return self

    def _renew(self) -> None:
        import obstore.exceptions as oe

        while not self._stop.wait(lease() / 3):
            try:
                self.version = self._put(_update(self.version))
            except (oe.PreconditionError, BTFError):
                self.lost = True  # taken over: the other run's output is what will remain
                return

    def __exit__(self, *exc_info) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        held = json.loads(storage.read(self.url) or b"{}")
        if held.get("owner") == self.owner:
            storage.remove(self.url)


class FileLock:
    """The lock file of one local output, held with :func:`fcntl.flock`."""

    def __init__(self, path: str, shown: str):
        self.path, self.shown = path, shown
        self.file = None

    def __enter__(self) -> FileLock:
        import fcntl

        self.file = open(self.path, "w")  # held until __exit__
        try:
            fcntl.flock(self.file, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            self.file.close()
            raise BTFError(f"{self.shown}: another btf run is writing this output (it holds "
                           f"{self.path}); wait for it to end") from None
        return self

    def __exit__(self, *exc_info) -> None:
        os.unlink(self.path) if os.path.exists(self.path) else None
        self.file.close()


def lock(location: str, shown: str):
    """The lock of the output at ``location`` (a sibling ``.NAME.lock``)."""
    target = storage.join(storage.parent(location), f".{storage.name(location)}.lock")
    return ObjectLock(target, shown) if storage.is_url(location) else FileLock(target, shown)

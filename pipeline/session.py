"""Where graphs run: one option picks a local scheduler or a dask.distributed cluster.

``synchronous``, ``threads`` and ``processes`` are dask's local schedulers; ``tcp://HOST:PORT``
connects to a running ``dask scheduler``, and ``tls://HOST:PORT`` to one that only lets in
clients with a certificate its CA signed (mutual TLS: the CA, this client's certificate and
key, from ``--tls-ca-file``, ``--tls-cert``, ``--tls-key`` or dask's own configuration,
``distributed.comm.tls.ca-file`` / ``.client.cert`` / ``.client.key``, e.g.
``DASK_DISTRIBUTED__COMM__TLS__CA_FILE``, which every dask client honours). Results are
identical on all of them, because every random number comes from a seed and chunk
coordinates, never from scheduling order.
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
from dataclasses import dataclass
from functools import cache, partial
from typing import Any

LOCAL_SCHEDULERS = ("synchronous", "threads", "processes")
CONNECT_TIMEOUT = "10s"  # how long to wait for a tcp:// scheduler (it may still be starting)
PROGRESS_AFTER = 0.5  # seconds of work before a progress bar appears (default)


def progress_after() -> float:
    """Seconds of work before a progress bar appears: dask config ``btf.progress-after``.

    Set it like any dask option, e.g. ``DASK_BTF__PROGRESS_AFTER=0`` for a bar on every
    compute (the cluster tests do, to see the bar on short jobs).
    """
    import dask

    return float(dask.config.get("btf.progress-after", PROGRESS_AFTER))


# seconds between tries of sending btf's worker plugin while a lost worker is being dropped
PLUGIN_WAITS = (0.25, 0.5, 1.0, 2.0, 4.0)
NO_WORKERS_TIMEOUT = 120.0  # seconds a cluster run waits with no worker at all (default)


def no_workers_timeout() -> float:
    """Seconds a cluster run waits while the cluster has no worker: ``btf.no-workers-timeout``.

    After that the run stops with an error instead of waiting for workers that may never come
    (all of them lost, or none started). Set it like any dask option, e.g.
    ``DASK_BTF__NO_WORKERS_TIMEOUT=600``.
    """
    import dask

    return float(dask.config.get("btf.no-workers-timeout", NO_WORKERS_TIMEOUT))


PROTOCOLS = ("tcp://", "tls://")


def is_cluster(scheduler: str) -> bool:
    """Whether a scheduler option names a dask.distributed scheduler's address."""
    return scheduler.startswith(PROTOCOLS)


def check_scheduler(text: str) -> str:
    """Return ``text`` if it names a local scheduler or a scheduler address, else raise."""
    if text in LOCAL_SCHEDULERS or (is_cluster(text) and len(text) > len("tcp://")):
        return text
    raise ValueError(
        f"unknown scheduler {text!r}; use one of {', '.join(LOCAL_SCHEDULERS)} "
        "or the address of a dask scheduler, tcp://HOST:PORT or tls://HOST:PORT"
    )


@dataclass(frozen=True)
class TLS:
    """A client's TLS files (``None``: from dask's configuration)."""

    ca_file: str | None = None
    cert: str | None = None
    key: str | None = None

    def security(self):
        """``distributed.security.Security`` for a ``tls://`` scheduler (mutual TLS)."""
        import dask
        from distributed.security import Security

        ca = self.ca_file or dask.config.get("distributed.comm.tls.ca-file", None)
        cert = self.cert or dask.config.get("distributed.comm.tls.client.cert", None)
        key = self.key or dask.config.get("distributed.comm.tls.client.key", None)
        missing = [name for name, value in (("--tls-ca-file", ca), ("--tls-cert", cert))
                   if not value]
        if missing:
            raise ValueError(f"a tls:// scheduler needs {' and '.join(missing)} (or dask's "
                             "distributed.comm.tls.ca-file / .client.cert configuration)")
        for path in (ca, cert, key):
            if path and not os.path.isfile(path):
                raise ValueError(f"{path}: no such TLS file")
        return Security(tls_ca_file=ca, tls_client_cert=cert, tls_client_key=key,
                        require_encryption=True)


@dataclass(frozen=True)
class RuntimeOptions:
    """How to run: scheduler, number of local workers, and whether to stay quiet."""

    scheduler: str = "threads"
    workers: int | None = None
    quiet: bool = False
    tls: TLS = TLS()

    def __post_init__(self):
        check_scheduler(self.scheduler)
        if self.workers is not None and self.workers < 1:
            raise ValueError(f"workers must be at least 1, got {self.workers}")

    def local_workers(self, *, reads: bool = False) -> int:
        """Tasks the local schedulers run at once.

        ``--workers``, else one per core, and one more for graphs that read zarr chunks (see
        :meth:`Session.compute`).
        """
        if self.workers is not None:
            return self.workers
        return (os.cpu_count() or 1) + reads


def limit_blas() -> None:
    """Use one BLAS thread in this process (dask workers: parallelism comes from tasks).

    threadpoolctl limits only the BLAS libraries already loaded, and a fresh worker process
    may not have loaded numpy yet (a spawned ``processes`` worker under pytest had not: its
    products then ran on two threads and differed in the last bits). So numpy is loaded first,
    and the environment tells libraries loaded later (scipy's own OpenBLAS) the same.
    """
    for name in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OMP_NUM_THREADS"):
        os.environ[name] = "1"
    import numpy  # noqa: F401
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1, user_api="blas")


_BLAS: list = [None, -1]  # threadpoolctl's controller, and len(sys.modules) when it was made


def _blas_controller():
    """The BLAS libraries loaded, as threadpoolctl sees them; seen again after any import.

    ``threadpool_limits`` lists every shared library of the process on each call: 2 ms with
    btf's imports, at every compute (10 s of CPU over a ``make test``). Libraries are loaded
    by imports, so the list is kept until ``sys.modules`` changes size.
    """
    import sys

    from threadpoolctl import ThreadpoolController

    modules = len(sys.modules)  # before the scan: an import during it makes the next call scan
    if _BLAS[0] is None or _BLAS[1] != modules:
        _BLAS[:] = [ThreadpoolController(), modules]
    return _BLAS[0]


def pin_openmp() -> None:
    """One OpenMP thread (faiss's searches and its OpenMP BLAS) in tasks of this process.

    As in every worker process (:func:`limit_blas`), for two reasons measured on ``btf
    enlarge``: faiss's distances differ in their last bits with the number of its BLAS
    threads, so the threads scheduler (two OpenMP threads) and the processes scheduler (one)
    gave different stores; and OpenMP takes every core for each search, so two dask threads
    searching ran four threads on two cores, spinning (52 s of CPU on two workers against
    34 s on one, for the same wall time). libgomp reads ``OMP_NUM_THREADS`` when it is
    loaded, which in btf is on a task's first search. A user's own setting is overridden, as
    in worker processes: the results must not depend on it.
    """
    os.environ["OMP_NUM_THREADS"] = "1"


MMAP_THRESHOLD = 16 << 20  # blocks from this size are mapped, and unmapped when freed
TRIM_THRESHOLD = 8 << 20  # free memory a heap may keep at its top (see steady_memory)


def steady_memory() -> None:
    """Give blocks of :data:`MMAP_THRESHOLD` and more back to the system when freed (glibc).

    glibc raises its mmap threshold to the largest block freed so far (up to 32 MiB), after
    which such blocks come from the threads' malloc arenas, which fragment: with three worker
    threads allocating and freeing blocks of tens of MiB, a one-pass compression over 1024
    texel tiles ended 34% above one over 16 tiles (0.42 against 0.31 GiB), the row side 15%.
    A fixed threshold keeps them out of the arenas: 1.14x and 1.12x then. (1 MiB was flat too
    but up to 2x slower, every smaller temporary being mapped afresh; one arena was no
    better.) Elsewhere (macOS, musl) this does nothing.

    Fixing the mmap threshold also ends glibc's raising of its trim threshold, which then
    stays at 128 KiB: every free at a heap's top gave memory back and the next allocation
    faulted it in again. Quilting's planning after a compression in the same ``btf run`` took
    5.1 M page faults and 29.9 s instead of 21.2 s. So the trim threshold is fixed too, at
    :data:`TRIM_THRESHOLD`: 8 MiB plans in 19.7 s (0.3 M faults; 4 MiB did not help), and
    keeps a one-pass compression of a 512^2 store at a peak of 523-531 MiB against 466-498
    MiB (32 MiB, glibc's own ratio to this mmap threshold, peaked at 607 MiB).

    This process gets both from ``mallopt``; processes it starts later (the ``processes``
    scheduler's workers) from glibc's ``MALLOC_MMAP_THRESHOLD_`` and ``MALLOC_TRIM_THRESHOLD_``,
    set here, at their start. Cluster workers are not changed from here: the image sets both
    (Dockerfile).
    """
    os.environ.setdefault("MALLOC_MMAP_THRESHOLD_", str(MMAP_THRESHOLD))
    os.environ.setdefault("MALLOC_TRIM_THRESHOLD_", str(TRIM_THRESHOLD))
    import ctypes

    try:
        mallopt = ctypes.CDLL(None).mallopt  # the C library this process already runs on
    except (OSError, AttributeError):
        return
    mallopt(-3, MMAP_THRESHOLD)  # M_MMAP_THRESHOLD (fixing it ends the dynamic threshold)
    mallopt(-1, TRIM_THRESHOLD)  # M_TRIM_THRESHOLD


def _blas_plugin():
    """A dask worker plugin that pins BLAS to one thread on every worker."""
    from distributed.diagnostics.plugin import WorkerPlugin

    class SingleThreadedBlas(WorkerPlugin):
        def setup(self, worker):
            limit_blas()

    return SingleThreadedBlas()


def _executing(dask_worker) -> int:
    """Tasks a dask worker is running now (sent to every worker by ``Client.run``)."""
    return len(dask_worker.state.executing) + len(dask_worker.state.long_running)


class Session:
    """A scheduler to compute graphs on, with progress reporting and messages on stderr.

    Use as a context manager; a ``tcp://`` scheduler is connected on entry and closed on exit.
    """

    def __init__(self, options: RuntimeOptions | None = None):
        self.options = options or RuntimeOptions()
        self.client = None
        self._pin_blas = False
        self._blas_plugin = False  # registered with the cluster's scheduler
        # what `btf run` did so far, stage by stage (pipeline.config.execute; btf report)
        self.history: list[dict] = []
        self._config = contextlib.ExitStack()

    def __enter__(self) -> Session:
        import dask

        if not is_cluster(self.options.scheduler):
            pin_openmp()
            # every local stage, not only the BLAS-heavy ones: a reconstruct of 3 MB chunks
            # freed and faulted in its blocks' buffers again (6.9-7.3 s, 6.1-6.5 s with it)
            steady_memory()
        else:
            from distributed import Client

            from pipeline.errors import BTFError

            security = None
            if self.options.scheduler.startswith("tls://"):
                try:
                    security = self.options.tls.security()
                except ValueError as exc:
                    raise BTFError(f"{self.options.scheduler}: {exc}") from None
            try:
                self.client = Client(self.options.scheduler, timeout=CONNECT_TIMEOUT,
                                     set_as_default=False, security=security)
            except OSError as exc:
                raise BTFError(
                    f"cannot reach the dask scheduler at {self.options.scheduler}: {exc}"
                ) from exc
            if self.options.workers is not None:
                self.log("note: --workers is ignored on a cluster; its workers are set where "
                         "they are started (dask worker --nworkers)")
        if dask.config.get("array.rechunk.method", None) is None:
            # what dask would choose: it looks for a default client, which a session's never
            # is, but the look imports distributed (0.17 s) at every first rechunk
            self._config.enter_context(dask.config.set({"array.rechunk.method": "tasks"}))
        return self

    def __exit__(self, *exc_info) -> None:
        if self.client is not None:
            self.client.close()
            self.client = None
        self._config.close()

    @property
    def quiet(self) -> bool:
        """Whether progress and messages are suppressed."""
        return self.options.quiet

    @property
    def parallelism(self) -> int:
        """How many tasks run at once: the cluster's worker threads, or the local workers.

        A cluster with no workers yet (adaptive) counts as the local machine's cores.
        """
        if self.client is not None:
            return sum(self.client.nthreads().values()) or os.cpu_count() or 1
        if self.options.scheduler == "synchronous":
            return 1
        return self.options.local_workers()

    @property
    def read_parallelism(self) -> int:
        """How many tasks run at once in a graph that reads (:meth:`compute` with ``reads``)."""
        if self.client is not None or self.options.scheduler == "synchronous":
            return self.parallelism
        return self.options.local_workers(reads=True)

    def log(self, message: str) -> None:
        """Print a progress message on stderr unless quiet."""
        if not self.options.quiet:
            print(message, file=sys.stderr, flush=True)

    def compute(self, *collections: Any, reads: bool = False) -> tuple:
        """Compute dask collections on this session's scheduler, with a progress bar.

        ``reads`` marks graphs whose tasks spend much of their time reading zarr chunks: zarr
        serialises those reads within a process, so unless ``--workers`` says otherwise the
        local schedulers run one more worker than there are cores, which keeps the cores busy
        while a worker waits (measured: 14% faster compression on 2 cores).

        If a task fails (or the user interrupts), the tasks still running are waited for
        before the error propagates, so that no late write lands in an output that the caller
        is about to remove.
        """
        import dask

        if self.client is not None:
            return self._compute_distributed(collections)
        from dask.base import named_schedulers

        # the scheduler's function, not its name: given a name, dask imports distributed
        # (0.2 s) to look for a client, on every local run
        settings: dict[str, Any] = {"scheduler": named_schedulers[self.options.scheduler]}
        workers = self.options.workers
        if workers is None and reads and self.options.scheduler != "synchronous":
            workers = self.options.local_workers(reads=True)
        pool = self._local_pool(workers)
        if pool is not None:
            settings["pool"] = pool
        if workers is not None:
            settings["num_workers"] = workers
        try:
            with dask.config.set(settings), self._local_progress(), self._task_blas():
                return dask.compute(*collections)
        finally:
            if pool is not None:
                pool.shutdown(wait=True, cancel_futures=True)

    def _task_blas(self):
        """One BLAS thread in tasks, where stages ask for it and wherever threads run tasks.

        On the threads scheduler the workers are the parallelism: each task's product on a
        BLAS pool of its own oversubscribed the cores, its idle threads spinning (a whole
        ``btf reconstruct`` of a 1 GB store: 10.6-11.0 s and 13.5 s of CPU with two BLAS
        threads, 8.0 s and 6.1 s with one). The synchronous scheduler keeps BLAS's threads
        unless a stage pins them (:meth:`blas_pinned_in_tasks`).
        """
        if not (self._pin_blas or self.options.scheduler == "threads"):
            return contextlib.nullcontext()
        return _blas_controller().limit(limits=1, user_api="blas")

    def _local_pool(self, workers: int | None):
        """A pool of our own for the local schedulers, so that we can wait for it to drain."""
        workers = workers or self.options.local_workers()
        if self.options.scheduler == "threads":
            from dask.threaded import ContextAwareThreadPoolExecutor

            return ContextAwareThreadPoolExecutor(workers)
        if self.options.scheduler == "processes":
            from concurrent.futures import ProcessPoolExecutor

            from dask.multiprocessing import get_context, initialize_worker_process

            return ProcessPoolExecutor(workers, mp_context=get_context(),
                                       initializer=partial(initialize_worker_process,
                                                           user_initializer=limit_blas))
        return None

    @contextlib.contextmanager
    def blas_pinned_in_tasks(self):
        """Run every task of the block's computes with one BLAS thread.

        For stages whose tasks are BLAS-heavy (the SVD): the workers provide the parallelism,
        so a BLAS thread pool per worker would only oversubscribe the cores; and the tasks'
        results then do not depend on how many threads BLAS would have picked (OpenBLAS's
        single-precision GEMM gives the same bits with any count here, its double-precision
        GEMM and QR do not, and other BLAS builds promise less). The client's own
        factorizations between computes keep the client's thread count, which does not depend
        on the scheduler. Cluster workers get a worker plugin (also for workers that join
        later); local process workers always run with one BLAS thread.
        """
        if self.client is not None and not self._blas_plugin:
            self._register_blas_plugin()
        steady_memory()
        self._pin_blas = True
        try:
            yield
        finally:
            self._pin_blas = False

    def _register_blas_plugin(self) -> None:
        """Register :func:`_blas_plugin` with the scheduler, once a session.

        The scheduler sends it to every worker it has; a worker lost meanwhile makes that fail
        with the connection's error, which would stop a whole ``btf run`` for one worker
        killed, so it is tried again while the scheduler drops the worker
        (:data:`PLUGIN_WAITS`). Workers that join later get it from the scheduler.
        """
        from distributed.comm.core import CommClosedError

        from pipeline.errors import BTFError

        for wait in (*PLUGIN_WAITS, None):
            try:
                self.client.register_plugin(_blas_plugin(), name="btf-single-threaded-blas")
            except (CommClosedError, OSError) as exc:
                if wait is None:
                    raise BTFError(f"{self.options.scheduler}: the workers did not take btf's "
                                   f"worker plugin after {len(PLUGIN_WAITS) + 1} tries "
                                   f"({type(exc).__name__}: {exc})") from None
                self.log(f"a worker was lost while btf's worker plugin was sent; trying again "
                         f"in {wait:g} s")
                time.sleep(wait)
            else:
                self._blas_plugin = True
                return

    def share(self, value: Any) -> Any:
        """A task argument for a large value that every task of a graph reads: one graph task.

        Locally threads share it (the ``processes`` scheduler pickles it for each task). On a
        cluster the scheduler holds it with the graph, one worker computes it and the others
        fetch it from there; if that worker is lost, the scheduler runs the task again. (Data
        scattered to the workers instead cannot be recomputed, and dask's active memory
        manager soon keeps it on one worker only: losing that worker then cancelled the run
        with "lost dependencies", as CI saw for compress and quilt.)
        """
        import dask

        return dask.delayed(value, pure=False)

    def _compute_distributed(self, collections) -> tuple:
        import warnings

        with warnings.catch_warnings():  # shared values travel with the graph on purpose
            warnings.filterwarnings("ignore", message="Sending large graph")
            futures = self.client.compute(list(collections))
        watchdog = _NoWorkers(self.client, futures, no_workers_timeout())
        try:
            if not self.options.quiet:
                self._cluster_progress(futures)
            return tuple(self.client.gather(futures))
        except BaseException:
            self.client.cancel(futures, force=True)
            if watchdog.fired:
                from pipeline.errors import BTFError

                raise BTFError(
                    f"the dask cluster at {self.options.scheduler} has had no worker for "
                    f"{watchdog.timeout:g} s, so this run stopped: start workers and run the "
                    "same command again (dask option btf.no-workers-timeout sets how long to "
                    "wait)") from None
            self._wait_until_idle()
            raise
        finally:
            watchdog.stop()

    def _cluster_progress(self, futures) -> None:
        """A text progress bar on stderr until ``futures`` finish (or one fails).

        As on the local schedulers, it appears only after :func:`progress_after` seconds. The
        bar is told this session's scheduler: the client is not the process's default one
        (``distributed.progress`` looks for that and fails without it).
        """
        from distributed.diagnostics.progressbar import TextProgressBar

        deadline = time.monotonic() + progress_after()
        while not all(f.done() for f in futures):  # (distributed.wait needs a default client)
            if time.monotonic() > deadline:
                break
            time.sleep(0.02)
        else:
            return
        with contextlib.redirect_stdout(sys.stderr):
            try:
                TextProgressBar(futures, scheduler=self.client.scheduler.address)
            finally:  # end the bar's line, also when interrupted
                print(file=sys.stderr)

    def _wait_until_idle(self, timeout: float = 120.0) -> None:
        """Wait (bounded) until no worker is executing a task any more."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            busy = self.client.run(_executing)
            if not any(busy.values()):
                return
            time.sleep(0.2)
        self.log(f"warning: workers still busy {timeout:.0f} s after the failure; a late task "
                 "may leave files behind")

    def _local_progress(self):
        if self.options.quiet:
            return contextlib.nullcontext()
        return _progress_bar()(minimum=progress_after(), out=sys.stderr)


@cache
def _progress_bar():
    """The text progress bar of dask, whose timer stops as soon as the compute ends.

    dask's own timer thread sleeps ``dt`` (0.1 s) between updates and the compute waits for it
    at the end: up to 0.1 s more per compute (measured: 0.27 s of 0.48 s for a small
    three-pass ``btf compress``). Here the timer waits on an event that the end sets.
    """
    import threading
    from timeit import default_timer

    from dask.diagnostics import ProgressBar

    class Bar(ProgressBar):
        def _start(self, dsk):
            self._ended = threading.Event()
            super()._start(dsk)

        def _finish(self, dsk, state, errored):
            self._ended.set()
            super()._finish(dsk, state, errored)

        def _timer_func(self):
            while self._running:
                elapsed = default_timer() - self._start_time
                if elapsed > self._minimum:
                    self._update_bar(elapsed)
                self._ended.wait(self._dt)

    return Bar


class _NoWorkers:
    """Cancel ``futures`` once ``client``'s cluster has had no worker for ``timeout`` seconds.

    A thread asks the scheduler for its workers every second while the futures run. Without
    it a run whose workers all died (a segfault, the out-of-memory killer) waits forever: the
    scheduler keeps its tasks for workers that may join later.
    """

    def __init__(self, client, futures, timeout: float):
        import threading

        self.client, self.futures, self.timeout = client, futures, timeout
        self.fired = False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, name="btf-no-workers",
                                        daemon=True)
        self._thread.start()

    def _watch(self) -> None:
        since = None
        while not self._stop.wait(1.0):
            try:
                workers = len(self.client.nthreads())
            except Exception:  # the client is closing or the scheduler is gone: not ours
                return
            if workers:
                since = None
                continue
            since = since if since is not None else time.monotonic()
            if time.monotonic() - since >= self.timeout:
                self.fired = True
                self.client.cancel(self.futures, force=True)
                return

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()

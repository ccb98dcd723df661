"""Where graphs run: one option picks a local scheduler or a dask.distributed cluster.

``synchronous``, ``threads`` and ``processes`` are dask's local schedulers; ``tcp://HOST:PORT``
connects to a running ``dask scheduler``. Results are identical on all of them, because every
random number comes from a seed and chunk coordinates, never from scheduling order.
"""

from __future__ import annotations

import contextlib
import sys
from dataclasses import dataclass
from typing import Any

import dask

LOCAL_SCHEDULERS = ("synchronous", "threads", "processes")
CONNECT_TIMEOUT = "10s"  # how long to wait for a tcp:// scheduler (it may still be starting)


def check_scheduler(text: str) -> str:
    """Return ``text`` if it names a local scheduler or a ``tcp://`` address, else raise."""
    if text in LOCAL_SCHEDULERS or (text.startswith("tcp://") and len(text) > len("tcp://")):
        return text
    raise ValueError(
        f"unknown scheduler {text!r}; use one of {', '.join(LOCAL_SCHEDULERS)} "
        "or the address of a dask scheduler, tcp://HOST:PORT"
    )


@dataclass(frozen=True)
class RuntimeOptions:
    """How to run: scheduler, number of local workers, and whether to stay quiet."""

    scheduler: str = "threads"
    workers: int | None = None
    quiet: bool = False

    def __post_init__(self):
        check_scheduler(self.scheduler)
        if self.workers is not None and self.workers < 1:
            raise ValueError(f"workers must be at least 1, got {self.workers}")


class Session:
    """A scheduler to compute graphs on, with progress reporting and messages on stderr.

    Use as a context manager; a ``tcp://`` scheduler is connected on entry and closed on exit.
    """

    def __init__(self, options: RuntimeOptions | None = None):
        self.options = options or RuntimeOptions()
        self.client = None

    def __enter__(self) -> Session:
        if self.options.scheduler.startswith("tcp://"):
            from distributed import Client

            try:
                self.client = Client(self.options.scheduler, timeout=CONNECT_TIMEOUT,
                                     set_as_default=False)
            except OSError as exc:
                from pipeline.errors import BTFError

                raise BTFError(
                    f"cannot reach the dask scheduler at {self.options.scheduler}: {exc}"
                ) from exc
        return self

    def __exit__(self, *exc_info) -> None:
        if self.client is not None:
            self.client.close()
            self.client = None

    @property
    def quiet(self) -> bool:
        """Whether progress and messages are suppressed."""
        return self.options.quiet

    def log(self, message: str) -> None:
        """Print a progress message on stderr unless quiet."""
        if not self.options.quiet:
            print(message, file=sys.stderr, flush=True)

    def compute(self, *collections: Any) -> tuple:
        """Compute dask collections on this session's scheduler, with a progress bar."""
        if self.client is not None:
            futures = self.client.compute(list(collections))
            if not self.options.quiet:
                from distributed import progress

                with contextlib.redirect_stdout(sys.stderr):
                    progress(futures, notebook=False)
                    print(file=sys.stderr)
            return tuple(self.client.gather(futures))
        settings: dict[str, Any] = {"scheduler": self.options.scheduler}
        if self.options.workers is not None:
            settings["num_workers"] = self.options.workers
        with dask.config.set(settings), self._local_progress():
            return dask.compute(*collections)

    def _local_progress(self):
        if self.options.quiet:
            return contextlib.nullcontext()
        from dask.diagnostics import ProgressBar

        return ProgressBar(minimum=0.5, out=sys.stderr)

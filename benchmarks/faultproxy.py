"""A TCP proxy on loopback that cuts every connection for a while: a server outage on demand.

It stands in front of a server (the tests' SeaweedFS S3 server) and passes bytes both ways.
:meth:`FlakyProxy.outage` resets every open connection and, for the given seconds, resets each
new one as soon as it is accepted, as a server that restarts or a network that drops does.
With ``after_requests``, the first outage starts by itself once that many HTTP requests
(``PUT``/``GET``/``POST``/``DELETE``/``HEAD`` lines from clients) have gone through, so that a
test can cut a run in the middle of its writes without timing it.
"""

from __future__ import annotations

import re
import socket
import struct
import threading
import time

_REQUEST = re.compile(rb"(?:^|\r\n)(?:PUT|GET|POST|DELETE|HEAD) /")


class FlakyProxy:
    """A proxy from ``127.0.0.1:PORT`` to ``target`` (host, port); a context manager."""

    def __init__(self, target: tuple[str, int], *, after_requests: int | None = None,
                 seconds: float = 10.0):
        self.target, self.after, self.seconds = target, after_requests, seconds
        self.requests, self.outages, self.reset = 0, [], 0
        self._down_until, self._tripped = 0.0, False
        self._lock = threading.Lock()
        self._open: set[socket.socket] = set()
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.port = self._listener.getsockname()[1]
        self._stopped = False
        threading.Thread(target=self._accept, daemon=True).start()

    @property
    def endpoint(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def outage(self, seconds: float) -> None:
        """Reset every connection now and every new one for ``seconds``."""
        with self._lock:
            self._down_until = time.monotonic() + seconds
            self.outages.append((time.time(), seconds))
            doomed, self._open = list(self._open), set()
            self.reset += len(doomed)
        for s in doomed:
            _reset(s)

    def close(self) -> None:
        """Stop accepting and close every connection."""
        self._stopped = True
        self._listener.close()
        with self._lock:
            doomed, self._open = list(self._open), set()
        for s in doomed:
            _reset(s)

    def __enter__(self) -> FlakyProxy:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _accept(self) -> None:
        while not self._stopped:
            try:
                client, _ = self._listener.accept()
            except OSError:
                return
            with self._lock:
                down = time.monotonic() < self._down_until
                self.reset += down
            if down:
                _reset(client)
                continue
            try:
                upstream = socket.create_connection(self.target, timeout=5)
            except OSError:
                _reset(client)
                continue
            upstream.settimeout(None)
            with self._lock:
                self._open.update((client, upstream))
            threading.Thread(target=self._pump, args=(client, upstream, True), daemon=True).start()
            threading.Thread(target=self._pump, args=(upstream, client, False),
                             daemon=True).start()

    def _pump(self, source: socket.socket, sink: socket.socket, from_client: bool) -> None:
        try:
            while data := source.recv(65536):
                if from_client and self.after is not None:
                    with self._lock:  # pumps of several connections count together
                        self.requests += len(_REQUEST.findall(data))
                        due = not self._tripped and self.requests >= self.after
                        self._tripped |= due
                    if due:
                        self.outage(self.seconds)
                        return
                sink.sendall(data)
        except OSError:
            pass
        finally:
            for s in (source, sink):
                with self._lock:
                    self._open.discard(s)
                try:
                    s.close()
                except OSError:
                    pass


def _reset(s: socket.socket) -> None:
    """Close with a TCP reset (linger 0), as a dropped connection looks to its peer."""
    try:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        s.close()
    except OSError:
        pass

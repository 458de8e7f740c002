"""The HTTP server ``/metrics`` is scraped on: prometheus_client's WSGI app on the standard
library's threading WSGI server, bounded.

prometheus_client's own ``start_http_server`` starts a thread for each connection and never
closes one that says nothing: 2,000 idle connections held 2,000 threads, and under systemd's
default limit of 1,024 descriptors some 980 of them took every descriptor the gateway had,
so that its zenoh session and its dashboard stopped answering. It runs in the gateway's
process, often on an address a remote Prometheus reaches.

Rules of this file:

1. At most ``MAX_SCRAPES`` connections are served at once; one more is closed as soon as it
   is accepted (a scraper tries again at its next interval). Holding them all keeps the
   metrics from others, never a descriptor or a thread more from the gateway.
2. A connection that sends nothing for ``IDLE_S`` is closed, and its slot freed; so is one
   whose request line and headers are not whole within ``IDLE_S`` of its opening (a line a
   second is never idle, and eight such held the metrics from every scraper).
3. Nothing is logged per request.
4. Only ``/metrics`` is served (the path Prometheus asks by default); any other path is 404.
"""

from __future__ import annotations

import contextlib
import socket
import threading
import time
from collections.abc import Callable, Iterable
from socketserver import ThreadingMixIn
from typing import Any
from wsgiref.simple_server import WSGIRequestHandler, WSGIServer, make_server

from prometheus_client import CollectorRegistry, make_wsgi_app

#: Connections served at once (rule 1): a Prometheus or two, and room for a person's curl.
MAX_SCRAPES = 8
#: How long a connection may send nothing, or take to send its whole head, before it is
#: closed (rule 2).
IDLE_S = 5.0
#: The one path served (rule 4).
METRICS_PATH = "/metrics"


class _Handler(WSGIRequestHandler):
    timeout = IDLE_S  # set on each connection's socket (rule 2)

    server: _BoundedServer

    def setup(self) -> None:
        super().setup()
        self.server.head_due(self)  # rule 2

    def parse_request(self) -> bool:
        whole = super().parse_request()  # the request line, then the headers, read
        self.server.head_came(self)
        return whole

    def finish(self) -> None:
        self.server.head_came(self)
        super().finish()

    def cut(self) -> None:
        """The head did not come whole in time: the wait for the rest ends (rule 2)."""
        with contextlib.suppress(OSError):
            self.connection.shutdown(socket.SHUT_RDWR)

    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 - the base's name
        """Rule 3."""


class _BoundedServer(ThreadingMixIn, WSGIServer):
    """A thread a connection, at most ``MAX_SCRAPES`` of them (rule 1)."""

    daemon_threads = True
    request_queue_size = 64

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self._slots = threading.BoundedSemaphore(MAX_SCRAPES)
        self._heads: dict[_Handler, float] = {}  # each connection's head not whole: its deadline
        self._heads_lock = threading.Lock()
        super().__init__(*args, **kwargs)

    def head_due(self, handler: _Handler) -> None:
        with self._heads_lock:
            self._heads[handler] = time.monotonic() + IDLE_S

    def head_came(self, handler: _Handler) -> None:
        with self._heads_lock:
            self._heads.pop(handler, None)

    def service_actions(self) -> None:
        """Between two looks at the listening socket (every half second): each connection
        whose head is late is cut (rule 2)."""
        moment = time.monotonic()
        with self._heads_lock:
            late = [handler for handler, due in self._heads.items() if moment >= due]
            for handler in late:
                del self._heads[handler]
        for handler in late:
            handler.cut()

    def process_request(self, request: Any, client_address: Any) -> None:
        if not self._slots.acquire(blocking=False):
            self.shutdown_request(request)
            return
        try:
            super().process_request(request, client_address)
        except BaseException:  # no thread started: nothing else frees the slot
            self._slots.release()
            raise

    def handle_error(self, request: Any, client_address: Any) -> None:
        """A connection that timed out or went (rule 2): nothing to tell (rule 3); the base
        printed a traceback for each."""

    def process_request_thread(self, request: Any, client_address: Any) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            self._slots.release()


def serve(registry: CollectorRegistry, host: str, port: int) -> tuple[WSGIServer, threading.Thread]:
    """``registry`` served on ``host:port`` (0: any free port) from a thread of its own; stop
    it with the server's ``shutdown`` and ``server_close``, then join the thread."""
    server = make_server(
        host,
        port,
        _metrics_only(make_wsgi_app(registry)),
        server_class=_BoundedServer,
        handler_class=_Handler,
    )
    thread = threading.Thread(target=server.serve_forever, name="metrics", daemon=True)
    thread.start()
    return server, thread


def _metrics_only(app: Callable[..., Iterable[bytes]]) -> Callable[..., Iterable[bytes]]:
    """``app`` on ``/metrics``, a 404 elsewhere (rule 4)."""

    def wsgi(environ: dict[str, Any], start_response: Callable[..., Any]) -> Iterable[bytes]:
        if environ.get("PATH_INFO") != METRICS_PATH:
            start_response("404 Not Found", [("Content-Type", "text/plain; charset=utf-8")])
            return [f"no such page: the metrics are at {METRICS_PATH}\n".encode()]
        return app(environ, start_response)

    return wsgi

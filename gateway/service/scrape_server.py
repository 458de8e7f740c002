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
2. A connection that sends nothing for ``IDLE_S`` is closed, and its slot freed.
3. Nothing is logged per request.
"""

from __future__ import annotations

import threading
from socketserver import ThreadingMixIn
from typing import Any
from wsgiref.simple_server import WSGIRequestHandler, WSGIServer, make_server

from prometheus_client import CollectorRegistry, make_wsgi_app

#: Connections served at once (rule 1): a Prometheus or two, and room for a person's curl.
MAX_SCRAPES = 8
#: How long a connection may send nothing before it is closed (rule 2).
IDLE_S = 5.0


class _Handler(WSGIRequestHandler):
    timeout = IDLE_S  # set on each connection's socket (rule 2)

    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 - the base's name
        """Rule 3."""


class _BoundedServer(ThreadingMixIn, WSGIServer):
    """A thread a connection, at most ``MAX_SCRAPES`` of them (rule 1)."""

    daemon_threads = True
    request_queue_size = 64

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self._slots = threading.BoundedSemaphore(MAX_SCRAPES)
        super().__init__(*args, **kwargs)

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
        host, port, make_wsgi_app(registry), server_class=_BoundedServer, handler_class=_Handler
    )
    thread = threading.Thread(target=server.serve_forever, name="metrics", daemon=True)
    thread.start()
    return server, thread

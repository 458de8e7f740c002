"""``busgate dashboard`` put together: one ``busgate.client.aio`` client, the ``Feed`` that
fills a ``Fleet`` from it, the ``Hub`` that pushes it to the browsers, the Starlette app,
served by uvicorn on the caller's loop until ``stop`` is set.

uvicorn is started as a part of a larger program (``busgate demo`` runs the gateway on the
same loop): it installs no signal handlers of its own, configures no logging, and is told to
stop by the caller's ``stop`` event.

Rules of this file:

1. The dashboard answers to the names a browser reaches its address by, and to those given
   with ``--allow-host``, never to any name: ``0.0.0.0`` and ``::`` mean the loopback names and
   this machine's name, not ``*`` (``app`` rule 3). Nothing is resolved: a lookup of the
   machine's name can leave the machine (DNS), and an address the operator wants a browser
   to use is named with ``--allow-host``.
2. Nothing on the network holds the server for ever: a request comes whole within
   ``REQUEST_TIMEOUT_S`` of the connection's opening or of the previous reply, or its
   connection is closed; an idle connection is closed after as long; a request that finds
   ``MAX_CONNECTIONS`` open, its own included, gets a 503; no more than ``MAX_HEAD_BYTES`` of
   an unfinished head is kept. One client address holds at most ``MAX_PER_CLIENT`` of the
   connections (past them a connection is closed as it opens), so one host holding
   connections open, slowly or idly, leaves the rest to the others and their e-stops; and
   uvicorn's warnings a request makes (refused at the limit, an upgrade it does not serve)
   are logged once a minute at most.
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import logging
import re
import socket
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any

import h11
import uvicorn
from uvicorn.protocols.http.h11_impl import H11Protocol

from busgate.client import aio
from busgate.client.errors import NoAnswerError, UnknownGatewayError
from busgate.client.keys import split_name
from busgate.dashboard.app import create_app, host_and_port
from busgate.dashboard.feed import Feed
from busgate.dashboard.fleet import Fleet
from busgate.dashboard.hub import Hub
from busgate.errors import CommandError

DEFAULT_LISTEN = "127.0.0.1:8080"
#: A port as digits only: ``int`` would also take " 80", "+80", "8_0" and "٨٠".
PORT = re.compile(r"[0-9]{1,5}")
STARTED_POLL_S = 0.02
GRACE_S = 2  # how long a stop waits for requests under way
#: How long a connection has to send a request whole (from its opening, or from the end of
#: the previous reply), and how long it may then stay idle (rule 2).
REQUEST_TIMEOUT_S = 5
#: Open connections (an event stream holds one per browser) at which a request gets a 503.
MAX_CONNECTIONS = 100
#: Connections one client address may hold (rule 2): most of ``MAX_CONNECTIONS``, since
#: behind a reverse proxy every browser comes from the proxy's one address, yet never all.
MAX_PER_CLIENT = 64
#: How often each of uvicorn's warnings a client's request makes may be logged (rule 2).
LIMIT_WARNING_EVERY_S = 60.0
#: Those warnings, as they begin.
SAID_PER_REQUEST = (
    "Exceeded concurrency limit.",
    "Unsupported upgrade request.",
    "No supported WebSocket library detected.",
    "Invalid HTTP request received.",  # each malformed request (its 400)
)
#: The most of a request line and headers kept while they have not ended (h11's
#: ``max_incomplete_event_size``, its default said here); past it, a 400.
MAX_HEAD_BYTES = 16 * 1024
LOOPBACK_NAMES = ("localhost", "127.0.0.1", "::1")


@dataclass(frozen=True)
class Listen:
    """Where the dashboard listens: an IP address and a TCP port (0: any free one), and the
    names it answers to besides its own (``--allow-host``, as ``allowed_name`` spells them)."""

    host: str
    port: int
    also_named: tuple[str, ...] = ()

    @classmethod
    def parse(cls, text: str, also_named: Iterable[str] = ()) -> Listen:
        """``HOST:PORT`` (``[::1]:8080`` for IPv6), answering to ``also_named`` too;
        ``CommandError`` for anything else."""
        written, colon, port = text.rpartition(":")
        bracketed = written.startswith("[") and written.endswith("]")
        host = written[1:-1] if bracketed else written
        try:
            address = ipaddress.ip_address(host)
            hosted = (address.version == 6) == bracketed  # "::1:8080" is an address, no port
        except ValueError:
            hosted = False
        if not colon or not hosted:
            raise CommandError(
                f"listen on HOST:PORT with HOST an IP address, e.g. {DEFAULT_LISTEN}, "
                f"not {text[:100]!r}"
            )
        number = int(port) if PORT.fullmatch(port) else -1
        if not 0 <= number <= 65535:
            raise CommandError(
                f"listen on HOST:PORT: port {port[:20]!r} is no port: from 0 to 65535 (0: any "
                "free one)"
            )
        return cls(host, number, tuple(allowed_name(name) for name in also_named))

    def names(self) -> set[str]:
        """The hosts a browser may name in its ``Host`` header (rule 1), in ``app``'s form: the
        address (and ``localhost`` for a loopback one, ``LOOPBACK_NAMES`` and this machine's
        name for every interface), and ``also_named``."""
        address = ipaddress.ip_address(self.host)
        if address.is_unspecified:
            own = [*LOOPBACK_NAMES, socket.gethostname().lower()]
        else:
            own = [address.compressed, *(["localhost"] if address.is_loopback else [])]
        return {*own, *self.also_named}

    def bind(self) -> socket.socket:
        """A TCP socket bound here; ``CommandError`` when the address cannot be had."""
        family = socket.AF_INET6 if ipaddress.ip_address(self.host).version == 6 else socket.AF_INET
        bound = socket.socket(family, socket.SOCK_STREAM)
        if self.port:  # a port of the operator's, taken again at once after a restart
            bound.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        # Port 0 without it: with it, the kernel may give a port another socket with it has
        # bound and is about to listen on (a CI run's demo found it in use at its listen).
        try:
            bound.bind((self.host, self.port))
        except OSError as exc:
            bound.close()
            raise CommandError(
                f"the dashboard cannot listen on {self.host}:{self.port}: {exc.strerror}"
            ) from exc
        return bound

    def exposure(self) -> str | None:
        """What listening here lets others do, when other hosts can reach it (a warning, as a
        gateway's zenoh listener's is); ``None`` on a loopback address."""
        if ipaddress.ip_address(self.host).is_loopback:
            return None
        host = f"[{self.host}]" if ":" in self.host else self.host
        return (
            f"{host}:{self.port} can be reached from other hosts: whoever reaches it may "
            "e-stop any gateway, reset its e-stop and enable any device (docs/fleet.md)"
        )

    def url(self, port: int) -> str:
        address = ipaddress.ip_address(self.host)
        shown = "127.0.0.1" if address.is_unspecified else self.host
        return f"http://{f'[{shown}]' if ':' in shown else shown}:{port}/"


def allowed_name(text: str) -> str:
    """A name to answer to (``--allow-host``): a DNS name or an IP address, without a port,
    in ``app``'s form; ``CommandError`` for anything else."""
    with contextlib.suppress(ValueError):
        return ipaddress.ip_address(text).compressed
    found = host_and_port(text)
    if found is None or found[1] is not None:
        raise CommandError(
            f"a name to answer to is a DNS name or an IP address, without a port, "
            f"not {text[:100]!r}"
        )
    return found[0]


class ClientActions:
    """The three things a browser may ask (``app.Actions``), done with the SDK."""

    def __init__(self, client: aio.Client) -> None:
        self._client = client

    async def estop(self, gateway: str | None) -> None:
        await self._client.estop(gateway)

    async def reset_estop(self, gateway: str) -> None:
        await self._client.reset_estop(gateway)

    async def enable(self, device: str) -> dict[str, Any]:
        """The device's re-enable command, sent once: a reply that timed out says nothing of
        whether it was taken, and sent again it would take the device out of an e-stop put
        meanwhile (an audit: the dashboard's retry did); the operator, who sees the timeout
        and the e-stop, presses again. A gateway whose info nobody answers is not up (``app``
        rule 4: 404, as the other actions answer)."""
        try:
            found = await self._client.device(device)
        except NoAnswerError:
            gateway, _ = split_name(device)  # the app takes only a device named gw/name
            up = sorted(await self._client.gateways())
            raise UnknownGatewayError(
                f"no gateway {gateway!r} is up (the gateways that answer: "
                f"{', '.join(up) or 'none'})",
                gateway=gateway,
                gateways=up,
            ) from None
        return await found.enable()


def _client_host(connection: object) -> str | None:
    """The address a connection (one of uvicorn's protocols) comes from."""
    client = getattr(connection, "client", None)
    return client[0] if client else None


class _NowAndThen(logging.Filter):
    """Lets each of uvicorn's warnings that a client's request can make (``SAID_PER_REQUEST``)
    through once every ``LIMIT_WARNING_EVERY_S``: it logged one for each request refused at
    the connection limit, two for each websocket upgrade, so a client could flood the log."""

    def __init__(self) -> None:
        super().__init__()
        self._next: dict[str, float] = {}

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        said = next((m for m in SAID_PER_REQUEST if message.startswith(m)), None)
        if said is None:
            return True
        if record.created < self._next.get(said, 0.0):
            return False
        self._next[said] = record.created + LIMIT_WARNING_EVERY_S
        return True


class _EmbeddedServer(uvicorn.Server):
    @contextlib.contextmanager
    def capture_signals(self) -> Iterator[None]:
        yield  # the caller's program owns SIGTERM and SIGINT


class _DeadlineProtocol(H11Protocol):
    """uvicorn's HTTP/1.1 with rule 2's deadline: uvicorn's keep-alive timer starts only once
    a reply is sent and stops at the first byte after it, so a client that sends half a
    request line, or a head and part of a body, would be kept for ever. Here a timer of
    ``timeout_keep_alive`` starts with the connection and again with each reply, and when it
    fires while the request is not in whole, the connection is closed. A connection past its
    address's ``MAX_PER_CLIENT`` is closed as it opens."""

    _deadline: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        host = _client_host(self)
        if host is not None and sum(_client_host(c) == host for c in self.connections) > (
            MAX_PER_CLIENT
        ):
            transport.close()
            return
        self._start_deadline()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        self._start_deadline()

    def connection_lost(self, exc: Exception | None) -> None:
        if self._deadline is not None:
            self._deadline.cancel()
        super().connection_lost(exc)

    def _start_deadline(self) -> None:
        if self._deadline is not None:
            self._deadline.cancel()
        if not self.transport.is_closing():
            self._deadline = self.loop.call_later(self.timeout_keep_alive, self._on_deadline)

    def _on_deadline(self) -> None:
        if self.conn.their_state in (h11.IDLE, h11.SEND_BODY):  # no request, or half of one
            self.transport.close()


async def serve_dashboard(
    client: aio.Client,
    listen: Listen,
    stop: asyncio.Event,
    *,
    prefix: str = "busgate",
    on_ready: Callable[[str], None] | None = None,
    bound: socket.socket | None = None,
) -> None:
    """Serve the dashboard on ``listen`` until ``stop`` is set; ``on_ready(url)`` once it
    listens. ``CommandError`` when the address cannot be listened on. ``bound``: the
    socket ``listen.bind()`` gave already (``busgate demo`` binds before its gateway starts,
    so that a port in use is refused at once), served and closed here."""
    hosts = listen.names()
    fleet = Fleet()
    feed = Feed(client, fleet, prefix)
    hub = Hub(fleet)
    app = create_app(hub, ClientActions(client), hosts=hosts)
    config = uvicorn.Config(
        app,
        host=listen.host,
        port=listen.port,
        http=_DeadlineProtocol,
        log_config=None,
        log_level="warning",
        access_log=False,
        lifespan="off",
        timeout_graceful_shutdown=GRACE_S,
        timeout_keep_alive=REQUEST_TIMEOUT_S,
        limit_concurrency=MAX_CONNECTIONS,
        h11_max_incomplete_event_size=MAX_HEAD_BYTES,
    )
    server = _EmbeddedServer(config)
    if bound is None:
        bound = listen.bind()  # here, so that a port in use is an error, not uvicorn's exit
    limit_warnings = _NowAndThen()
    logging.getLogger("uvicorn.error").addFilter(limit_warnings)
    pushing = asyncio.create_task(hub.run())
    serving = asyncio.create_task(server.serve(sockets=[bound]))
    try:
        while not (server.started or serving.done()):
            await asyncio.sleep(STARTED_POLL_S)
        if not server.started:
            raise CommandError(f"the dashboard did not start on {listen.host}:{listen.port}")
        if on_ready is not None:
            on_ready(listen.url(bound.getsockname()[1]))
        stopping = asyncio.create_task(stop.wait())
        await asyncio.wait({serving, stopping}, return_when=asyncio.FIRST_COMPLETED)
        stopping.cancel()
    finally:
        hub.let_go()  # the streams end, so the server's shutdown need not wait for them
        server.should_exit = True
        await serving
        pushing.cancel()
        feed.close()
        bound.close()
        logging.getLogger("uvicorn.error").removeFilter(limit_warnings)

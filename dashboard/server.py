"""``busgate dashboard`` put together: one ``busgate.client.aio`` client, the ``Feed`` that
fills a ``Fleet`` from it, the ``Hub`` that pushes it to the browsers, the Starlette app,
served by uvicorn on the caller's loop until ``stop`` is set.

uvicorn is started as a part of a larger program (``busgate demo`` runs the gateway on the
same loop): it installs no signal handlers of its own, configures no logging, and is told to
stop by the caller's ``stop`` event.
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import re
import socket
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import uvicorn

from busgate.client import aio
from busgate.client.errors import error_for
from busgate.codecs.errors import CommandError
from busgate.dashboard.app import create_app
from busgate.dashboard.feed import Feed
from busgate.dashboard.fleet import Fleet
from busgate.dashboard.hub import Hub

DEFAULT_LISTEN = "127.0.0.1:8080"
#: A port as digits only: ``int`` would also take " 80", "+80", "8_0" and "٨٠".
PORT = re.compile(r"[0-9]{1,5}")
STARTED_POLL_S = 0.02
ENABLE_TRIES = 3
GRACE_S = 2  # how long a stop waits for requests under way


@dataclass(frozen=True)
class Listen:
    """Where the dashboard listens: an IP address and a TCP port (0: any free one)."""

    host: str
    port: int

    @classmethod
    def parse(cls, text: str) -> Listen:
        """``HOST:PORT`` (``[::1]:8080`` for IPv6); ``CommandError`` for anything else."""
        written, colon, port = text.rpartition(":")
        bracketed = written.startswith("[") and written.endswith("]")
        host = written[1:-1] if bracketed else written
        try:
            address = ipaddress.ip_address(host)
            number = int(port) if PORT.fullmatch(port) else -1
            if (address.version == 6) != bracketed:  # "::1:8080" is an address, not a port
                number = -1
        except ValueError:
            number = -1
        if not colon or not 0 <= number <= 65535:
            raise CommandError(
                f"listen on HOST:PORT with HOST an IP address, e.g. {DEFAULT_LISTEN}, "
                f"not {text[:100]!r}"
            )
        return cls(host, number)

    @property
    def allowed_hosts(self) -> list[str]:
        """The ``Host`` headers a browser sends to this address (``app`` rule 3): any, when it
        listens on every interface (the README says what that means)."""
        address = ipaddress.ip_address(self.host)
        if address.is_unspecified:
            return ["*"]
        names = [f"[{self.host}]" if address.version == 6 else self.host]
        return [*names, "localhost"] if address.is_loopback else names

    def bind(self) -> socket.socket:
        """A TCP socket bound here; ``CommandError`` when the address cannot be had."""
        family = socket.AF_INET6 if ipaddress.ip_address(self.host).version == 6 else socket.AF_INET
        bound = socket.socket(family, socket.SOCK_STREAM)
        bound.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            bound.bind((self.host, self.port))
        except OSError as exc:
            bound.close()
            raise CommandError(
                f"the dashboard cannot listen on {self.host}:{self.port}: {exc.strerror}"
            ) from None
        return bound

    def url(self, port: int) -> str:
        address = ipaddress.ip_address(self.host)
        shown = "127.0.0.1" if address.is_unspecified else self.host
        return f"http://{f'[{shown}]' if ':' in shown else shown}:{port}/"


class ClientActions:
    """The two things a browser may ask (``app.Actions``), done with the SDK."""

    def __init__(self, client: aio.Client) -> None:
        self._client = client

    async def estop(self, gateway: str | None) -> None:
        await self._client.estop(gateway)

    async def enable(self, device: str) -> dict[str, Any]:
        """The device's re-enable command, sent again (``ENABLE_TRIES`` in all) while its reply
        times out: a timeout says nothing of whether it was taken, and enabling an enabled
        device changes nothing."""
        found = await self._client.device(device)
        for attempt in range(1, ENABLE_TRIES + 1):
            try:
                return await found.enable()
            except error_for("device_timeout"):
                if attempt == ENABLE_TRIES:
                    raise
        raise AssertionError("unreachable")


class _EmbeddedServer(uvicorn.Server):
    @contextlib.contextmanager
    def capture_signals(self) -> Iterator[None]:
        yield  # the caller's program owns SIGTERM and SIGINT


async def serve_dashboard(
    client: aio.Client,
    listen: Listen,
    stop: asyncio.Event,
    *,
    prefix: str = "busgate",
    on_ready: Callable[[str], None] | None = None,
) -> None:
    """Serve the dashboard on ``listen`` until ``stop`` is set; ``on_ready(url)`` once it
    listens. ``CommandError`` when the address cannot be listened on."""
    fleet = Fleet()
    feed = Feed(client, fleet, prefix)
    hub = Hub(fleet)
    app = create_app(hub, ClientActions(client), allowed_hosts=listen.allowed_hosts)
    config = uvicorn.Config(
        app,
        host=listen.host,
        port=listen.port,
        log_config=None,
        log_level="warning",
        access_log=False,
        lifespan="off",
        timeout_graceful_shutdown=GRACE_S,
    )
    server = _EmbeddedServer(config)
    bound = listen.bind()  # here, so that a port in use is an error, not uvicorn's exit
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

"""What the SDK's tests against a real gateway share (tests/test_client_sdk.py,
test_client_aio.py, test_client_resilience.py): the demo's devices, how long a follow stream
lasts without a new target, a second session watching a gateway's events, and fresh target
positions.

The gateway runs as a child process (conftest's ``module_demo``, or one a test starts); the
watcher is a session of the SDK's own core (``busgate.client.core.Core``), so what it sees is
what any subscriber on the gateway's events key sees.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import os
import threading
import time
from collections.abc import Awaitable, Callable, Iterator
from typing import Any, TypeVar

from busgate.client.core import Core
from busgate.client.errors import error_for
from busgate.gateway.cli.demo import DEMO_BUSES, GATEWAY_NAME
from busgate.gateway.scheduler.tickers import FRESH_PERIODS, MIN_FRESH_S
from busgate.schemas.families import PROTOCOLS

#: Every device of ``busgate demo``, with its kind.
DEMO_DEVICES: dict[str, str] = {
    name: PROTOCOLS[bus.protocol].kind for bus in DEMO_BUSES for name, _ in bus.devices
}
#: The demo's gateway name.
DEMO = GATEWAY_NAME
#: A follow stream without a new target for this long goes stale (``stream_stale``): the
#: gateway's rule at the demo's follow period, 20 ms (``schemas.config.DeviceConfig``).
STALE_S = max(FRESH_PERIODS * 0.020, MIN_FRESH_S)

_watchers = itertools.count(1)
T = TypeVar("T")


def fresh_positions(start: int) -> Iterator[int]:
    """Inspire LA positions (0–2000) never used twice in a module: a state showing one came
    from the command that asked for it."""
    return iter(range(start, 2000, 7))


def the_client_id(name: str) -> str:
    """A client id (1–64 of ``A-Za-z0-9_-``) made from a test's name."""
    cleaned = "".join(c if c.isalnum() or c in "_-" else "-" for c in name)
    return cleaned[-60:].lstrip("-_") or "test"


class EventWatch:
    """Every event a gateway publishes on ``<prefix>/<gateway>/events``, with the monotonic
    time it arrived, from a session of its own; a context manager."""

    def __init__(self, endpoint: str, gateway: str = DEMO) -> None:
        self._core = Core(endpoint, client_id=f"event-watch-{os.getpid()}-{next(_watchers)}")
        self._lock = threading.Lock()
        self._events: list[tuple[float, dict[str, Any]]] = []
        self._core.subscribe(self._core.keys.events(gateway), self._on_event)

    def _on_event(self, key: str, payload: bytes) -> None:
        with self._lock:
            self._events.append((time.monotonic(), json.loads(payload)))

    def of(self, device: str, *types: str, since: float = 0.0) -> list[dict[str, Any]]:
        """The events of ``device`` (of ``types``, when given) that came after ``since``."""
        with self._lock:
            events = list(self._events)
        return [
            event
            for arrived, event in events
            if arrived >= since and event.get("device") == device
            and (not types or event.get("type") in types)
        ]

    def close(self) -> None:
        self._core.close()

    def __enter__(self) -> EventWatch:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


#: Tries of a command whose simulated device missed its reply: the demo's simulators share a
#: loaded machine's cores with the gateway and the tests, and one late reply is a
#: ``device_timeout`` (the gateway tells it rightly), which is not what these tests are about.
TRIES = 3
#: The pause before a try again: a refusal for a device gone offline after late replies (a
#: base's wheel: ``bases`` rule 3) comes at once, and the device is back only once its
#: offline probe is answered, some hundreds of ms later.
RETRY_PAUSE_S = 0.5


def patiently(command: Callable[..., T], *args: Any) -> T:
    """``command(*args)``, sent again (at most ``TRIES`` times in all) while its reply is
    ``device_timeout``; any other error at once."""
    for attempt in range(1, TRIES + 1):
        try:
            return command(*args)
        except error_for("device_timeout"):
            if attempt == TRIES:
                raise
            time.sleep(RETRY_PAUSE_S)
    raise AssertionError("unreachable")


async def patiently_async(command: Callable[..., Awaitable[T]], *args: Any) -> T:
    """``patiently`` for a coroutine function."""
    for attempt in range(1, TRIES + 1):
        try:
            return await command(*args)
        except error_for("device_timeout"):
            if attempt == TRIES:
                raise
            await asyncio.sleep(RETRY_PAUSE_S)
    raise AssertionError("unreachable")

"""The dashboard's one view of the zenoh network: a ``busgate.client.aio`` client's
subscriptions (every gateway's device states, bases' odometry, bus statistics and events, and
the gateways' liveliness) poured into a ``Fleet``, and each gateway's ``info`` asked for as it
comes. Bases are found by their odometry, which ``info`` does not list.

However many browsers watch, the gateways see one client: this one, so that many browsers
cost the gateways nothing more.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from collections.abc import Callable
from typing import Any

from busgate.client import aio
from busgate.client.base import gateway_infos
from busgate.client.errors import GatewayError
from busgate.client.keys import Keys
from busgate.dashboard.fleet import MAX_GATEWAYS, Fleet
from busgate.errors import BusgateError

log = logging.getLogger(__name__)

INFO_WAIT_S = 2.0
#: How often a gateway whose ``info`` did not answer is asked again, while it is up.
INFO_TRIES = 5


class Feed:
    """Keeps ``fleet`` up to date from ``client`` until ``close``."""

    def __init__(self, client: aio.Client, fleet: Fleet, prefix: str) -> None:
        self._client, self._fleet, self._keys = client, fleet, Keys(prefix)
        self._loop = asyncio.get_running_loop()
        self._asking: set[asyncio.Task] = set()
        #: Gateways up that found the fleet full (``MAX_GATEWAYS``), in the order they came:
        #: the first is taken when a gateway goes.
        self._waiting: dict[str, None] = {}
        self._waiting_lock = threading.Lock()
        self._ends: list[Callable[[], None]] = [
            client.subscribe(self._keys.device("*", "*", "state"), self._on_state),
            client.subscribe(self._keys.base("*", "*", "odom"), self._on_odometry),
            client.subscribe(self._keys.bus("*", "*", "stats"), self._on_stats),
            client.subscribe(self._keys.events("*"), self._on_event),
            client.on_gateways(self._on_gateway),
        ]

    def close(self) -> None:
        for end in self._ends:
            end()
        for task in self._asking:
            task.cancel()

    # -- zenoh's threads -------------------------------------------------------------------------

    # A sample's key may be a wildcard's (a put on ``busgate/**/state`` reaches these
    # subscriptions too): one that names no gateway and device, bus or base is dropped.

    def _on_state(self, key: str, body: Any) -> None:
        names = self._keys.names_in(key, "dev", "state")
        if names is not None:
            self._fleet.state(*names, body)

    def _on_odometry(self, key: str, body: Any) -> None:
        names = self._keys.names_in(key, "base", "odom")
        if names is not None:
            self._fleet.odometry(*names, body)

    def _on_stats(self, key: str, body: Any) -> None:
        names = self._keys.names_in(key, "bus", "stats")
        if names is not None:
            self._fleet.stats(*names, body)

    def _on_event(self, key: str, body: Any) -> None:
        gateway = self._keys.gateway_in(key, "events")
        if gateway is not None:
            self._fleet.event(gateway, body)

    def _on_gateway(self, gateway: str, alive: bool) -> None:
        with self._waiting_lock:
            if not alive:
                self._waiting.pop(gateway, None)
                self._fleet.gateway_gone(gateway)
                taken = next((w for w in self._waiting if self._fleet.gateway_up(w)), None)
                if taken is not None:
                    del self._waiting[taken]
                    self._loop.call_soon_threadsafe(self._ask_info, taken)
            elif self._fleet.gateway_up(gateway):
                self._loop.call_soon_threadsafe(self._ask_info, gateway)
            elif self._fleet.full and not self._fleet.has(gateway):
                if not self._waiting:
                    log.warning(
                        "%d gateways shown already: %s, and any more, wait for one to go",
                        MAX_GATEWAYS,
                        gateway,
                    )
                if len(self._waiting) < MAX_GATEWAYS:  # bounded too (fleet rule 2)
                    self._waiting[gateway] = None

    # -- the loop --------------------------------------------------------------------------------

    def _ask_info(self, gateway: str) -> None:
        task = self._loop.create_task(self._info(gateway))
        self._asking.add(task)
        task.add_done_callback(self._asking.discard)

    async def _info(self, gateway: str) -> None:
        why = "no answer"
        for _ in range(INFO_TRIES):
            try:
                answers = await self._client.query(self._keys.info(gateway), timeout=INFO_WAIT_S)
            except (BusgateError, GatewayError) as exc:
                why = str(exc)
            else:
                info = gateway_infos(answers).get(gateway)  # its own, on its own key
                if info is not None:
                    self._fleet.info(gateway, info)
                    return
                why = "no info of its own among the answers" if answers else "no answer"
            if not self._fleet.has(gateway):
                return
            await asyncio.sleep(INFO_WAIT_S / 2)
        log.warning("gateway %s is up but its info did not answer (%s)", gateway, why)

"""A device's state messages as a client reads them: the latest one (``Latest``, for
``Device.state``) and each one as it comes (``Stream``, for ``Device.states``).

Rules: the zenoh callback only stores the payload and its arrival time and calls the sinks
(which may not block); parsing into the kind's model happens in the reader's thread or task.
A gateway going away clears what ``Latest`` holds: the last state of a gateway that is gone
is not handed out as the device's latest.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable
from typing import Any

from busgate.client.base import Found, Shared

log = logging.getLogger(__name__)


class Stream:
    """Each state payload of one device to ``sink`` while the ``with`` block runs."""

    def __init__(self, shared: Shared, found: Found, sink: Callable[[bytes], Any]) -> None:
        self._key = shared.core.keys.device(found.gateway, found.name, "state")
        self._shared, self._sink = shared, sink
        self._end: Callable[[], None] | None = None

    def __enter__(self) -> Stream:
        sink = self._sink
        self._end = self._shared.core.subscribe(self._key, lambda key, payload: sink(payload))
        return self

    def __exit__(self, *exc_info: object) -> None:
        if self._end is not None:
            self._end()


class Latest:
    """The latest state payload of one device, kept from the first ask to the client's close."""

    def __init__(self, shared: Shared, found: Found) -> None:
        self.gateway = found.gateway
        self._lock = threading.Lock()
        self._latest: tuple[float, bytes] | None = None
        self._waiting: list[Callable[[bytes], object]] = []
        key = shared.core.keys.device(found.gateway, found.name, "state")
        shared.core.subscribe(key, self._on_state)
        shared.core.on_gateway_gone(self._gateway_gone)

    def recent(self, max_age_s: float) -> bytes | None:
        """The latest payload if it came in the last ``max_age_s`` seconds."""
        latest = self._latest
        if latest is None or time.monotonic() - latest[0] > max_age_s:
            return None
        return latest[1]

    def on_next(self, callback: Callable[[bytes], object]) -> Callable[[], None]:
        """Call ``callback(payload)`` once, with the next payload (zenoh's thread); returns
        what withdraws it (a wait that timed out)."""
        with self._lock:
            self._waiting.append(callback)

        def withdraw() -> None:
            with self._lock, contextlib.suppress(ValueError):
                self._waiting.remove(callback)

        return withdraw

    def wait(self, max_age_s: float, timeout_s: float) -> bytes | None:
        """A recent payload, else the next within ``timeout_s`` (``None``: none came)."""
        payload = self.recent(max_age_s)
        if payload is not None:
            return payload
        came = threading.Event()
        got: list[bytes] = []

        def take(payload: bytes) -> None:
            got.append(payload)
            came.set()

        withdraw = self.on_next(take)
        if not came.wait(timeout_s):
            withdraw()
        return got[0] if got else None

    def _on_state(self, key: str, payload: bytes) -> None:
        with self._lock:
            self._latest = (time.monotonic(), payload)
            waiting, self._waiting = self._waiting, []
        for callback in waiting:
            try:
                callback(payload)
            except Exception:  # a waiter gone with its event loop must not rob the others
                log.debug("a state waiter failed", exc_info=True)

    def _gateway_gone(self, gateway: str) -> None:
        if gateway == self.gateway:
            self._latest = None

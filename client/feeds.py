"""A device's state messages as a client reads them: the latest one (``Latest``, for
``Device.state``) and each one as it comes (``Stream``, for ``Device.states``); and the
``Inbox`` that hands what zenoh's threads bring to a reader, one future at a time.

Rules: the zenoh callback only stores the payload and its arrival time and settles the futures
of its readers (whose callbacks may not block); parsing into the kind's model happens in the
reader's thread or task. A gateway going away clears what ``Latest`` holds: the last state of a
gateway that is gone is not handed out as the device's latest. A reader that gave up (its
future cancelled, as at a timeout) takes nothing from those that still wait.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, InvalidStateError
from typing import Any, Generic, TypeVar

from busgate.client.base import Found, Shared

T = TypeVar("T")


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


class Inbox(Generic[T]):
    """Items put on zenoh's threads, taken one at a time by one reader: ``next`` is a future
    of the next one (done at once when one waits), ``put`` settles it."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._items: deque[T] = deque()
        self._taker: Future | None = None

    def put(self, item: T) -> None:
        with self._lock:
            taker, self._taker = self._taker, None
            if taker is None or not taker.set_running_or_notify_cancel():
                self._items.append(item)  # nobody waits, or the reader gave up: the next's
                return
        taker.set_result(item)

    def next(self) -> Future:
        taken: Future = Future()
        with self._lock:
            if self._items:
                taken.set_result(self._items.popleft())
            else:
                self._taker = taken
        return taken


class Latest:
    """The latest state payload of one device, kept from the first ask to the client's close."""

    def __init__(self, shared: Shared, found: Found) -> None:
        self.gateway = found.gateway
        self._lock = threading.Lock()
        self._latest: tuple[float, bytes] | None = None
        self._waiting: list[Future] = []
        key = shared.core.keys.device(found.gateway, found.name, "state")
        shared.core.subscribe(key, self._on_state)
        shared.core.on_gateway_gone(self._gateway_gone)

    def recent(self, max_age_s: float) -> bytes | None:
        """The latest payload if it came in the last ``max_age_s`` seconds."""
        latest = self._latest
        if latest is None or time.monotonic() - latest[0] > max_age_s:
            return None
        return latest[1]

    def next(self) -> Future:
        """A future of the next payload; cancelling it (a wait that timed out) withdraws it."""
        came: Future = Future()
        with self._lock:
            self._waiting.append(came)
        came.add_done_callback(self._withdraw)
        return came

    def _withdraw(self, came: Future) -> None:
        if came.cancelled():
            with self._lock, contextlib.suppress(ValueError):
                self._waiting.remove(came)

    def _on_state(self, key: str, payload: bytes) -> None:
        with self._lock:
            self._latest = (time.monotonic(), payload)
            waiting, self._waiting = self._waiting, []
        for came in waiting:
            with contextlib.suppress(InvalidStateError):  # given up on meanwhile
                came.set_result(payload)

    def _gateway_gone(self, gateway: str) -> None:
        if gateway == self.gateway:
            self._latest = None

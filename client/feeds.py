"""The messages a gateway publishes on one key as a client reads them: a device's states or a
gateway's joints, the latest one (``Latest``, for ``Device.state``, ``Joint.state`` and
``Client.joints``) and each one as it comes (``Stream``, for ``Device.states`` and
``Client.joints_feed``); and the ``Inbox`` that hands what zenoh's threads bring to a reader,
one future at a time.

Rules: the zenoh callback only stores the payload and its arrival time and settles the futures
of its readers (whose callbacks may not block); parsing into the kind's model happens in the
reader's thread or task. A gateway going away clears what ``Latest`` holds: the last message of
a gateway that is gone is not handed out as its latest. A reader that gave up (its
future cancelled, as at a timeout) takes nothing from those that still wait. A reader that
falls behind loses the oldest of what waits for it, past ``MAX_WAITING``. A reader still
waiting when its client closes meets ``session closed`` at once (``core.closed_reading``),
not its timeout: nothing more comes.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, InvalidStateError
from typing import Generic, TypeVar

from busgate.client.core import Core, closed_reading
from busgate.client.messages import feed_deadline
from busgate.client.steps import Items, Next, Steps

T = TypeVar("T")
log = logging.getLogger(__name__)
#: The most items an ``Inbox`` holds for its reader: ten seconds of a device's states at
#: 100 Hz.
MAX_WAITING = 1000
#: The most bytes of payloads it holds: a thousand of a peer's 2 MiB messages (what a session
#: takes in at most) held 2 GiB for a reader that had stopped reading.
MAX_WAITING_BYTES = 64 * 1024 * 1024


class Stream:
    """Each payload on ``key`` to ``inbox`` while the ``with`` block runs; the inbox ends with
    the subscription (the client closed under its reader)."""

    def __init__(self, core: Core, key: str, inbox: Inbox[bytes]) -> None:
        self._key, self._core, self._inbox = key, core, inbox
        self._end: Callable[[], None] | None = None

    def __enter__(self) -> Stream:
        inbox, key = self._inbox, self._key
        self._end = self._core.subscribe(
            key, lambda key, payload: inbox.put(payload), lambda: inbox.end(closed_reading(key))
        )
        return self

    def __exit__(self, *exc_info: object) -> None:
        if self._end is not None:
            self._end()


class Inbox(Generic[T]):
    """Items put on zenoh's threads, taken one at a time by one reader: ``next`` is a future
    of the next one (done at once when one waits), ``put`` settles it. A reader more than
    ``MAX_WAITING`` items (or ``MAX_WAITING_BYTES`` of payloads) behind loses the oldest (a
    warning says so, once): a feed's newest messages are what a late reader wants, and what
    waits is memory."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._items: deque[T] = deque()
        self._bytes = 0  # of the payloads waiting (items that are bytes)
        self._taker: Future | None = None
        self._ended_with: Exception | None = None  # what a reader meets once the items run out
        #: The items dropped unread, the oldest first, a reader being ``MAX_WAITING`` behind.
        self.dropped = 0

    def put(self, item: T) -> None:
        with self._lock:
            taker, self._taker = self._taker, None
            if taker is None or not taker.set_running_or_notify_cancel():
                self._items.append(item)  # nobody waits, or the reader gave up: the next's
                self._bytes += _size(item)
                while len(self._items) > MAX_WAITING or self._bytes > MAX_WAITING_BYTES:
                    self._fell_behind()
                    self._bytes -= _size(self._items.popleft())
                return
        taker.set_result(item)

    def _fell_behind(self) -> None:
        if not self.dropped:
            log.warning(
                "a feed's reader is %d messages or %d MiB behind: the oldest are dropped unread",
                MAX_WAITING,
                MAX_WAITING_BYTES >> 20,
            )
        self.dropped += 1

    def next(self) -> Future:
        taken: Future = Future()
        with self._lock:
            if self._items:
                item = self._items.popleft()
                self._bytes -= _size(item)
                taken.set_result(item)
            elif self._ended_with is not None:
                taken.set_exception(self._ended_with)
            else:
                self._taker = taken
        return taken

    def end(self, why: Exception) -> None:
        """Nothing more comes: the reader takes what waits, then meets ``why``."""
        with self._lock:
            self._ended_with = why
            taker, self._taker = self._taker, None
        if taker is not None and taker.set_running_or_notify_cancel():
            taker.set_exception(why)


def _size(item: object) -> int:
    """What an item waiting weighs against ``MAX_WAITING_BYTES``: a payload its length."""
    return len(item) if isinstance(item, bytes) else 0


class Latest:
    """The latest payload on ``key``, a key of ``gateway``'s, kept from the first ask to the
    client's close."""

    def __init__(self, core: Core, key: str, gateway: str) -> None:
        self.gateway = gateway
        self._lock = threading.Lock()
        self._latest: tuple[float, bytes] | None = None
        self._waiting: list[Future] = []
        self._ended_with: Exception | None = None  # the subscription's end: what a reader meets
        core.subscribe(key, self._on_message, lambda: self._ended(closed_reading(key)))
        core.on_gateway_gone(self._gateway_gone)

    def recent(self, max_age_s: float) -> bytes | None:
        """The latest payload if it came in the last ``max_age_s`` seconds."""
        latest = self._latest
        if latest is None or time.monotonic() - latest[0] > max_age_s:
            return None
        return latest[1]

    def newer_than(self, payload: bytes) -> bytes | None:
        """The latest payload if one came after ``payload`` (a payload taken from here: it
        is the one kept until another replaces it), else ``None``. A reader that found one
        payload no message reads it, so none that came while it looked waits for the next."""
        latest = self._latest
        return None if latest is None or latest[1] is payload else latest[1]

    def next(self) -> Future:
        """A future of the next payload; cancelling it (a wait that timed out) withdraws it."""
        came: Future = Future()
        with self._lock:
            if self._ended_with is not None:
                came.set_exception(self._ended_with)
                return came
            self._waiting.append(came)
        came.add_done_callback(self._withdraw)
        return came

    def _withdraw(self, came: Future) -> None:
        if came.cancelled():
            with self._lock, contextlib.suppress(ValueError):
                self._waiting.remove(came)

    def _on_message(self, key: str, payload: bytes) -> None:
        with self._lock:
            self._latest = (time.monotonic(), payload)
            waiting, self._waiting = self._waiting, []
        for came in waiting:
            with contextlib.suppress(InvalidStateError):  # given up on meanwhile
                came.set_result(payload)

    def _ended(self, why: Exception) -> None:
        """The subscription ended (the client closed): what waits, and what asks later,
        meets ``why``."""
        with self._lock:
            self._ended_with = why
            waiting, self._waiting = self._waiting, []
        for came in waiting:
            with contextlib.suppress(InvalidStateError):  # given up on meanwhile
                came.set_exception(why)

    def _gateway_gone(self, gateway: str) -> None:
        if gateway == self.gateway:
            self._latest = None


def parsed_feed(
    core: Core, key: str, parse: Callable[[bytes], T | None], timeout_s: float
) -> Items[T]:
    """Each message on ``key`` that ``parse`` takes, as it comes, until ``timeout_s`` (one it
    leaves out, ``None``, is told by it): a device's states, a base's odometry, a gateway's
    joints messages."""
    deadline = feed_deadline(timeout_s)
    inbox: Inbox[bytes] = Inbox()
    with Stream(core, key, inbox):
        while (left := deadline - time.monotonic()) > 0:
            payload = yield Next(inbox.next(), left)
            if payload is None:
                return
            message = parse(payload)
            if message is not None:
                yield message


def latest_parsed(
    latest: Latest, parse: Callable[[bytes], T | None], timeout_s: float, max_age_s: float
) -> Steps[T | None]:
    """The latest message that ``parse`` takes: one received in the last ``max_age_s``
    seconds, else the next within ``timeout_s`` (one kept meanwhile first); ``None`` when
    none came. One that ``parse`` leaves out is waited past, not raised: a peer's bad
    message on the key fails no reader."""
    payload = latest.recent(max_age_s)
    message = None if payload is None else parse(payload)
    deadline = time.monotonic() + timeout_s
    while message is None and (left := deadline - time.monotonic()) > 0:
        newer = None if payload is None else latest.newer_than(payload)
        payload = newer if newer is not None else (yield Next(latest.next(), left))
        message = None if payload is None else parse(payload)
    return message

"""What a bus owner is: the one object that touches a serial port or a CAN interface.

``BusOwner`` is an abstract base class rather than a ``typing.Protocol``: the owners are the
gateway's own, one per kind of link, and share their idle loop (``idle_until``), each saying
only what its idle work is (``take_unsolicited``, every ``idle_batch_s``); and an owner that
lacks a method fails when it is made, not on the bus thread the first time the runner calls it.

Rules of every owner:

1. Only the bus thread calls it; nothing else touches its port.
2. ``exchange`` raises ``DeviceTimeoutError`` when no reply came in time (the link is fine) and
   ``BusIOError`` when the link failed (the owner has closed itself; reopening is the
   runner's business). The reply it returns holds the events that answer the request, every
   one matched to ``request.expected``: nothing after the owner matches them again.
3. On a line that carries frames nobody asked for (heartbeats, on CAN), they go with their
   arrival time to the sink the owner was made with, whenever it reads its line: while it
   waits for a reply and while idle. A question-and-answer line has none: idle, its owner
   only waits.
4. When it has a ``tap`` (the flight recorder), every frame it writes and every read from its
   line goes to it, with the host's time, on the bus thread: ``(time, TX or RX, bytes, CAN
   identifier or None)``, plain values only (a tuple of them is nothing the garbage
   collector walks). The tap only appends; it never waits.
"""

from __future__ import annotations

import abc
import time
from collections.abc import Callable
from typing import ClassVar

from busgate.gateway.bus.clock import now
from busgate.gateway.bus.request import Exchange, LinkTiming, Request
from busgate.gateway.bus.stats import BusCounters

#: ``pause(seconds)``: wait that long; true when the wait was cut short (new work for the bus,
#: or news that brought events: the runner's pause publishes what the owner took in).
Pause = Callable[[float], bool]
#: Directions of a tapped frame (rule 4): written by the gateway, or read by it.
TX, RX = "tx", "rx"
Tap = Callable[[tuple[float, str, bytes, int | None]], None]


class BusOwner(abc.ABC):
    """One port or interface, run one exchange at a time."""

    #: The port or interface, as logs and errors name it.
    port: str
    timing: LinkTiming
    counters: BusCounters
    #: While idle, the longest pause between two looks for frames nobody asked for
    #: (``math.inf``: none come, so idle time is only waiting).
    idle_batch_s: ClassVar[float]
    #: Where every frame goes as well (rule 4); ``None``: nowhere.
    tap: Tap | None = None

    @property
    @abc.abstractmethod
    def is_open(self) -> bool:
        """The port or interface is ours."""

    @abc.abstractmethod
    def open(self) -> None:
        """Take the port or interface; ``BusUnavailableError`` when it cannot be had."""

    @abc.abstractmethod
    def close(self) -> None:
        """Let it go; closing what is closed, or gone already, is fine."""

    @abc.abstractmethod
    def exchange(self, request: Request, *, at: float | None = None) -> Exchange:
        """Send ``request`` (at the ``perf_counter`` time ``at``, when given: the last wait
        is done here, right before the write) and wait for its reply (rule 2)."""

    @abc.abstractmethod
    def take_unsolicited(self) -> None:
        """Hand what came unasked to the sink (rule 3), without waiting."""

    def idle_until(self, deadline: float, pause: Pause | None = None) -> bool:
        """Spend the time until ``deadline`` idle: take what came unasked, pause at most
        ``idle_batch_s``, and again. ``pause`` (by default a sleep) cutting a pause short
        ends the wait at once: then ``False``, else ``True`` once ``deadline`` has come."""
        pause = pause or _sleep
        while True:
            self.take_unsolicited()
            remaining = deadline - now()
            if remaining <= 0:
                return True
            if pause(min(self.idle_batch_s, remaining)):
                return False


def _sleep(seconds: float) -> bool:
    time.sleep(seconds)
    return False

"""Periodic traffic: follow streams (coalesced per tick) and device keep-alives.

Rules of this file:

1. A tick is due a full period after the previous tick actually started, never earlier, so no
   interval is shorter than the period and a late tick is not made up by a burst.
2. A follow stream holds only while fresh: a new target within ``max(3 periods, 100 ms)``.
   A stale stream is dropped at the next tick and reported through ``on_stale``.
3. Streams of one driver kind and one period share a ticker, up to the kind's
   ``follow_group_limit`` per frame (15 Inspire LA actuators in one 0xF3 broadcast frame, many
   DS servos in one SYNC WRITE); more streams open another ticker.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from busgate.gateway.bus.request import Request
from busgate.gateway.bus.stats import BusCounters
from busgate.gateway.drivers.base import Driver

MIN_FRESH_S = 0.1
FRESH_PERIODS = 3


@dataclass(slots=True)
class FollowStream:
    """One device's stream. ``latest`` is ``(target, when)``, replaced whole (one atomic
    assignment) by whichever thread has a new target, and read by the bus thread at a tick."""

    driver: Driver
    latest: tuple[Any, float]


class FollowTicker:
    """Sends the latest targets of its streams every ``period_s``, in one frame."""

    def __init__(
        self,
        driver_class: type[Driver],
        period_s: float,
        counters: BusCounters,
        on_stale: Callable[[Driver], None],
    ) -> None:
        self.driver_class = driver_class
        self.period_s = period_s
        self.fresh_s = max(FRESH_PERIODS * period_s, MIN_FRESH_S)
        self.counters = counters
        self.on_stale = on_stale
        self.streams: dict[str, FollowStream] = {}
        self._due: float | None = None
        self._last_start: float | None = None
        self._continuing = False  # the next tick follows the previous one without a pause

    def has_room(self, driver: Driver) -> bool:
        limit = self.driver_class.follow_group_limit
        return driver.name in self.streams or len(self.streams) < limit

    def update(self, driver: Driver, target: Any, now: float) -> FollowStream:
        """A new target for ``driver``; a new ticker starts ticking at once."""
        stream = self.streams.get(driver.name)
        if stream is None:
            stream = self.streams[driver.name] = FollowStream(driver, (target, now))
        else:
            stream.latest = (target, now)
        if self._due is None:
            last = self._last_start
            self._due = now if last is None else max(now, last + self.period_s)
            self._continuing = False
        return stream

    def stop(self, name: str) -> None:
        self.streams.pop(name, None)

    def carried(self) -> list[Driver]:
        """The devices a tick's frame carries."""
        return [stream.driver for stream in self.streams.values()]

    def next_due(self) -> float | None:
        return self._due if self.streams else None

    def build(self, now: float) -> Request | None:
        for name, stream in list(self.streams.items()):
            if now - stream.latest[1] > self.fresh_s:
                del self.streams[name]
                self.on_stale(stream.driver)
        if not self.streams:
            self._due = None
            return None
        targets = [(s.driver, s.latest[0]) for s in self.streams.values()]
        return self.driver_class.follow_request(targets)

    def sent(self, start: float) -> None:
        if self._continuing and self._last_start is not None:
            self.counters.follow_interval(start - self._last_start, self.period_s)
        self._continuing = True
        self._last_start = start
        self._due = start + self.period_s


class KeepaliveTicker:
    """Repeats what a device needs to keep going (a ZLAC706's speed) while it needs it."""

    def __init__(self, driver: Driver) -> None:
        self.driver = driver
        self.period_s = 0.0
        self._last_start = 0.0

    def next_due(self) -> float | None:
        need = self.driver.keepalive(self._last_start)
        if need is None:
            return None
        self.period_s = need[0]
        return self._last_start + self.period_s

    def build(self, now: float) -> Request | None:
        need = self.driver.keepalive(now)
        return None if need is None else need[1]

    def sent(self, start: float) -> None:
        self._last_start = start

"""The follow streams of one bus: which ticker carries each device's stream, and what happens
when a stream ends.

Rules of this file:

1. Bus thread only, but for ``store_latest``: a client's new target for a running stream is
   stored where the next tick reads it, from any thread, without waking the bus thread.
2. A stream that goes stale or is stopped for one device (its client left, it rebooted, a
   command stopped the device: ``BusWork``) is reported with an event and followed by the
   device's ``stale_stream`` requests (a ZLAC706 gets 0 rpm) as a command. Streams ended all
   at once (e-stop, lost bus, shutdown) are only reported: what comes next puts every device
   in its safe state anyway; so is a stream a trajectory takes over (``drop``): the
   trajectory goes on from where it left the device.
3. A stream that ended but by ``drop`` tells ``on_left`` when its last tick went (a ramp's:
   once the tick that sends its target went), for where the device is commanded to be held
   until something newer is read of it (``plays`` rule 4).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from typing import Any

from busgate.gateway.bus.stats import BusCounters
from busgate.gateway.drivers.base import Driver, Follows
from busgate.gateway.scheduler.planner import BusPlanner, Job
from busgate.gateway.scheduler.tickers import FollowStream, FollowTicker


class FollowStreams:
    """Starts, feeds and ends the follow streams of the devices on one bus."""

    def __init__(
        self, planner: BusPlanner, counters: BusCounters, drivers: dict[str, Driver]
    ) -> None:
        self.planner = planner
        self.counters = counters
        self.drivers = drivers
        self._streams: dict[str, FollowStream] = {}
        #: Told of a device whose stream ended, with when its last tick went (rule 3).
        self.on_left: Callable[[Driver, float], None] = lambda driver, at: None

    def store_latest(self, device: str, target: Any, moment: float, follows: Follows) -> bool:
        """Any thread: the new target of ``device``'s running stream of what the target
        ``follows``; ``False`` (nothing stored) when it has none, or a ramp that ends on its
        target (fed here, it would never go stale), and the bus thread must ``start`` one (or
        refuse the target: ``BusWork.start_stream``)."""
        stream = self._streams.get(device)
        if stream is None or stream.limiter.follows != follows or stream.ends_on_target:
            return False  # a ramp: the bus thread makes it a stream again, which goes stale
        stream.latest = (target, moment)
        return True

    def following(self, device: str) -> bool:
        """Whether ``device`` has a running stream."""
        return device in self._streams

    def sent(self, device: str, follows: Follows) -> float | None:
        """Where ``device``'s running stream of what it ``follows`` sent it last
        (``FollowStream.sent_value``), or ``None`` with no such stream."""
        stream = self._streams.get(device)
        if stream is None or stream.limiter.follows != follows:
            return None
        return stream.sent_value()

    def fed(self, device: str) -> bool:
        """Whether ``device``'s running stream takes a client's targets as they come (a
        follow stream; not a ramp to a target kept, which a new target feeds)."""
        stream = self._streams.get(device)
        return stream is not None and not stream.ends_on_target

    def start(
        self, driver: Driver, target: Any, moment: float, *, ends_on_target: bool = False
    ) -> None:
        """Start (or feed) ``driver``'s stream on a ticker of its kind and period with room;
        with ``ends_on_target``, a ramp to ``target`` that ends there (``tickers`` rule 5)."""
        period = driver.follow_period_s
        tickers = self._tickers()
        chosen = next((t for t in tickers if driver.name in t.streams), None) or next(
            (
                t
                for t in tickers
                if t.driver_class is type(driver) and t.period_s == period and t.has_room(driver)
            ),
            None,
        )
        if chosen is None:
            chosen = FollowTicker(
                type(driver),
                period,
                self.counters,
                self._went_stale,
                self._reached,
                spacing=self.planner.spacing,
                on_ramp_sent=lambda driver, at: self.on_left(driver, at),
            )
            self.planner.tickers.append(chosen)
        self._streams[driver.name] = chosen.update(
            driver, target, moment, ends_on_target=ends_on_target
        )

    def end(self, device: str, reason: str) -> None:
        """End ``device``'s stream now, as if it went stale (rule 2)."""
        for ticker in self._tickers():
            if device in ticker.streams:
                ticker.stop(device)
                self._ended(self.drivers[device], "stream_stopped", reason=reason)

    def drop(self, device: str, reason: str) -> None:
        """End ``device``'s stream without its stale-stream requests (a trajectory takes the
        device from where the stream left it); reported ``stream_stopped``."""
        for ticker in self._tickers():
            if device in ticker.streams:
                ticker.stop(device)
                self._streams.pop(device, None)
                self.drivers[device].emit("stream_stopped", reason=reason)

    def end_all(self, reason: str) -> None:
        """End every stream, reported only (rule 2)."""
        for ticker in self._tickers():
            for name in list(ticker.streams):
                ticker.stop(name)
                self._streams.pop(name, None)
                self.drivers[name].emit("stream_stopped", reason=reason)
                self._left(self.drivers[name])

    def _reached(self, driver: Driver) -> None:
        """A ramp sent its target: the device keeps it; nothing to report."""
        self._streams.pop(driver.name, None)

    def _went_stale(self, driver: Driver) -> None:
        self._ended(driver, "stream_stale")

    def _ended(self, driver: Driver, event: str, **fields: Any) -> None:
        self._streams.pop(driver.name, None)
        driver.emit(event, **fields)
        self._left(driver)
        requests = driver.stale_stream()
        if requests:
            self.planner.push_stop(Job(driver.name, deque(requests)))

    def _left(self, driver: Driver) -> None:
        """``driver``'s stream ended after its last tick went, if one did (rule 3); not while
        a command's follow target to it waits to go (that one will be the last)."""
        at = self.planner.spacing.last(driver.name)
        if at is not None and at > -math.inf:
            self.on_left(driver, at)

    def _tickers(self) -> list[FollowTicker]:
        return [t for t in self.planner.tickers if isinstance(t, FollowTicker)]

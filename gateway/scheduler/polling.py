"""A device's telemetry reads at its poll rate, and what a poll is while the device is away.

Its own module because polling is the one place where a device's being online changes what
the bus sends on its behalf: an online device is polled, one that went offline (or was never
sent its ``init``) is asked whether it is back (its ``init``), and one that rebooted first gets
its settings again.
"""

from __future__ import annotations

from busgate.gateway.bus.request import Request
from busgate.gateway.drivers.base import Driver

#: How often a device that went offline is asked whether it is back.
OFFLINE_PROBE_S = 0.25


class DevicePoller:
    """A driver's telemetry reads at its poll rate (a ``planner.Poller``); an offline device
    is asked at most every ``OFFLINE_PROBE_S``, so that one silent device (each of its polls
    a timeout, its retries and a hold-off) does not take its neighbours' share of the bus."""

    def __init__(self, driver: Driver, poll_hz: float, start: float) -> None:
        self.driver = driver
        self.device = driver.name
        self.poll_period_s = 1.0 / poll_hz
        self.next_due = start
        #: The poll last built carries the device's settings again (its ``restore``).
        self._restoring = False
        #: Its ``init`` was built (``_greeting``: the poll last built is the first): a device
        #: that reports unasked (heartbeats) may be online before it, and is sent it then.
        self._greeted = self._greeting = False

    @property
    def period_s(self) -> float:
        if self.driver.online:
            return self.poll_period_s
        return max(self.poll_period_s, OFFLINE_PROBE_S)

    def build(self) -> list[Request]:
        driver = self.driver
        self._restoring = driver.online and driver.restore_pending
        self._greeting = not self._greeted
        if not driver.online or self._greeting:  # online before its first: a report unasked
            self._greeted = True
            return driver.init()
        if self._restoring:  # it rebooted: its settings again, then the poll
            driver.restore_pending = False
            return driver.restore() + driver.poll()
        return driver.poll()

    def withdrawn(self) -> None:
        if self._restoring:  # the settings never went: due with the next poll
            self.driver.restore_pending = True
        self._greeted = self._greeted and not self._greeting
        self._restoring = self._greeting = False

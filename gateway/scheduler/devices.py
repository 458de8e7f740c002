"""The devices of one bus as its thread meets them: each driver by name, the driver a reply
or a frame nobody asked for comes from, and which devices have news for their clients.

It is made before the bus owner, so that the owner is made with where frames nobody asked
for (heartbeats) go: straight to their device's driver, from the owner that read them. The
bus's telemetry, made after it, takes the one hook it has (``before_next_reading``): a look
at the bus may take two readings of one device (two heartbeats), and the first one's state
must be made before the second overwrites it. Bus thread only.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping

from busgate.codecs.framing import ExpectedReply
from busgate.gateway.drivers.base import Driver
from busgate.gateway.scheduler.planner import EVERY_DEVICE, Job


class BusDevices:
    """The drivers of one bus, and which of them have a new state to publish."""

    def __init__(self, drivers: Iterable[Driver]) -> None:
        self.drivers = {driver.name: driver for driver in drivers}
        self._news: set[str] = set(self.drivers)  # every device's first state is news
        #: Called with a device whose news is not yet published when its next reading
        #: begins, before that reading's first frame is taken in (the telemetry publishes it).
        self.before_next_reading: Callable[[Driver], None] = _nothing

    def answering(self, expected: ExpectedReply) -> Driver | None:
        """The device a reply ``expected`` comes from: the one with its id now (an id changes
        with ``set_id``), or a point-to-point line's one device (a reply without an id)."""
        for driver in self.drivers.values():
            if expected.source_id in (driver.device_id, None):
                return driver
        return None

    def unsolicited(self, event: object, when: float) -> None:
        """A frame nobody asked for (a heartbeat, an alarm report): to the driver of the
        device it names; that device has news when its driver says so (a heartbeat's first
        frame waits for its second)."""
        device_id = getattr(event, "device_id", None)  # a frame naming no device is nobody's
        for driver in self.drivers.values():
            if driver.device_id == device_id:
                if driver.name in self._news and driver.begins_reading(event):
                    self.before_next_reading(driver)
                if driver.unsolicited(event, when):
                    self.touched(driver)
                return

    def touched(self, driver: Driver) -> None:
        """Something happened to ``driver``'s device: its state is news."""
        self._news.add(driver.name)

    def published(self, driver: Driver) -> None:
        """``driver``'s news is published (ahead of the others')."""
        self._news.discard(driver.name)

    @property
    def has_news(self) -> bool:
        return bool(self._news)

    def take_news(self) -> set[str]:
        """The devices with news since the last call."""
        news, self._news = self._news, set()
        return news


def tell_unsent(job: Job, drivers: Mapping[str, Driver]) -> None:
    """``job`` was taken out before all its frames went (it expired, was withdrawn, refused
    ``busy``, or its bus went down): each device it was for, or moved, is told
    (``Driver.unsent``), and gets back the e-stop its planning changed (a re-enable or a
    reset that never went leaves the device e-stopped)."""
    names = {job.device, *job.also_moves}
    for driver in drivers.values():
        if EVERY_DEVICE in names or driver.name in names:
            driver.unsent()
        if driver.name in job.estop_before:
            driver.estop_latched, driver.driving_before_estop = job.estop_before[driver.name]


def estop_states(drivers: Iterable[Driver]) -> dict[str, tuple[bool, bool]]:
    """Each driver's e-stop as a job's planning may change it: latched, and whether it was
    driving when it latched (``Job.estop_before``)."""
    return {d.name: (d.estop_latched, d.driving_before_estop) for d in drivers}


def estop_changed(
    before: dict[str, tuple[bool, bool]], drivers: Iterable[Driver]
) -> dict[str, tuple[bool, bool]]:
    """The entries of ``before`` (``estop_states``) that the drivers no longer hold."""
    now = estop_states(drivers)
    return {name: state for name, state in before.items() if now[name] != state}


def _nothing(_driver: Driver) -> None:
    pass

"""A driver's state as its bus publishes it (``Telemetry`` stamps it and sets its ``stale``
flag), for the tests that read a whole state off a driver they drove by hand."""

from __future__ import annotations

from typing import Any

from busgate.gateway.drivers.base import Driver
from busgate.gateway.scheduler.devices import BusDevices
from busgate.gateway.scheduler.telemetry import Telemetry


def published(driver: Driver, now: float) -> dict[str, Any]:
    """``driver``'s state at ``now`` (bus clock) as the bus runner publishes it (a device
    polled at no rate is never stale)."""
    telemetry = Telemetry("bus", BusDevices([driver]), {}, on_event=lambda event: None,
                          on_state=lambda device, state: None)
    return telemetry.reply_state(driver, now)

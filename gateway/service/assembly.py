"""From a bus's configuration to a running bus: owner, timing, drivers, runner.

One function builds a bus wherever one is needed (``busgate bench``, the daemon), so a bus in
a benchmark is the same machine as a bus in production.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from busgate.gateway.bus.can_owner import CanBusOwner
from busgate.gateway.bus.clock import now
from busgate.gateway.bus.serial_owner import SerialBusOwner
from busgate.gateway.bus.stats import BusCounters
from busgate.gateway.drivers.base import DeviceEvent
from busgate.gateway.drivers.families import check_family, link_timing, make_driver
from busgate.gateway.scheduler.runner import BusRunner
from busgate.schemas.config import CanBus, SerialBus
from busgate.schemas.families import FAMILIES, PROTOCOLS


def build_bus(
    bus: SerialBus | CanBus,
    *,
    on_event: Callable[[DeviceEvent], None] = lambda e: None,
    on_state: Callable[[str, dict[str, Any]], None] = lambda device, state: None,
) -> BusRunner:
    """A bus runner for ``bus`` (not started)."""
    protocol = PROTOCOLS[bus.protocol]
    check_family(FAMILIES[protocol.kind])  # a part missing is named here, before anything opens
    drivers = [make_driver(device, protocol) for device in bus.devices]
    counters = BusCounters(now())
    margin = bus.reply_margin_ms / 1000
    owner: SerialBusOwner | CanBusOwner
    if isinstance(bus, SerialBus):
        timing = link_timing(bus.protocol, bus.baudrate, margin_s=margin, gap_s=bus.gap_s)
        owner = SerialBusOwner(bus.port, protocol.codec, timing, counters)
    else:
        timing = link_timing(bus.protocol, bus.bitrate, margin_s=margin)
        owner = CanBusOwner(
            bus.interface,
            bus.channel,
            bus.options,
            protocol.codec,
            timing,
            counters,
            on_unsolicited=lambda event, when: None,
        )
    runner = BusRunner(
        bus.name,
        owner,
        timing,
        drivers,
        poll_hz={device.name: device.poll_hz for device in bus.devices},
        on_event=on_event,
        on_state=on_state,
        realtime_priority=bus.realtime_priority,
        late_reply_holdoff_s=bus.late_reply_holdoff_ms / 1000,
    )
    if isinstance(owner, CanBusOwner):
        owner.on_unsolicited = runner.unsolicited  # heartbeats go to their drivers
    return runner

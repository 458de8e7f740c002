"""From a bus's configuration to a running bus: drivers, timing, owner, runner; and the
buses stopped together.

One function builds a bus wherever one is needed (``busgate bench``, the daemon, a bus
worker), so a bus in a benchmark is the same machine as a bus in production. The devices come
first: a CAN owner is made with where the frames nobody asked for go (their drivers), and the
runner with the same devices, so nothing is wired after it was made. ``stop_together`` stops
them (and a daemon's workers) all at once, as the daemon and a worker do on their way out.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterable
from typing import Any

from busgate.gateway.bus.can_owner import CanBusOwner
from busgate.gateway.bus.clock import ask_realtime, now
from busgate.gateway.bus.owner import BusOwner
from busgate.gateway.bus.serial_owner import SerialBusOwner
from busgate.gateway.bus.stats import BusCounters
from busgate.gateway.drivers.base import DeviceEvent
from busgate.gateway.drivers.families import check_family, link_timing, make_driver
from busgate.gateway.scheduler.devices import BusDevices
from busgate.gateway.scheduler.runner import BusRunner
from busgate.schemas.config import CanBus, Config, SerialBus
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
    devices = BusDevices(make_driver(device, protocol) for device in bus.devices)
    counters = BusCounters(now())
    margin = bus.reply_margin_ms / 1000
    owner: BusOwner
    if isinstance(bus, SerialBus):
        timing = link_timing(bus.protocol, bus.baudrate, margin_s=margin, gap_s=bus.gap_s)
        owner = SerialBusOwner(bus.port, protocol.codec, timing, counters)
    else:
        timing = link_timing(bus.protocol, bus.bitrate, margin_s=margin)
        owner = CanBusOwner(
            bus.interface,
            bus.channel,
            bus.options.arguments(),
            protocol.codec,
            timing,
            counters,
            on_unsolicited=devices.unsolicited,  # heartbeats go to their drivers
        )
    return BusRunner(
        bus.name,
        owner,
        timing,
        devices,
        poll_hz={device.name: device.poll_hz for device in bus.devices},
        on_event=on_event,
        on_state=on_state,
        realtime_priority=bus.realtime_priority,
        late_reply_holdoff_s=bus.late_reply_holdoff_ms / 1000,
    )


def realtime_process(config: Config, who: str) -> bool:
    """When a bus of ``config`` asks for SCHED_FIFO (``realtime_priority``), the calling
    thread asks for the highest priority asked, before it starts any other: every thread
    the process starts afterwards inherits it (zenoh's, the publishing loop's, a worker's
    reader), and each bus thread then asks its own. Not the bus threads alone: an e-stop
    reaches them through those threads, and any of them may hold the interpreter a bus thread
    waits for; at normal priority, each would wait behind every other process of the host
    for a core. Whether it was asked and granted."""
    priorities = [bus.realtime_priority for bus in config.buses if bus.realtime_priority]
    return bool(priorities) and ask_realtime(max(priorities), who)


#: How long a bus is given to stop (streams, safe state, close) when it is stopped.
STOP_TIMEOUT_S = 0.8


def stop_together(stops: Iterable[Callable[[], None]]) -> None:
    """Call every stop at once, each on a thread of its own (one bus's safe-state frames never
    wait for another's), and return when all have returned."""
    threads = [threading.Thread(target=stop) for stop in stops]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()

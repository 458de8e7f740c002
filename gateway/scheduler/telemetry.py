"""What the bus thread tells clients about its devices: their events, logged and handed on,
and a fresh state for each device with news that changed it.

Its own module because it is the one place a published state is finished: it gets its ``ts``
here (wall time, since clients compare it with their own clock; the drivers know only the
bus thread's clock) and its ``stale`` flag, both for the states streamed and for the state a
command's reply carries. Bus thread only; ``on_event`` and ``on_state`` may not block.

Rules of this file:

1. ``ts`` is when the values were read: the device's last reply (``last_reply``, bus clock)
   in wall time, converted once per reply, so every state of one reading carries the same
   ``ts``. A device never read is stamped when its state is taken (nothing was measured).
2. A device with news is published only when its state differs from the last one published
   in more than ``last_reply_age_s``: a follow tick that read nothing (an LA's follow frame
   has no reply) publishes nothing, every reply does (a new ``ts``). A device with events
   publishes its state with them. The state is built only once it is known to differ: it
   is judged by what it is made of (``Told``), a reading's time, three flags and the
   driver's telemetry, not by building it and comparing two copies (a follow tick marks
   each device it carried, a hundred times a second). A device never read is judged without
   its ``ts`` on purpose: stamped when taken, it would make every look a new state.
3. Every reading is published: when a look at the bus takes a device's next reading (a second
   heartbeat) before its state was published, that state is made first
   (``BusDevices.before_next_reading``).
4. Every event is published; its log line, at most one a device and type every
   ``EVENT_LOG_EVERY_S`` (a fault that flaps at the poll rate, a device that reboots again
   and again, would fill the journal, whose rate limit then drops the service's other
   lines). A line held back is written once its interval has passed, if no newer one of its
   kind came, so the log's last word on a device is its last event; a line says how many it
   held back before it.
5. A command's reply carries its device's state as it is when the command ends, and that
   state is published first when it differs from the last one (``reply_state``): a client
   holding the reply finds no older state in the info, and the stream brings none older after
   it.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from typing import Any

from busgate.gateway.bus.clock import now
from busgate.gateway.drivers.base import DeviceEvent, Driver
from busgate.gateway.scheduler.devices import BusDevices

log = logging.getLogger(__name__)

#: Telemetry older than this many poll periods is marked stale.
STALE_PERIODS = 3
#: The shortest time between two log lines of one device's events of one type (rule 4).
EVENT_LOG_EVERY_S = 1.0

#: What a device's state is made of, all but its age (rule 2): the bus-clock time of the
#: reading (``last_reply``; ``None``: never read), ``online``, ``estopped``, ``stale``, and
#: the driver's telemetry (``joint`` is computed from it, ``device`` and ``kind`` never change).
Told = tuple[float | None, bool, bool, bool, dict[str, Any]]


class Telemetry:
    """The events and states of the devices of one bus."""

    def __init__(
        self,
        bus: str,
        devices: BusDevices,
        poll_periods: dict[str, float],
        *,
        on_event: Callable[[DeviceEvent], None],
        on_state: Callable[[str, dict[str, Any]], None],
    ) -> None:
        self.bus = bus
        self.devices = devices
        self.poll_periods = poll_periods
        self.on_event = on_event
        self.on_state = on_state
        #: The last state published of each device (read from any thread, one item at a time).
        self.states: dict[str, dict[str, Any]] = {}
        #: Each device's last reply, bus clock, and its wall time (rule 1).
        self._read_at: dict[str, tuple[float, float]] = {}
        #: What each device's last published state was made of (rule 2).
        self._told: dict[str, Told] = {}
        #: The last ``publish`` sent events.
        self.had_events = False
        #: Per (device, event type): when its last line was logged, and the line held back
        #: since with how many were (rule 4).
        self._logged_at: dict[tuple[str, str], float] = {}
        self._held_back: dict[tuple[str, str], tuple[DeviceEvent, int]] = {}
        devices.before_next_reading = self._publish_reading

    def _publish_reading(self, driver: Driver) -> None:
        """``driver``'s state now, ahead of the others', before its next reading overwrites it
        (rule 3); its events go with the next ``publish``."""
        self.devices.published(driver)
        self._state_out(driver, now(), changed_only=True)

    def publish(self, moment: float) -> list[str]:
        """Events out, and a fresh state for each device with events, or with news that
        changed its state (rule 2); the devices that rebooted (their follow targets are
        stale) come back."""
        news = self.devices.take_news()
        rebooted = []
        self.had_events = False
        if self._held_back:
            self._log_held_back(moment)
        for name, driver in self.devices.drivers.items():
            driver.check_heartbeat(moment)
            events = driver.drain_events()
            if events:
                self.had_events = True
            for event in events:
                self.tell(event, moment)
                if event.type == "rebooted":
                    rebooted.append(name)
            if events or name in news:
                self._state_out(driver, moment, changed_only=not events)
        return rebooted

    def tell(self, event: DeviceEvent, moment: float) -> None:
        """``event`` in the log (rule 4) and handed on."""
        self._log(event, moment)
        self.on_event(event)

    def _state_out(self, driver: Driver, moment: float, *, changed_only: bool) -> None:
        """``driver``'s state at ``moment`` handed on, unless ``changed_only`` and it is made of
        what the last one was (rule 2)."""
        told = self._made_of(driver, moment)
        if changed_only and told == self._told.get(driver.name):
            return
        self._handed_on(driver.name, told, self._built(driver, moment, told))

    def _handed_on(self, device: str, told: Told, state: dict[str, Any]) -> None:
        self._told[device] = told
        self.states[device] = state
        self.on_state(device, state)

    def reply_state(self, driver: Driver, moment: float) -> dict[str, Any]:
        """``driver``'s state for a command's reply at ``moment`` (bus clock), published first
        when it differs from the last one published (rule 5): stamped with when it was read
        (rule 1), and marked ``stale`` when its telemetry is more than ``STALE_PERIODS`` poll
        periods old (an oversubscribed bus, or a device not answering)."""
        told = self._made_of(driver, moment)
        state = self._built(driver, moment, told)
        if told != self._told.get(driver.name):
            self._handed_on(driver.name, told, state)
        return state

    def _made_of(self, driver: Driver, moment: float) -> Told:
        replied = driver.last_reply
        period = self.poll_periods.get(driver.name)
        stale = period is not None and (
            replied is None or moment - replied > STALE_PERIODS * period
        )
        return replied, driver.online, driver.estopped, stale, driver.telemetry(moment)

    def _built(self, driver: Driver, moment: float, told: Told) -> dict[str, Any]:
        """``driver``'s state, made of ``told`` (its envelope, ``ts`` first and ``stale`` last,
        around the driver's telemetry): one dict, built once (a heartbeat makes one)."""
        replied, online, estopped, stale, telemetry = told
        return {
            "ts": self._read_time(driver, moment),
            "device": driver.name,
            "kind": driver.kind,
            "online": online,
            "last_reply_age_s": None if replied is None else moment - replied,
            "estopped": estopped,
            **telemetry,
            "joint": driver.joint.state(telemetry),
            "stale": stale,
        }

    def _read_time(self, driver: Driver, moment: float) -> float:
        """The wall time of ``driver``'s last reply, converted when first asked for; the wall
        time now for a device never read."""
        replied = driver.last_reply
        if replied is None:
            return time.time()
        read = self._read_at.get(driver.name)
        if read is None or read[0] != replied:
            read = self._read_at[driver.name] = (replied, time.time() - (moment - replied))
        return read[1]

    def _log(self, event: DeviceEvent, moment: float) -> None:
        """``event``'s line, or held back (rule 4)."""
        kind = (event.device, event.type)
        _, held = self._held_back.pop(kind, (event, 0))
        if moment - self._logged_at.get(kind, -math.inf) < EVENT_LOG_EVERY_S:
            self._held_back[kind] = (event, held + 1)
        else:
            self._write_line(kind, event, held, moment)

    def _log_held_back(self, moment: float) -> None:
        for kind, (event, held) in list(self._held_back.items()):
            if moment - self._logged_at[kind] >= EVENT_LOG_EVERY_S:
                del self._held_back[kind]
                self._write_line(kind, event, held - 1, moment)

    def _write_line(
        self, kind: tuple[str, str], event: DeviceEvent, held: int, moment: float
    ) -> None:
        """``event``'s line, saying how many of its kind were held back before it."""
        self._logged_at[kind] = moment
        details = " ".join(f"{key}={value}" for key, value in event.fields.items())
        log.info(
            "bus %s device %s: %s%s%s",
            self.bus,
            event.device,
            event.type,
            f" ({details})" if details else "",
            f" [{held} more {event.type} lines held back before this one]" if held else "",
        )

"""How a put that gets no reply is told: a refused put as a ``command_refused`` event, at most
one a device every ``TOLD_EVERY_S``; an e-stop and an e-stop reset as an ``estop`` or
``estop_reset`` event and a log line, at most one of each every ``TOLD_EVERY_S``.

A put gets no reply, so its refusal is an event, published on two keys to every subscriber of
events (dashboards, recorders, other clients). A client streaming targets at 100 Hz to an
e-stopped device, or flooding bad puts, would otherwise make an event of every put and bury
the events that matter under them; a client putting e-stops in a loop (a button held, a
teleoperation program that sends one each turn) would do the same, with a log line each that
the journal's rate limit would answer by dropping the service's other lines.

Rules of this file:

1. Nothing is lost: a put is either told, or withheld and counted in the ``suppressed``
   field of the next one told in its slot (a device's refusals, the e-stops, the resets)
   since the last told one. The last withheld one is told by ``flush`` once its slot's interval has
   passed, so a burst's end is told, however the burst ended.
2. Memory is bounded whatever the names: each device and base of the gateway has a slot of
   its own; a name the gateway does not have counts under one shared slot, its event naming
   the device as the put did (cut, ``shown``); every e-stop, whoever sent it, under one
   other, and every reset under a third.
3. Any thread may report (zenoh's, a bus thread's future callback); ``flush`` runs on the
   publishing loop's thread. One lock guards the slots.
4. E-stops and resets are told in the order they came: an e-stop withheld when a reset comes
   is told first, whatever its interval, and a reset withheld when an e-stop comes (else the
   journal of a stuck button let go, then a reset, read as an e-stop after the reset).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass
from typing import Any

from busgate.gateway.bus.clock import now
from busgate.gateway.drivers.base import DeviceEvent
from busgate.schemas.validation import shown

log = logging.getLogger(__name__)

#: The shortest time between two puts told in one slot.
TOLD_EVERY_S = 0.1
#: The slot of every device name the gateway does not have (rule 2): no device has this name,
#: a configured name being a single key chunk.
UNKNOWN = "/"
#: The slots of the e-stops and of their resets (rule 2), which no device name can be either.
ESTOPS, RESETS = "*", "*/reset"
#: Of e-stops and resets, the slot told first when the other's put comes (rule 4).
_OTHER_OF = {ESTOPS: RESETS, RESETS: ESTOPS}


@dataclass(slots=True)
class _Slot:
    told_at: float = float("-inf")
    withheld: int = 0  # puts not told, the latest (``latest``) included
    latest: DeviceEvent | None = None  # the latest withheld put's event


class PutReports:
    """The events of refused puts, e-stops and their resets, at most one a slot per interval
    (the rules above); ``tell`` gets each event told."""

    def __init__(
        self,
        devices: Collection[str],
        tell: Callable[[DeviceEvent], None],
        *,
        every_s: float = TOLD_EVERY_S,
        clock: Callable[[], float] = now,
    ) -> None:
        self._devices = devices
        self._tell = tell
        self._every_s = every_s
        self._clock = clock
        self._slots: dict[str, _Slot] = {}
        self._pending = 0  # slots with a withheld put: ``flush`` looks only when some are
        self._lock = threading.Lock()

    def refused(self, device: str, error: dict[str, Any]) -> None:
        """A put naming ``device`` was refused with ``error`` (``code``, ``message``)."""
        slot = device if device in self._devices else UNKNOWN
        self._report(slot, DeviceEvent(shown(device), "command_refused", error))

    def estop(self, key: str, sender: str | None) -> None:
        """An e-stop was put on ``key`` by ``sender`` (when it named itself)."""
        fields = {"key": key} | client_field(sender)
        self._report(ESTOPS, DeviceEvent("*", "estop", fields))

    def estop_reset(self, sender: str | None, not_reset: Sequence[str] = ()) -> None:
        """Every device's e-stop was reset by a put of ``sender`` (when it named itself), but
        those ``not_reset`` (claimed by another client)."""
        self._report(RESETS, DeviceEvent("*", "estop_reset", reset_fields(sender, not_reset)))

    @property
    def withheld(self) -> bool:
        """Whether a put waits for its slot's interval to pass (for a later ``flush``)."""
        return bool(self._pending)

    def flush(self, *, every: bool = False) -> None:
        """Tell each withheld put whose slot's interval has passed (rule 1); with ``every``,
        each one withheld (the gateway stops: nothing waits for a next round)."""
        if not self._pending:
            return
        moment = self._clock()
        with self._lock:
            for slot in self._slots.values():
                if slot.latest is not None and (every or moment - slot.told_at >= self._every_s):
                    self._told_withheld(slot, moment)

    def _report(self, name: str, event: DeviceEvent) -> None:
        moment = self._clock()
        with self._lock:
            other = _OTHER_OF.get(name)
            before = self._slots.get(other) if other is not None else None
            if before is not None and before.latest is not None:  # rule 4
                self._told_withheld(before, moment)
            slot = self._slots.get(name)
            if slot is None:
                slot = self._slots[name] = _Slot()
            if moment - slot.told_at >= self._every_s:
                self._told(slot, event, moment)
                return
            if slot.latest is None:
                self._pending += 1
            slot.withheld += 1
            slot.latest = event

    def _told_withheld(self, slot: _Slot, moment: float) -> None:
        """Under the lock: ``slot``'s latest withheld put told now."""
        assert slot.latest is not None
        slot.withheld -= 1  # the one told is not suppressed
        self._told(slot, slot.latest, moment)

    def _told(self, slot: _Slot, event: DeviceEvent, moment: float) -> None:
        """Under the lock: ``event`` told now, with the count of those withheld before it."""
        if slot.withheld:
            fields = event.fields | {"suppressed": slot.withheld}
            event = DeviceEvent(event.device, event.type, fields)
        if slot.latest is not None:
            self._pending -= 1
        slot.told_at, slot.withheld, slot.latest = moment, 0, None
        self._tell(event)


def reset_fields(sender: str | None, not_reset: Sequence[str]) -> dict[str, Any]:
    """The fields of a whole gateway's ``estop_reset`` event: its ``client`` when it named
    one, and the devices it left to their holders (``not_reset``) when there are any."""
    return client_field(sender) | ({"not_reset": list(not_reset)} if not_reset else {})


def client_field(sender: str | None) -> dict[str, str]:
    """An event's ``client``: the one that sent what it tells, when it named one."""
    return {"client": sender} if sender else {}


#: The log line of an e-stop and of an e-stop reset of the whole gateway, by event type.
TOLD_LINES = {"estop": "e-stop of every bus", "estop_reset": "e-stop reset of every bus"}


def log_told(
    event_type: str, sender: str | None, suppressed: int = 0, not_reset: Sequence[str] = ()
) -> None:
    """The log line of an e-stop or a reset of the whole gateway (``TOLD_LINES``), naming the
    client that sent it when known, how many came since the last line without one of their
    own (``put_reports``), and the devices a reset left to their holders
    (``reset_every_bus``)."""
    since = f" ({suppressed} more since the last told)" if suppressed else ""
    log.warning(
        "%s%s%s%s",
        TOLD_LINES[event_type],
        f" from {sender}" if sender else "",
        since,
        not_reset_said(not_reset),
    )


def not_reset_said(not_reset: Sequence[str]) -> str:
    """What a reset of the whole gateway's line or answer adds of the devices it left to
    their holders (``reset_every_bus``); nothing when it left none."""
    return f"; not reset, claimed by another client: {', '.join(not_reset)}" if not_reset else ""

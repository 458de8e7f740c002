"""How a refused put is told: as a ``command_refused`` event, at most one a device every
``TOLD_EVERY_S``.

A put gets no reply, so its refusal is an event, published on two keys to every subscriber of
events (dashboards, recorders, other clients). A client streaming targets at 100 Hz to an
e-stopped device, or flooding bad puts, would otherwise make an event of every put and bury
the events that matter under them.

Rules of this file:

1. Nothing is lost: a refusal is either told, or withheld and counted in the ``suppressed``
   field of the next one told for its device (the refusals of that device not told since the
   last told one). The last withheld refusal is told by ``flush`` once its device's interval
   has passed, so a burst's end is told, however the burst ended.
2. Memory is bounded whatever the names: a device the gateway does not have counts under one
   shared slot, its event naming the device as the put did (cut, ``shown``).
3. Any thread may report a refusal (zenoh's, a bus thread's future callback); ``flush`` runs on
   the publishing loop's thread. One lock guards the slots.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Collection
from dataclasses import dataclass
from typing import Any

from busgate.gateway.drivers.base import DeviceEvent
from busgate.schemas.validation import shown

#: The shortest time between two refusals told for one device.
TOLD_EVERY_S = 0.1
#: The slot of every device name the gateway does not have (rule 2): no device has this name,
#: a configured name being a single key chunk.
UNKNOWN = "/"


@dataclass(slots=True)
class _Slot:
    told_at: float = float("-inf")
    withheld: int = 0  # refusals not told, the latest (``latest``) included
    latest: tuple[str, dict[str, Any]] | None = None  # the device as named, the error


class RefusalReports:
    """The ``command_refused`` events of refused puts, at most one a device per interval."""

    def __init__(
        self,
        devices: Collection[str],
        tell: Callable[[DeviceEvent], None],
        *,
        every_s: float = TOLD_EVERY_S,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._devices = devices
        self._tell = tell
        self._every_s = every_s
        self._clock = clock
        self._slots: dict[str, _Slot] = {}
        self._pending = 0  # slots with a withheld refusal: ``flush`` looks only when some are
        self._lock = threading.Lock()

    def refused(self, device: str, error: dict[str, Any]) -> None:
        """A put naming ``device`` was refused with ``error`` (``code``, ``message``)."""
        key = device if device in self._devices else UNKNOWN
        moment = self._clock()
        with self._lock:
            slot = self._slots.get(key)
            if slot is None:
                slot = self._slots[key] = _Slot()
            if moment - slot.told_at >= self._every_s:
                self._told(slot, shown(device), error, moment)
                return
            if slot.latest is None:
                self._pending += 1
            slot.withheld += 1
            slot.latest = (shown(device), error)

    @property
    def withheld(self) -> bool:
        """Whether a refusal waits for its device's interval to pass (for a later ``flush``)."""
        return bool(self._pending)

    def flush(self, *, every: bool = False) -> None:
        """Tell each withheld refusal whose device's interval has passed (rule 1); with
        ``every``, each one withheld (the gateway stops: nothing waits for a next round)."""
        if not self._pending:
            return
        moment = self._clock()
        with self._lock:
            for slot in self._slots.values():
                if slot.latest is not None and (every or moment - slot.told_at >= self._every_s):
                    device, error = slot.latest
                    slot.withheld -= 1  # the one told is not suppressed
                    self._told(slot, device, error, moment)

    def _told(self, slot: _Slot, device: str, error: dict[str, Any], moment: float) -> None:
        """Under the lock: ``error`` told now, with the count of those withheld before it."""
        fields = (error | {"suppressed": slot.withheld}) if slot.withheld else error
        if slot.latest is not None:
            self._pending -= 1
        slot.told_at, slot.withheld, slot.latest = moment, 0, None
        self._tell(DeviceEvent(device, "command_refused", fields))

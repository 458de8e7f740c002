"""``<prefix>/<gw>/joints``: every joint of the gateway in one message, the feed a robot's
controller, ROS or a dashboard wants rather than one state key per device.

Rules of this file:

1. Each joint's entry comes from its device's latest published state (its ``joint`` values,
   ``ts`` and ``stale``): the same reading as the state, never a second one.
2. The message goes out when any joint was read again (a state with a new ``ts``), at most
   once per ``min_interval_s`` (the fastest poll period of the gateway's devices); a joint
   never read is in it with null values and ``ts`` null.
3. Pure: the bridge hands it states and asks it, on the loop's thread, what to publish.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from busgate.gateway.drivers.base import Driver


class JointsFeed:
    """The joints message of one gateway (the rules above)."""

    def __init__(self, gateway: str, drivers: Iterable[Driver], min_interval_s: float) -> None:
        self.gateway = gateway
        self.min_interval_s = min_interval_s
        #: Each joint's entry without its values, by device.
        self._joints: dict[str, dict[str, Any]] = {
            driver.name: {
                "name": driver.joint.name,
                "device": driver.name,
                "type": driver.joint.type,
                "unit": driver.joint.unit,
            }
            for driver in drivers
        }
        #: Each device's latest state with a joint (states are not changed once published):
        #: its entry is built when a message goes out, not at every state.
        self._latest: dict[str, dict[str, Any]] = {}
        #: Each device's state an entry was last built from, and that entry as sent: a
        #: device not read again since keeps it (an entry is not changed once sent either).
        self._sent: dict[str, tuple[dict[str, Any], dict[str, Any]]] = {}
        self._read_again = False
        self._last_sent: float | None = None

    def take(self, device: str, state: dict[str, Any]) -> None:
        """A state published for ``device``: its joint's values, if read again."""
        if device not in self._joints or not isinstance(state.get("joint"), dict):
            return
        if state.get("ts") != self._latest.get(device, _NEVER_READ).get("ts"):
            self._read_again = True
        self._latest[device] = state

    def due_in(self, moment: float) -> float | None:
        """How long from ``moment`` until the next message may go out (0: now); ``None``
        while no joint was read again since the last."""
        if not self._read_again:
            return None
        if self._last_sent is None:
            return 0.0
        return max(0.0, self.min_interval_s - (moment - self._last_sent))

    def due(self, moment: float, wall_time: float) -> dict[str, Any] | None:
        """The message to publish now (``moment`` on a monotonic clock), or ``None``."""
        if self.due_in(moment) != 0.0:  # nothing read again, or too soon after the last
            return None
        self._read_again = False
        self._last_sent = moment
        latest, sent, entries = self._latest, self._sent, []
        for device, joint in self._joints.items():
            state = latest.get(device, _NEVER_READ)
            built = sent.get(device)
            if built is None or built[0] is not state:
                built = sent[device] = (state, _entry(joint, state))
            entries.append(built[1])
        return {"gateway": self.gateway, "ts": wall_time, "joints": entries}


#: The state a joint never read has its entry from: null values, ``ts`` null, stale.
_NEVER_READ: dict[str, Any] = {"joint": {}, "ts": None, "stale": True}


def _entry(joint: dict[str, Any], state: dict[str, Any]) -> dict[str, Any]:
    """A joint's entry: its name, device, type and unit, and the values of ``state`` (set one
    by one: faster than a display that unpacks ``joint``)."""
    values, entry = state["joint"], joint.copy()
    entry["position"] = values.get("position")
    entry["velocity"] = values.get("velocity")
    entry["effort"] = values.get("effort")
    entry["ts"] = state.get("ts")
    entry["stale"] = bool(state.get("stale"))
    return entry

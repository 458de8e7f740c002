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
        self._entries: dict[str, dict[str, Any]] = {
            driver.name: {
                "name": driver.joint.name,
                "device": driver.name,
                "type": driver.joint.type,
                "unit": driver.joint.unit,
                "position": None,
                "velocity": None,
                "effort": None,
                "ts": None,
                "stale": True,
            }
            for driver in drivers
        }
        self._read_again = False
        self._last_sent: float | None = None

    def take(self, device: str, state: dict[str, Any]) -> None:
        """A state published for ``device``: its joint's values, if read again."""
        entry = self._entries.get(device)
        joint = state.get("joint")
        if entry is None or not isinstance(joint, dict):
            return
        if state.get("ts") != entry["ts"]:
            self._read_again = True
        entry.update(
            position=joint.get("position"),
            velocity=joint.get("velocity"),
            effort=joint.get("effort"),
            ts=state.get("ts"),
            stale=bool(state.get("stale")),
        )

    def due(self, moment: float, wall_time: float) -> dict[str, Any] | None:
        """The message to publish now (``moment`` on a monotonic clock), or ``None``."""
        if not self._read_again:
            return None
        if self._last_sent is not None and moment - self._last_sent < self.min_interval_s:
            return None
        self._read_again = False
        self._last_sent = moment
        return {
            "gateway": self.gateway,
            "ts": wall_time,
            "joints": [dict(entry) for entry in self._entries.values()],
        }

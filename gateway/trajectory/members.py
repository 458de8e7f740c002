"""The devices of a trajectory the gateway plays, and what a trajectory needs of its gateway.

Rules of this file: a ``Member`` is one device of one running trajectory, its path and its
tolerances fixed when the play is accepted; it reads the device's state from what its bus
published (``BusRunner.states``, each state replaced whole), never from the bus's live tables.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

from busgate.errors import CommandError, RefusedError
from busgate.gateway.drivers.base import Driver
from busgate.gateway.scheduler.runner import BusRunner
from busgate.gateway.trajectory.interpolation import Path, sent

#: Per values field: the follow payload's key and the telemetry's measured field.
FIELDS = {"positions": ("position", "position"), "rpms": ("rpm", "speed_rpm")}


class Gateway(Protocol):
    """What a trajectory needs of its gateway (``busgate.gateway.api.commands.GatewayApi``):
    its name and its devices, each with the runner of its bus."""

    @property
    def name(self) -> str: ...

    @property
    def devices(self) -> Mapping[str, tuple[BusRunner, Driver]]: ...


@dataclass
class Member:
    """One device of a running trajectory."""

    name: str
    runner: BusRunner
    driver: Driver
    path: Path
    key: str  # the follow payload's key: position or rpm
    measured_key: str
    path_tolerance: float | None
    goal_tolerance: float | None
    claimed: bool  # its client held the device's claim when it started

    def sample(self, t_s: float) -> dict[str, Any]:
        return self.payload(self.path.at(t_s))

    def payload(self, value: float) -> dict[str, Any]:
        """The follow payload that sends ``value``."""
        return {self.key: sent(value) if self.key == "position" else value}

    def takes(self, value: float) -> bool:
        """Whether the device takes ``value`` as its target."""
        try:
            self.driver.follow_target(self.payload(value))
        except (CommandError, RefusedError):
            return False
        return True

    def measured(self) -> tuple[float, float] | None:
        """(wall time read, value) of the device's last published state."""
        state = self.runner.states.get(self.name) or {}
        value, read = state.get(self.measured_key), state.get("ts")
        return None if value is None or read is None else (read, value)


@dataclass
class Running:
    id: str
    client: str | None
    members: list[Member]
    start_at: float  # wall
    start_bus: float  # the same moment, bus clock: the start its devices' tickers have
    end_s: float
    goal_time_s: float
    next_feedback: float = 0.0
    errors: dict[str, float | None] = field(default_factory=dict)

    @property
    def end_at(self) -> float:
        return self.start_at + self.end_s

    def summary(self, moment: float) -> dict[str, Any]:
        t_s = max(0.0, moment - self.start_at)
        return {
            "id": self.id,
            "client": self.client,
            "devices": [m.name for m in self.members],
            "start_at": self.start_at,
            "end_at": self.end_at,
            "t_s": t_s,
            "progress": 1.0 if self.end_s == 0 else min(1.0, t_s / self.end_s),
        }

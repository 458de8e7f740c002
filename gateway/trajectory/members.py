"""The devices of a trajectory the gateway plays, and what a trajectory needs of its gateway.

Rules of this file: a ``Member`` is one device of one running trajectory, its path and its
tolerances fixed when the play is accepted, in the device's raw units; it reads the device's
state from what its bus published (``BusRunner.states``, each state replaced whole), never from
the bus's live tables. Which fields carry its values (the follow payload's, the telemetry's)
is its family's declaration (``Stream``, from ``JointDeclaration``): nothing here names one.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

from busgate.errors import CommandError, RefusedError
from busgate.gateway.drivers.base import Driver
from busgate.gateway.scheduler.runner import BusRunner
from busgate.gateway.trajectory.interpolation import Path, sent
from busgate.schemas.trajectory import ValuesField


@dataclass(frozen=True, slots=True)
class Stream:
    """What a trajectory's values are to one device, by its family's joint declaration: the
    follow payload's field that carries them, and the telemetry's fields of the value it is
    commanded and the value measured (``None``: the family reports none)."""

    follow: str
    commanded: str | None
    measured: str | None
    #: The values are speeds (a speed leaving its trajectory ramps to 0), not positions.
    speed: bool


def stream_of(driver: Driver, values: ValuesField) -> Stream:
    """How ``driver``'s device takes a trajectory's ``values`` (positions or rpms), from its
    family's declaration; ``bad_command`` when it has no follow stream of them."""
    declaration = driver.joint_declaration()
    speed = values == "rpms"
    follow = declaration.follow_velocity if speed else declaration.follow_position
    if follow is None:
        moves = [name for name, key in (("positions", declaration.follow_position),
                                        ("speeds (rpms)", declaration.follow_velocity))
                 if key]  # fmt: skip
        raise RefusedError(
            "bad_command",
            f"{driver.name} ({driver.kind}) has no follow stream of {values}: "
            + (f"its trajectories move {moves[0]}" if moves else "it plays no trajectory"),
        )
    if speed:
        return Stream(follow, declaration.target_speed_rpm, declaration.speed_rpm, speed=True)
    return Stream(follow, declaration.target, declaration.position, speed=False)


@dataclass(frozen=True, slots=True)
class PathSampler:
    """What a device's bus ticks for its trajectory: the follow payload of its path at each
    moment from the start. Plain values, so that a bus in a worker process is sent a copy
    (docs/workers.md)."""

    path: Path
    follow: str
    speed: bool
    #: The whole counts a position is sent within (its joint's ``raw_limits``).
    limits: tuple[int, int]

    def __call__(self, t_s: float) -> dict[str, Any]:
        return self.payload(self.path.at(t_s))

    def sent(self, value: float) -> float:
        """What goes on the wire for the path's ``value``: a speed as it is, a position the
        nearest whole count inside the joint's limits (``Joint.raw_limits``: the path is
        within the limits, ``checks``, so this only rounds, as ``Joint.target_raw`` does)."""
        if self.speed:
            return value
        low, high = self.limits
        return min(max(sent(value), low), high)

    def payload(self, value: float) -> dict[str, Any]:
        """The follow payload that sends the path's ``value``."""
        return {self.follow: self.sent(value)}


class Gateway(Protocol):
    """What a trajectory needs of its gateway (``busgate.gateway.api.commands.GatewayApi``):
    its name, its devices, each with the runner of its bus, and its count of e-stops."""

    @property
    def name(self) -> str: ...

    @property
    def estops(self) -> int: ...

    @property
    def devices(self) -> Mapping[str, tuple[BusRunner, Driver]]: ...


@dataclass
class Member:
    """One device of a running trajectory."""

    name: str
    runner: BusRunner
    driver: Driver
    path: Path
    stream: Stream
    path_tolerance: float | None  # raw units, as the path
    goal_tolerance: float | None
    claimed: bool  # its client held the device's claim when it started
    #: What its bus ticks.
    sampler: PathSampler = field(init=False)

    def __post_init__(self) -> None:
        joint = self.driver.joint
        self.sampler = PathSampler(
            self.path, self.stream.follow, self.stream.speed, joint.raw_limits
        )

    @property
    def speed(self) -> bool:
        """Its trajectory moves a speed (it ramps to 0 when it leaves), not a position."""
        return self.stream.speed

    def sample(self, t_s: float) -> dict[str, Any]:
        """The follow payload of the path at ``t_s``."""
        return self.sampler(t_s)

    def value(self, t_s: float) -> float:
        """What a tick at ``t_s`` sends."""
        return self.sampler.sent(self.path.at(t_s))

    def payload(self, value: float) -> dict[str, Any]:
        return self.sampler.payload(value)

    def takes(self, value: float) -> bool:
        """Whether the device takes the path's ``value`` as its target."""
        try:
            self.driver.follow_target(self.payload(value))
        except (CommandError, RefusedError):
            return False
        return True

    @property
    def si_unit(self) -> str:
        """The SI unit of its path's values as a joint: its joint's unit, per second for a
        speed."""
        unit = self.driver.joint.unit
        return f"{unit}/s" if self.stream.speed else unit

    def si(self, value: float) -> float:
        """A value of its path (raw) in ``si_unit``."""
        joint = self.driver.joint
        return joint.velocity_si(value) if self.stream.speed else joint.position_si(value)

    def si_difference(self, difference: float) -> float:
        """A difference of two values of its path (raw: an error) in ``si_unit``."""
        joint = self.driver.joint
        return joint.velocity_si(difference) if self.stream.speed else joint.scale * difference

    def measured(self) -> tuple[float, float] | None:
        """(wall time read, value) of the device's last published state."""
        state = self.runner.states.get(self.name) or {}
        field = self.stream.measured
        value, read = (state.get(field) if field else None), state.get("ts")
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
